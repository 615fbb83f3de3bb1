"""Shared pieces of the benchmarks: timing, tables, plots, and the robot of docs/paper-cases.md.

The robot (paper section 6, fixed in docs/paper-cases.md) is built twice, the same way:

- in flexmbs (`robot_flexmbs`), exactly as the robot case cases/robot_2dof.toml does,
  with any number of quadratic 3-node elements per arm;
- in Exudyn (`ExudynRobot`), with ObjectBeamGeometricallyExact2D in its 3-node (quadratic)
  form, NodeRigidBody2D nodes, the same section numbers (taken from flexmbs.Tube so that EA,
  kGA (Cowper), EI, rhoA, rhoI are bit-identical), point masses as ObjectRigidBody2D with zero
  inertia on the arm-end nodes, the pin, hinge and the two absolute rotation drives as
  CoordinateConstraints, gravity as LoadMassProportional, the static equilibrium by its static
  solver (updateInitialValues=True), and its generalized-alpha with rho_inf = 0.5.

Both models have the same 6 (2 n_el + 1) nodal coordinates, the same element and the same
integrator: at equal mesh and step they give the same discrete solution up to the Newton
tolerances (checked by `work_precision.py`, column "|fx - ex|").
"""
from __future__ import annotations

import math
import os
import platform
import statistics
import time
from dataclasses import dataclass

import numpy as np

ARM = 0.6                                  # arm length (m)
THETA1_0 = math.radians(120.0)             # arm 1 w.r.t. ground at t = 0
THETA2_0 = math.radians(-150.0)            # arm 2 w.r.t. arm 1 at t = 0
TIP0 = ARM * math.cos(THETA1_0) + ARM * math.cos(THETA1_0 + THETA2_0)   # x0 = y0 (m)
E_ALU, NU_ALU, RHO_ALU = 72e9, 0.3, 2700.0
GRAVITY = 9.81


# ----------------------------------------------------------------------------- timing
@dataclass
class Timing:
    """Repeated timing of one call: wall-clock and process CPU seconds (min and median)."""
    wall_min: float
    wall_median: float
    cpu_min: float
    cpu_median: float
    runs: int

    @property
    def best(self):
        """The figure the tables use: the smallest process CPU time over the repeats.

        On the shared 2-core machine other processes stretch the wall time of a
        single-threaded run (waiting for a core), not its CPU time; every run here is
        single-threaded (OPENBLAS_NUM_THREADS=1, Exudyn's default of one thread).
        """
        return self.cpu_min


def time_call(fn, repeats=3, budget=2.0, setup=None):
    """Time fn(setup()) (or fn() without setup) up to `repeats` times, fewer once `budget`
    seconds are spent, at least once; setup() is not timed.

    Returns (last result, Timing).
    """
    walls, cpus = [], []
    result = None
    spent = 0.0
    for _ in range(max(1, repeats)):
        arg = setup() if setup is not None else None
        c0, w0 = time.process_time(), time.perf_counter()
        result = fn(arg) if setup is not None else fn()
        w1, c1 = time.perf_counter(), time.process_time()
        walls.append(w1 - w0)
        cpus.append(c1 - c0)
        spent += w1 - w0
        if spent > budget:
            break
    return result, Timing(min(walls), statistics.median(walls), min(cpus), statistics.median(cpus),
                          len(walls))


def machine_summary():
    """One line describing the machine and the thread settings of the run."""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "?")
    except OSError:
        cpu = platform.processor() or "?"
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    return (f"{cpu}, {os.cpu_count()} cores, load average {load:.2f} at start, "
            f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, "
            f"Python {platform.python_version()}, {source_state()}")


def source_state():
    """The git commit of the tree and whether the Fortran core differs from it."""
    import subprocess
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "fortran"], cwd=root,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "git state unknown"
    return f"commit {head or '?'}{' + uncommitted fortran/ changes' if dirty else ''}"


