"""The weakly coupled method: equivalent static loads and static optimization in cycles (paper 5.3).

One cycle: MBS analysis of the current design -> ESL of every body (paper 3.3,
`flexmbs.esl`) -> test of eq. (25) -> static multi-load-case optimization (23) with the ESL
held fixed -> next design. The static problem minimizes the beam mass subject to the
component form of the case's deviation constraint at every time step:

* formulation (28) of the robot: eq. (29), ((R1 u1_A)_y)^2 + ((R2 u2_tip)_y)^2 <= limit^2;
* formulation (30): eq. (31), |R1 u1_A + R2 u2_tip|^2 <= limit^2;
* formulation (33) of the four-bar (loop opened at A): eq. (34) |R1 u1_A|^2 <= limit^2 and
  eq. (35) |R2 u2_A + R3 u3_B|^2 <= limit^2, frames crank at O, coupler at B, follower at C,

with u^b_n = K^b(p)^-1 g_eq,n^b, the displacement of the body's far end (the end opposite its
frame node). The squared form avoids the kink of the square root where the deviation
vanishes. Gradients are analytic, du/dp = -K^-1 (dK/dp) u, one factorization per body per
design for all load cases. The optimizer is scipy's SLSQP; its iterations are the "inner
iterations".

Beyond the paper's algorithm: convergence of eq. (25) is confirmed over `confirm_cycles`
more cycles (the test can fire on an unstable fixed point), an oscillation between designs
(the paper's Table 5) is detected and reported, optional move limits bound the design change
per cycle, and the final design's deviation in the full dynamic simulation is reported beside
the one the static model predicted.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from flexmbs.cases import as_case
from flexmbs.errors import CaseError, ModelError
from flexmbs.sections import real_number, whole_number
from flexmbs.esl import (BodyStiffness, ChordFrame, TangentFrame, equivalent_static_loads,
                         esl_change, static_response)
from flexmbs.optimize.result import HistoryWriter, OptimizationResult

__all__ = ["ComponentConstraint", "component_constraints", "StaticProblem", "StaticOptimum",
           "optimize_weakly"]


# ---------------------------------------------------------------------------- constraints
@dataclass(frozen=True)
class ComponentConstraint:
    """A deviation constraint written with body-frame displacements.

    dl_n^2 = sum over terms (bodies, components) of
             sum_{c in components} ( sum_{b in bodies} (R_0,n^b u_n,end^b)_c )^2  <= limit^2,

    where u_n,end^b is the local displacement of body b's far end and c = 0 (x), 1 (y).

    Attributes
    ----------
    name : e.g. 'eq29'.
    terms : tuple of (tuple of body names, tuple of components).
    """
    name: str
    terms: tuple


def component_constraints(formulation, body_names):
    """The component constraints of a deviation formulation (paper eqs. 29, 31, 34-35).

    Parameters
    ----------
    formulation : '28', '30' or '33' (the case's deviation measure).
    body_names : the ESL bodies in the case's order (robot: arm 1, arm 2; four-bar: crank,
        coupler, follower).
    """
    f = str(formulation)
    names = list(body_names)
    if f in ("28", "37"):
        _need(names, 2, f)
        return [ComponentConstraint("eq29", (((names[0],), (1,)), ((names[1],), (1,))))]
    if f == "30":
        _need(names, 2, f)
        return [ComponentConstraint("eq31", (((names[0], names[1]), (0, 1)),))]
    if f == "33":
        _need(names, 3, f)
        return [ComponentConstraint("eq34", (((names[0],), (0, 1)),)),
                ComponentConstraint("eq35", (((names[1], names[2]), (0, 1)),))]
    raise CaseError(f"the weakly coupled method has no component form of deviation formulation "
                    f"{formulation!r} (known: '28', '30', '33')")


def _need(names, n, f):
    if len(names) != n:
        raise CaseError(f"deviation formulation {f} needs {n} ESL bodies, the case gives "
                        f"{len(names)}: {names}")


def _far_end(body, frame_node):
    """The body's end node opposite the frame node."""
    return body.last if frame_node == body.first else body.first