# ----------------------------------------------------------------------------- tables / plots
def format_table(headers, rows, title=None):
    """A plain-text table: headers and rows of already formatted strings (or numbers)."""
    cells = [[str(h) for h in headers]] + [[_fmt(v) for v in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    if title:
        lines.append(title)
    lines.append("  ".join(c.rjust(w) for c, w in zip(cells[0], widths)))
    lines.append("  ".join("-" * w for w in widths))
    for r in cells[1:]:
        lines.append("  ".join(c.rjust(w) for c, w in zip(r, widths)))
    return "\n".join(lines)


def _fmt(v):
    if isinstance(v, str):
        return v
    if v is None:
        return "-"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    if not math.isfinite(v):
        return "-" if math.isnan(v) else str(v)
    if v == 0:
        return "0"
    if 1e-3 <= abs(v) < 1e4:
        return f"{v:.4g}"
    return f"{v:.3e}"


def pyplot():
    """matplotlib.pyplot with a non-interactive backend, or None if matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        return plt
    except ImportError:
        return None


# ----------------------------------------------------------------------------- robot
def tip_path(t):
    """Ideal tip path of eq. (26): (x, y) arrays, x = x0 + D(t), y = y0 + D(t),
    D = (stroke/T)(t - T/(2 pi) sin(2 pi t/T)), T = 0.5 s, stroke 0.5 m."""
    t = np.asarray(t, float)
    period, stroke = 0.5, 0.5
    w = 2 * np.pi / period
    d = stroke / period * (t - np.sin(w * t) / w)
    return TIP0 + d, TIP0 + d


def deviation30(t, tip_xy):
    """Deviation (30) in metres: distance of the tip from the ideal path at every t."""
    x, y = tip_path(t)
    tip_xy = np.asarray(tip_xy, float)
    return np.hypot(tip_xy[:, 0] - x, tip_xy[:, 1] - y)


def robot_geometry():
    """Points O, A and the tip (m) of the initial posture."""
    a = (ARM * math.cos(THETA1_0), ARM * math.sin(THETA1_0))
    tip = (a[0] + ARM * math.cos(THETA1_0 + THETA2_0), a[1] + ARM * math.sin(THETA1_0 + THETA2_0))
    return (0.0, 0.0), a, tip


def section_properties(p=0.05):
    """[EA, kGA, EI, rhoA, rhoI] of the robot's tube (outer diameter p, wall 0.1 p), by flexmbs."""
    import flexmbs as fx
    mat = fx.Material(E=E_ALU, nu=NU_ALU, rho=RHO_ALU)
    return np.asarray(fx.Tube.with_wall_ratio(p, 0.1).properties(mat), float)


def robot_flexmbs(elements_per_arm=2, p=0.05, stiffness_factor=1.0, drive_laws=None):
    """The robot of docs/paper-cases.md in flexmbs: (model, arm1 Body, arm2 Body).

    Quadratic elements, pin + absolute drive at O, hinge + absolute drive of arm 2's root at A,
    2 kg at A, 1 kg at the tip, gravity -y. `stiffness_factor` scales E (robustness tests);
    `drive_laws` = (theta1, theta1 + theta2) TimeLaws (default: the paper's motion).
    """
    import flexmbs as fx
    import sys
    tests = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests")
    if tests not in sys.path:                # the robot's inverse kinematics (left the library)
        sys.path.insert(0, tests)
    from robot_kinematics import robot_joint_laws
    mat = fx.Material(E=E_ALU * stiffness_factor, nu=NU_ALU, rho=RHO_ALU)
    sec = fx.Tube.with_wall_ratio(p, 0.1)
    if drive_laws is None:
        th1, _, th12 = robot_joint_laws()
    else:
        th1, th12 = drive_laws
    o, a, tip = robot_geometry()
    m = fx.Model("robot")
    a1 = m.add_beam("arm1", o, a, elements_per_arm, material=mat, section=sec)
    a2 = m.add_beam("arm2", a, tip, elements_per_arm, material=mat, section=sec)
    m.pin(a1.first)
    m.drive_rotation(a1.first, th1)
    m.hinge(a1.last, a2.first)
    m.drive_rotation(a2.first, th12)
    m.add_point_mass(a1.last, 2.0)
    m.add_point_mass(a2.last, 1.0)
    m.set_gravity(0.0, -GRAVITY)
    return m, a1, a2


def exudyn_available():
    """(True, version) if Exudyn imports, else (False, the reason)."""
    try:
        import exudyn
        return True, exudyn.__version__
    except Exception as exc:   # ImportError, or a broken binary wheel
        return False, f"{type(exc).__name__}: {exc}"


def _symbolic_drive(which):
    """Exudyn symbolic (C++-evaluated) offset of drive `which` (1: theta1, 12: theta1+theta2)
    w.r.t. its value at t = 0, i.e. the planar inverse kinematics of eq. (26), elbow down."""
    import exudyn as exu
    esym = exu.symbolic
    w = 4.0 * math.pi                        # 2 pi / T, T = 0.5 s; stroke / T = 1

    def offset(mbs, t, itemNumber, lOffset):
        x = TIP0 + (t - esym.sin(w * t) / w)                      # x = y on this path
        c2 = (2.0 * x * x - 2.0 * ARM * ARM) / (2.0 * ARM * ARM)
        th2 = -esym.acos(c2)
        th1 = esym.atan2(x, x) - esym.atan2(ARM * esym.sin(th2), ARM + ARM * esym.cos(th2))
        if which == 1:
            return th1 - THETA1_0
        return th1 + th2 - (THETA1_0 + THETA2_0)
    return offset


def _python_drive(which):
    """The same offsets as plain Python user functions (slower: one Python call each)."""
    w = 4.0 * math.pi

    def offset(mbs, t, itemNumber, lOffset):
        x = TIP0 + (t - math.sin(w * t) / w)
        c2 = (2.0 * x * x - 2.0 * ARM * ARM) / (2.0 * ARM * ARM)
        th2 = -math.acos(max(-1.0, min(1.0, c2)))
        th1 = math.atan2(x, x) - math.atan2(ARM * math.sin(th2), ARM + ARM * math.cos(th2))
        if which == 1:
            return th1 - THETA1_0
        return th1 + th2 - (THETA1_0 + THETA2_0)
    return offset


class ExudynFailed(RuntimeError):
    """Exudyn's solver stopped (Newton failure with adaptive steps off, or a failed static)."""


class ExudynRobot:
    """The robot of docs/paper-cases.md in Exudyn; one instance per simulation (Exudyn keeps state).

    Parameters
    ----------
    elements_per_arm : int
        Quadratic 3-node ObjectBeamGeometricallyExact2D elements per arm.
    p : float, default 0.05
        Outer tube diameter (m).
    drives : {'symbolic', 'python'}, default 'symbolic'
        Drive laws as Exudyn symbolic user functions (evaluated in C++) or Python callbacks.
    """

    def __init__(self, elements_per_arm=2, p=0.05, drives="symbolic"):
        import exudyn as exu
        from exudyn import itemInterface as ii
        from exudyn.advancedUtilities import CreateSymbolicUserFunction
        self.exu = exu
        ea, kga, ei, rhoa, rhoi = section_properties(p)
        sc = exu.SystemContainer()
        mbs = sc.AddSystem()
        self._sc, self.mbs = sc, mbs
        nel = int(elements_per_arm)
        o, a, tip = robot_geometry()
        arms = []
        gvec = [0.0, -GRAVITY, 0.0]
        for p0, p1 in ((o, a), (a, tip)):
            phi = math.atan2(p1[1] - p0[1], p1[0] - p0[0])
            npts = 2 * nel + 1
            nodes = []
            for k in range(npts):
                s = k / (npts - 1)
                nodes.append(mbs.AddNode(ii.NodeRigidBody2D(
                    referenceCoordinates=[p0[0] + (p1[0] - p0[0]) * s, p0[1] + (p1[1] - p0[1]) * s, phi])))
            for e in range(nel):
                ob = mbs.AddObject(ii.ObjectBeamGeometricallyExact2D(
                    nodeNumbers=nodes[2 * e:2 * e + 3], length=ARM / nel, massPerLength=rhoa,
                    crossSectionInertia=rhoi, bendingStiffness=ei, axialStiffness=ea,
                    shearStiffness=kga, visualization=ii.VObjectBeamGeometricallyExact2D(show=False)))
                mk = mbs.AddMarker(ii.MarkerBodyMass(bodyNumber=ob))
                mbs.AddLoad(ii.LoadMassProportional(markerNumber=mk, loadVector=gvec))
            arms.append(nodes)
        a1, a2 = arms
        for node, mass in ((a1[-1], 2.0), (a2[-1], 1.0)):
            ob = mbs.AddObject(ii.ObjectRigidBody2D(nodeNumber=node, mass=mass, inertia=0.0,
                                                    visualization=ii.VObjectRigidBody2D(show=False)))
            mk = mbs.AddMarker(ii.MarkerBodyMass(bodyNumber=ob))
            mbs.AddLoad(ii.LoadMassProportional(markerNumber=mk, loadVector=gvec))
        ground = mbs.AddNode(ii.NodePointGround())
        mg = mbs.AddMarker(ii.MarkerNodeCoordinate(nodeNumber=ground, coordinate=0))

        def coord(n, c):
            return mbs.AddMarker(ii.MarkerNodeCoordinate(nodeNumber=n, coordinate=c))
        for c in (0, 1):
            mbs.AddObject(ii.CoordinateConstraint(markerNumbers=[mg, coord(a1[0], c)]))         # pin O
            mbs.AddObject(ii.CoordinateConstraint(markerNumbers=[coord(a1[-1], c), coord(a2[0], c)]))  # hinge A
        # drives: plain zero offset for the static solve (drive positions at t = 0), the
        # time law is attached after it
        self._drives = [mbs.AddObject(ii.CoordinateConstraint(markerNumbers=[mg, coord(a1[0], 2)])),
                        mbs.AddObject(ii.CoordinateConstraint(markerNumbers=[mg, coord(a2[0], 2)]))]
        self._drive_kind = drives
        self._keep = []
        if drives == "symbolic":
            for obj, which in zip(self._drives, (1, 12)):
                f = CreateSymbolicUserFunction(mbs, _symbolic_drive(which), "offsetUserFunction",
                                               itemTypeName="ObjectConnectorCoordinate")
                self._keep.append(f)
        elif drives == "python":
            self._keep = [_python_drive(1), _python_drive(12)]
        else:
            raise ValueError(f"drives must be 'symbolic' or 'python', got {drives!r}")
        self.sensor = mbs.AddSensor(ii.SensorNode(nodeNumber=a2[-1], storeInternal=True, writeToFile=False,
                                                  outputVariableType=exu.OutputVariableType.Position))
        self.tip_node = a2[-1]
        mbs.Assemble()
        self.ode2 = mbs.systemData.ODE2Size()
        self.ae = mbs.systemData.AEsize()
        self.stats = {}

    def settings(self, h, t_end, rho_inf=0.5, modified_newton=False, sparse=False, rtol=1e-8,
                 static_rtol=1e-6, adaptive=False):
        """Exudyn SimulationSettings of a generalized-alpha run with steps h: fixed, or with
        adaptive=True under Exudyn's own step control (its default adaptiveStep: a step whose
        Newton iteration fails is cut by adaptiveStepDecrease and regrown later)."""
        exu = self.exu
        ss = exu.SimulationSettings()
        ss.solutionSettings.writeSolutionToFile = False
        ss.solutionSettings.sensorsWritePeriod = h
        ss.displayComputationTime = False
        ss.displayStatistics = False
        ss.staticSolver.verboseMode = 0
        ss.timeIntegration.verboseMode = 0
        ss.linearSolverType = exu.LinearSolverType.EigenSparse if sparse else exu.LinearSolverType.EXUdense
        ss.timeIntegration.generalizedAlpha.spectralRadius = rho_inf
        ss.timeIntegration.newton.useModifiedNewton = bool(modified_newton)
        ss.timeIntegration.newton.relativeTolerance = rtol
        # fixed steps (a failure is reported), or Exudyn's own step control
        ss.timeIntegration.adaptiveStep = bool(adaptive)
        ss.timeIntegration.numberOfSteps = int(round(t_end / h))
        ss.timeIntegration.endTime = ss.timeIntegration.numberOfSteps * h
        # Exudyn's default static tolerance (1e-8 of the initial residual) sits below the
        # round-off floor of this stiff model from 8 elements per arm on (1e-6 works up to 32,
        # 1e-4 at 128 elements per arm); Newton converges quadratically, so the state is far
        # more accurate than the criterion: see the column |fx - ex| of work_precision.py
        ss.staticSolver.newton.relativeTolerance = static_rtol
        return ss

    def run(self, ss):
        """Static equilibrium at t = 0, then the dynamic run; returns (t, tip (nt, 2)).

        Only this method is timed by the benchmarks (model building and Assemble are not).
        """
        exu = self.exu
        exu.SetWriteToConsole(False)      # a failure is reported by the exception below
        try:
            return self._run(ss)
        finally:
            exu.SetWriteToConsole(True)

    def _run(self, ss):
        import warnings
        mbs = self.mbs
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                ok = mbs.SolveStatic(ss, updateInitialValues=True)
            except Exception as exc:
                raise ExudynFailed(f"static solver: {exc}") from None
            if not ok:
                raise ExudynFailed("static solver failed")
            for obj, f in zip(self._drives, self._keep):
                mbs.SetObjectParameter(obj, "offsetUserFunction", f)
            try:
                ok = mbs.SolveDynamic(ss)
            except Exception as exc:
                raise ExudynFailed(f"dynamic solver: {exc}") from None
            if not ok:
                raise ExudynFailed("dynamic solver failed")
        it = mbs.sys["dynamicSolver"].it
        self.stats = dict(steps=int(it.currentStepIndex), newton_iterations=int(it.newtonStepsCount),
                          jacobians=int(it.newtonJacobiCount))
        data = mbs.GetSensorStoredData(self.sensor)
        return data[:, 0], data[:, 1:3]