# ---------------------------------------------------------------------------- static problem
class StaticProblem:
    """The static multi-load-case problem (23) for one set of ESL.

    Parameters
    ----------
    case : Case (design -> element properties and derivatives, mass).
    loads : EquivalentStaticLoads of the cycle.
    constraints : list of ComponentConstraint.
    end_nodes : dict body name -> node whose displacement enters the constraints.
    limit : deviation limit (m).
    """

    def __init__(self, case, loads, constraints, end_nodes, limit):
        self.case = case
        self.loads = loads
        self.constraints = list(constraints)
        self.limit = float(limit)
        self.nt = len(loads.bodies[0].t)
        self._body = {}
        for b in loads:
            ks = b.stiffness
            k = ks.nodes.index(end_nodes[b.name])
            cols = []
            for d in (3 * k, 3 * k + 1):
                hit = np.flatnonzero(ks.free == d)
                cols.append(int(hit[0]) if hit.size else -1)   # -1: held by the frame (zero)
            self._body[b.name] = dict(ks=ks, g=b.g_eq, c=np.cos(b.angle), s=np.sin(b.angle),
                                      cols=cols)

    def _props(self, p):
        model = self.case.build_model(np.asarray(p, float))
        return model.element_properties(), self.case.element_property_derivatives(p)

    def end_displacements(self, p, gradient=False):
        """Inertial components R_0,n u_n,end of every body: dict name -> (w (nt, 2),
        dw (nv, nt, 2) or None)."""
        props, dprops = self._props(p)
        out = {}
        for name, d in self._body.items():
            cols = [c for c in d["cols"] if c >= 0]
            u, du = static_response(d["ks"], d["g"], props, cols, dprops if gradient else None)
            loc = np.zeros((self.nt, 2))
            dloc = np.zeros((dprops.shape[2], self.nt, 2)) if gradient else None
            k = 0
            for j, col in enumerate(d["cols"]):
                if col >= 0:
                    loc[:, j] = u[:, k]
                    if gradient:
                        dloc[:, :, j] = du[:, :, k]
                    k += 1
            c, s = d["c"], d["s"]
            w = np.column_stack([c * loc[:, 0] - s * loc[:, 1], s * loc[:, 0] + c * loc[:, 1]])
            dw = None
            if gradient:
                dw = np.stack([c * dloc[:, :, 0] - s * dloc[:, :, 1],
                               s * dloc[:, :, 0] + c * dloc[:, :, 1]], axis=-1)
            out[name] = (w, dw)
        return out

    def squared_deviations(self, p, gradient=False):
        """dl_n^2 of every constraint: (ncon, nt), and d(dl^2)/dp (ncon, nt, nv) if asked."""
        ends = self.end_displacements(p, gradient)
        ncon = len(self.constraints)
        nv = len(np.atleast_1d(p))
        val = np.zeros((ncon, self.nt))
        grad = np.zeros((ncon, self.nt, nv)) if gradient else None
        for i, con in enumerate(self.constraints):
            for bodies, comps in con.terms:
                v = sum(ends[b][0] for b in bodies)
                for cc in comps:
                    val[i] += v[:, cc] ** 2
                    if gradient:
                        dv = sum(ends[b][1][:, :, cc] for b in bodies)      # (nv, nt)
                        grad[i] += 2.0 * v[:, cc][:, None] * dv.T
        return val, grad


@dataclass
class StaticOptimum:
    """Outcome of one static optimization (23)."""
    design_mm: np.ndarray
    mass_kg: float
    iterations: int
    success: bool
    message: str
    predicted_max_deviation_m: float
    active_steps: dict
    screened_steps: int


def _optimize_static(problem, case, p0, lower, upper, *, screen, ftol, maxiter, active_tol):
    """Solve (23) with SLSQP on x = p / upper (mm / mm), objective m / m(p0)."""
    scale = np.asarray(case.upper_mm, float)
    m0 = float(case.mass(p0))
    lim2 = problem.limit ** 2
    cache = {}

    def evaluate(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = problem.squared_deviations(x * scale, gradient=True)
        return cache[key]

    def objective(x):
        p = x * scale
        return float(case.mass(p)) / m0, np.asarray(case.mass_gradient(p), float) * scale / m0

    def select(val, current):
        dl = np.sqrt(np.maximum(val, 0.0))
        mx = dl.max(axis=1, keepdims=True)
        keep = dl >= screen * mx
        return keep | current

    x = np.clip(np.asarray(p0, float), lower, upper) / scale
    bounds = list(zip(lower / scale, upper / scale))
    val0, _ = problem.squared_deviations(x * scale)
    keep = select(val0, np.zeros_like(val0, bool))
    nit = 0
    res = None
    for _ in range(20):
        idx = np.nonzero(keep)

        def cons(x, idx=idx):
            return 1.0 - evaluate(x)[0][idx] / lim2

        def cons_jac(x, idx=idx):
            return -(evaluate(x)[1][idx[0], idx[1], :] * scale) / lim2

        res = minimize(objective, x, jac=True, method="SLSQP", bounds=bounds,
                       constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}],
                       options=dict(ftol=ftol, maxiter=maxiter))
        nit += int(res.nit)
        x = np.clip(res.x, [b[0] for b in bounds], [b[1] for b in bounds])
        val, _ = problem.squared_deviations(x * scale)
        violated = (val > lim2 * (1 + 1e-6)) & ~keep
        if not violated.any():
            break
        keep = select(val, keep)
    p = x * scale
    val, _ = problem.squared_deviations(p)
    dl = np.sqrt(np.maximum(val, 0.0))
    active = {c.name: (np.flatnonzero(dl[i] >= (1 - active_tol) * problem.limit) + 1).tolist()
              for i, c in enumerate(problem.constraints)}
    return StaticOptimum(design_mm=p, mass_kg=float(case.mass(p)), iterations=nit,
                         success=bool(res.success), message=str(res.message),
                         predicted_max_deviation_m=float(dl.max()), active_steps=active,
                         screened_steps=int(keep.sum()))


# ---------------------------------------------------------------------------- cycles
def _oscillation(designs, changes, period_max=6, ratio=0.2):
    """Period of a repeating pattern in the last designs (2..period_max) or None.

    A period P is reported when each of the last two designs is much closer to the design P
    cycles before it than to its predecessor (distance ratio < `ratio`) and the ESL change
    of eq. (25) has not decreased over the period (a slowly converging alternation is not
    reported).
    """
    for P in range(2, period_max + 1):
        if len(designs) < P + 2 or changes[-1 - P] is None:
            continue
        ok = changes[-1] >= 0.5 * changes[-1 - P]
        for k in (len(designs) - 1, len(designs) - 2):
            back = np.linalg.norm(designs[k] - designs[k - P])
            step = np.linalg.norm(designs[k] - designs[k - 1])
            if step == 0 or back >= ratio * step:
                ok = False
                break
        if ok:
            return P
    return None


def check_cycle_options(eps, max_cycles, confirm_cycles, max_inner, ftol, active_tol,
                        move_limit, screen):
    """The weakly coupled method's numeric options, checked (ModelError naming the option)."""
    eps = real_number("eps", eps, positive=True)
    max_cycles = whole_number("max_cycles", max_cycles, 1)
    confirm_cycles = whole_number("confirm_cycles", confirm_cycles, 0)
    max_inner = whole_number("max_inner", max_inner, 1)
    ftol = real_number("ftol", ftol, positive=True)
    active_tol = real_number("active_tol", active_tol, positive=True)
    if move_limit is not None:
        move_limit = real_number("move_limit (or None)", move_limit, positive=True)
    if not (real_number("screen", screen) >= 0.0 and screen <= 1.0):
        raise ModelError(f"screen must lie in [0, 1], got {screen!r}")
    return eps, max_cycles, confirm_cycles, max_inner, ftol, active_tol, move_limit, screen


def move_limited_bounds(x, lower, upper, move_limit):
    """The bounds of the next static optimization: the variables' bounds, narrowed to
    x (1 -/+ move_limit) when a relative move limit is given."""
    if move_limit is None:
        return lower.copy(), upper.copy()
    return np.maximum(lower, x * (1 - move_limit)), np.minimum(upper, x * (1 + move_limit))


class CycleControl:
    """The stopping decisions of the weakly coupled cycles: eq. (25) below eps in
    1 + confirm_cycles consecutive cycles (converged), the designs repeating (oscillation,
    see `_oscillation`), the cycle cap. Shared by the paper-case and the general-problem loops.

    Attributes: designs, changes (one per cycle), converged, reason, period (oscillation
    period or None), paper_cycle (first cycle of the current run of eq. (25) below eps)."""

    def __init__(self, eps, confirm_cycles, max_cycles, stop_on_oscillation):
        self.eps, self.confirm_cycles = eps, confirm_cycles
        self.max_cycles, self.stop_on_oscillation = max_cycles, stop_on_oscillation
        self.designs, self.changes = [], []
        self.consecutive, self.paper_cycle = 0, None
        self.converged, self.reason, self.period = False, "", None

    def observe(self, cycle, design, change, record):
        """Take a cycle's design and ESL change; an oscillation is noted in `record`."""
        self.designs.append(np.array(design, float).copy())
        self.changes.append(change)
        if change is not None and change < self.eps:
            self.consecutive += 1
            if self.paper_cycle is None:
                self.paper_cycle = cycle
        else:
            self.consecutive, self.paper_cycle = 0, None
        if self.consecutive > self.confirm_cycles:
            self.converged = True
            self.reason = (f"relative ESL change (eq. 25) {change:.3g} < {self.eps:g} in "
                           f"{self.consecutive} consecutive cycles")
        elif change is not None:
            self.period = _oscillation(self.designs, self.changes)
            if self.period is not None:
                record["oscillation_period"] = self.period

    def stop(self, cycle):
        """Whether the cycles end after this one (`reason` says why)."""
        if self.converged:
            return True
        if self.period is not None and self.stop_on_oscillation:
            self.reason = (f"oscillation: the designs repeat with period {self.period} cycles "
                           f"(eq. 25 change {self.changes[-1]:.3g})")
            return True
        if cycle == self.max_cycles:
            self.reason = f"maximum number of cycles ({self.max_cycles}) reached"
            return True
        return False


def _progress_callback(progress):
    """None or False: no progress reports; else a callable taking one history record."""
    if progress is None or progress is False:
        return None
    if not callable(progress):
        raise ModelError(f"progress must be a callable taking one history record, or None/False, "
                         f"got {progress!r}")
    return progress


def optimize_weakly(case, start_mm=None, *, eps=1e-2, max_cycles=30, confirm_cycles=1,
                    move_limit=None, frame="tangent", screen=0.3, ftol=1e-8, max_inner=200,
                    active_tol=1e-3, stop_on_oscillation=True, history=None, progress=None,
                    simulate_kw=None):
    """Optimize a case with the weakly coupled method (paper 5.3).

    Parameters
    ----------
    case : flexmbs.cases.Case, or a case name, path or dict (then loaded with load_case)
    start_mm : array, optional
        Starting design (mm); default `case.start_mm`.
    eps : float, default 1e-2
        Tolerance of the relative ESL change, eq. (25) (the largest over the bodies).
    max_cycles : int, default 30
        Maximum number of cycles (MBS analyses).
    confirm_cycles : int, default 1
        Eq. (25) must hold in 1 + confirm_cycles consecutive cycles (0: the paper's test).
    move_limit : float, optional
        Relative move limit per cycle: the static problem's bounds are clipped to
        p (1 -+ move_limit). Default: none.
    frame : {'tangent', 'chord'}, default 'tangent'
        Corotational frame of every body, at the case's frame node (`case.esl_bodies`);
        'chord' runs from that node to the body's far end.
    screen : float in [0, 1], default 0.3
        The static problem starts with the time steps whose deviation is at least `screen`
        times the current maximum of its constraint (0: all steps); steps found violated
        at its solution are added and the problem solved again.
    ftol : float, default 1e-8
        SLSQP's tolerance (objective normalized by the cycle's starting mass).
    max_inner : int, default 200
        SLSQP iterations per static problem.
    active_tol : float, default 1e-3
        A time step counts as active when its deviation is >= (1 - active_tol) limit.
    stop_on_oscillation : bool, default True
        Stop when the designs repeat with a period of 2 to 6 cycles (reason 'oscillation').
    history : str, path or HistoryWriter, optional
        File receiving one JSON line per cycle as the run goes.
    progress : callable, optional
        Called with each history record.
    simulate_kw : dict, optional
        Extra keyword arguments of `case.simulate`.

    Returns
    -------
    OptimizationResult
        method 'weakly'; iterations = cycles (MBS analyses); inner_iterations = SLSQP
        iterations summed; details: predicted_max_deviation_m (the static model's maximum
        deviation of the final design), paper_test_cycle (the cycle at which eq. (25) first
        held), static_optimizations, oscillation_period, esl_change.
    """
    t_start = time.perf_counter()
    case = as_case(case, "optimize_weakly: case")
    lower = np.asarray(case.lower_mm, float)
    upper = np.asarray(case.upper_mm, float)
    p = case.start_design(start_mm).copy()
    eps, max_cycles, confirm_cycles, max_inner, ftol, active_tol, move_limit, screen = \
        check_cycle_options(eps, max_cycles, confirm_cycles, max_inner, ftol, active_tol,
                            move_limit, screen)
    if not isinstance(frame, str) or frame not in ("tangent", "chord"):
        raise ModelError(f"frame must be 'tangent' or 'chord', got {frame!r}")
    progress = _progress_callback(progress)
    if simulate_kw is not None and not isinstance(simulate_kw, dict):
        raise ModelError(f"simulate_kw must be a dict of simulate's keyword arguments or None, "
                         f"got {simulate_kw!r}")
    sim_kw = dict(simulate_kw or {})
    sim_kw.setdefault("store", "all")

    writer = history if isinstance(history, HistoryWriter) else HistoryWriter(history)
    own_writer = not isinstance(history, HistoryWriter)

    model = case.build_model(p)
    bodies = getattr(case, "esl_bodies", None)
    if not bodies:
        raise CaseError(f"case {getattr(case, 'name', case)!r} defines no ESL bodies (esl_bodies): "
                        "the weakly coupled method needs the bodies and their frame nodes")
    frames, stiffness, end_nodes = [], {}, {}
    for name, node in bodies:
        body = model.body(name)
        end = _far_end(body, node)
        fr = TangentFrame(node) if frame == "tangent" else ChordFrame(node, end)
        frames.append((name, fr))
        stiffness[name] = BodyStiffness(model, body, fr)
        end_nodes[name] = end
    constraints = component_constraints(case.formulation, [n for n, _ in frames])

    prev_loads = None
    control = CycleControl(eps, confirm_cycles, max_cycles, stop_on_oscillation)
    pending = None            # the static optimum that produced the current design
    inner_total = 0
    n_static = 0
    cr = None
    change = None
    try:
        for cycle in range(1, max_cycles + 1):
            cr = case.simulate(p, **sim_kw)
            model = case.build_model(p)
            loads = equivalent_static_loads(model, cr.result, frames, stiffness=stiffness,
                                            props=model.element_properties())
            changes = None if prev_loads is None else esl_change(loads, prev_loads)
            change = None if changes is None else max(changes.values())
            dev = np.asarray(cr.deviation)
            record = dict(
                iteration=cycle, design_mm=p, mass_kg=float(case.mass(p)),
                max_deviation_m=float(dev.max()), t_at_max_s=float(cr.t[int(np.argmax(dev))]),
                esl_change=change, esl_change_per_body=changes,
                inner_iterations=None if pending is None else pending.iterations,
                predicted_max_deviation_m=None if pending is None else pending.predicted_max_deviation_m,
                active_steps=None if pending is None else pending.active_steps,
                static_message=None if pending is None or pending.success else pending.message,
                simulation_active_steps=(np.flatnonzero(dev >= (1 - active_tol) * case.limit_m)
                                         + 1).tolist())
            control.observe(cycle, p, change, record)
            writer.write(record)
            if progress is not None:
                progress(writer.records[-1])
            if control.stop(cycle):
                break
            lo, hi = move_limited_bounds(p, lower, upper, move_limit)
            problem = StaticProblem(case, loads, constraints, end_nodes, case.limit_m)
            pending = _optimize_static(problem, case, p, lo, hi, screen=screen, ftol=ftol,
                                       maxiter=max_inner, active_tol=active_tol)
            inner_total += pending.iterations
            n_static += 1
            prev_loads = loads
            p = pending.design_mm.copy()
    finally:
        if own_writer:
            writer.close()
    dev = np.asarray(cr.deviation)
    details = dict(
        predicted_max_deviation_m=None if pending is None else pending.predicted_max_deviation_m,
        paper_test_cycle=control.paper_cycle, static_optimizations=n_static,
        oscillation_period=control.period, esl_change=change, eps=eps,
        confirm_cycles=confirm_cycles, move_limit=move_limit, frame=frame,
        formulation=str(case.formulation),
        t_end=float(cr.t[-1]), active_steps=None if pending is None else pending.active_steps,
        simulation_active_steps=writer.records[-1]["simulation_active_steps"])
    return OptimizationResult(
        method="weakly", case=getattr(case, "name", "case"), design_mm=p.copy(),
        mass_kg=float(case.mass(p)), iterations=len(control.designs),
        inner_iterations=inner_total, simulations=len(control.designs),
        converged=control.converged, reason=control.reason,
        history=list(writer.records), max_deviation_m=float(dev.max()),
        wall_time_s=time.perf_counter() - t_start, start_mm=control.designs[0],
        details=details, t=np.asarray(cr.t), deviation=dev)
