"""simulate(model, ...) and its Result object."""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from flexmbs.analysis.settings import (DesignDerivatives, InitialConditions, RunSettings,
                                       SimulationSettings)
from flexmbs.analysis.settings import check_flag as _check_flag
from flexmbs.analysis.validity import apply_validity, check_result, diagnose_failure
from flexmbs.core import (SolverStatus, Status, core_model_args, klu_analysis, run_interruptible,
                          simulate_arrays, system_matrices)
from flexmbs.errors import ModelError, ResourceError, SettingWarning, SimulationError
from flexmbs.model.arrays import Model
from flexmbs.model.kinematics import drive_velocities
from flexmbs.model.sections import has_complex
from flexmbs.resources import time_steps
from flexmbs.resources import check_memory, estimate_memory, format_bytes

__all__ = ["simulate", "Result", "DENSE_MAX_UNKNOWNS", "NEWTON_MODES", "time_grid",
           "system_matrices", "core_model_args", "newton_mode", "stored_dofs", "memory_estimate",
           "interpolation_matrix", "step_grid"]

#: Largest system solved with dense LU when solver="auto" (KLU above). benchmarks/scaling.py
#: measured KLU faster than LAPACK's dense LU at every size from 18 unknowns up (1.5x at 18,
#: 2x at 54, 8x at 198, with or without Jacobian reuse), so "auto" always takes KLU.
DENSE_MAX_UNKNOWNS = 0

_SOLVERS = {"dense": 1, "klu": 2}

#: Newton strategies of `simulate` (codes of the core, generalized_alpha.f90 NEWTON_*).
NEWTON_MODES = {"full": 0, "reuse": 1, "auto": 2}


#: Largest refinement of the laws' table under a non-uniform step grid (law_times).
LAW_REFINE = 16


def step_grid(steps, t_end):
    """The times (n + 1,) of a non-uniform step grid `steps` (simulate's keyword): finite,
    strictly increasing from 0 to t_end (its last time set to t_end exactly), or a
    ModelError naming what is wrong."""
    tg = np.asarray(steps, float) if not isinstance(steps, (str, bytes)) else None
    if tg is None or tg.ndim != 1 or tg.size < 2 or not np.all(np.isfinite(tg)):
        raise ModelError(f"steps must be a finite 1-D array of at least 2 times (s), got "
                         f"{steps!r:.80}")
    if tg[0] != 0.0 or abs(tg[-1] - t_end) > 1e-9 * max(1.0, t_end) or np.any(np.diff(tg) <= 0):
        raise ModelError(f"steps must increase strictly from 0 to t_end = {t_end:g} s, got "
                         f"times from {tg[0]:g} to {tg[-1]:g} s (smallest step "
                         f"{np.diff(tg).min():g} s)")
    tg = tg.copy()
    tg[-1] = t_end
    return tg


def law_times(h, nsteps, steps=None):
    """(times, k) of the grid the time laws are tabulated on (the core interpolates them
    between its points by cubic Hermite, exact at the points): the output grid j h (k = 1),
    or with a non-uniform step grid `steps` the grid of spacing h / k, k the least power of
    two with h / k no longer than its shortest step, at most LAW_REFINE (its points every
    k-th a time of the output grid): a law with a kink (samples, a ramp's end) is then
    followed as closely as by a fixed step h / k."""
    if steps is None:
        return h * np.arange(nsteps + 1), 1
    k = 1
    while h / k > float(np.diff(steps).min()) * (1 + 1e-9) and k < LAW_REFINE:
        k *= 2
    return (h / k) * np.arange(nsteps * k + 1), k


def interpolation_matrix(tg, t):
    """(t.size, tg.size) sparse matrix W of the cubic Lagrange interpolation through the 4
    step-grid points around each time of t (fewer when the grid has fewer; one-sided at the
    ends): values on the grid tg (rows) to values at t, W @ y. A time of t that is a grid
    time takes the grid value exactly. Linear in the grid values alone, with weights
    independent of the design: the design derivatives on the grid and the adjoint's seeds
    (W^T) map by the same matrix. Its error, O(H^4) for smooth values on steps H, is below
    generalized-alpha's O(H^2)."""
    from scipy.sparse import csr_matrix

    tg = np.asarray(tg, float)
    t = np.asarray(t, float)
    n = tg.size
    k = min(4, n)
    i = np.clip(np.searchsorted(tg, t, side="right") - 1, 0, n - 2)
    start = np.clip(i - (k // 2 - 1), 0, n - k)
    nodes = start[:, None] + np.arange(k)[None, :]
    x = tg[nodes]
    w = np.ones((t.size, k))
    for a in range(k):
        for b in range(k):
            if a != b:
                w[:, a] *= (t - x[:, b]) / (x[:, a] - x[:, b])
    hit = np.abs(t[:, None] - x) <= 1e-12 * max(1.0, float(tg[-1]))
    exact = hit.any(axis=1)
    w[exact] = hit[exact].astype(float)
    return csr_matrix((w.ravel(), (np.repeat(np.arange(t.size), k), nodes.ravel())),
                      shape=(t.size, n))


def time_grid(t_end, h, memory_limit=None):
    """Number of steps and time grid t_j = j h, j = 0..n; t_end must be a multiple of h.

    The step count is checked before the grid is built (see `time_steps`)."""
    nsteps = time_steps(t_end, h, memory_limit)
    return nsteps, h * np.arange(nsteps + 1)


@dataclass
class Result:
    """The outcome of a simulation.

    Attributes
    ----------
    t : (nt,) time grid.
    q, qd, qdd : (nt, nout) stored coordinates, velocities, accelerations; columns follow `dofs`.
    mu : (nt, nc) constraint forces (physical multipliers k*lambda of eq. 1), row order of the model.
    dofs : (nout,) stored coordinates (0-based indices of q).
    stats : newton_iterations, factorizations, residual_evaluations, step_cuts,
        static_iterations, steps, sensitivity_factorizations (of the factorizations, those
        made for the derivative solves), symbolic_analyses (KLU's symbolic analyses of the
        pattern made by the run: 0, the model's one being borrowed,
        flexmbs.core.KluAnalysis), solver, unknowns, newton (the strategy), memory_estimate
        (bytes: the estimate checked against the memory limit before the run).
    wall_time : seconds spent in the simulation (including the set-up in Python).
    validity : flexmbs.analysis.validity.Validity, the checks run after the simulation (strains of the
        beams, constraint drift, energy of a free system); see SimulationSettings.validity.
    sens_dofs, dq : with design_derivatives: the coordinates and their dq/dp (nt, nsens, nv).
    dmu : with constraint_force_derivatives=True: d(mu)/dp (nt, nc, nv) of every constraint row.
    tape : with tape=True: every converged (sub-)step's state for the discrete adjoint, a dict
        of q, qd, qdd (ndof, ncol), mu (nc, ncol), h (ncol,) (the step that led to the column; 0
        for the initial state) and grid (nt,) (the 1-based column of every time point).
    error : with flexmbs.analysis.accuracy.simulate_with_error: the estimated time-discretisation
        error of q (ErrorEstimate; its pointwise errors have q's shape).
    checkpoints : with checkpoints=K: the full integration state at every K-th time point,
        a dict of every (K) and states (checkpoint_rows(ndof, nc), nsteps // K + 1): q, qd,
        qdd, a, the predictor's previous qdd (ndof each), mu (nc), the previous step and the
        scalings k, p of eq. (1) (what a segment of the run is restarted from:
        flexmbs.analysis.adjoint).
    steps : with simulate(steps=...): a dict of t (the step grid's times) and matrix (the
        interpolation_matrix from them to `t`); the tape, the checkpoints and
        stats['steps'] are the step grid's, every other array is on `t`. None on the
        uniform grid.
    """
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    mu: np.ndarray
    dofs: np.ndarray
    stats: dict
    wall_time: float
    #: the RunSettings that ran (flexmbs.analysis.settings: the SimulationSettings with solver
    #: and newton resolved, and the run's h and t_end)
    settings: object = None
    #: the InitialConditions the run started from (q0, qd0: arrays of every coordinate)
    initial: object = None
    sens_dofs: np.ndarray | None = None
    dq: np.ndarray | None = None
    validity: object = None
    dmu: np.ndarray | None = None
    tape: dict | None = None
    checkpoints: dict | None = None
    #: with flexmbs.analysis.accuracy.simulate_with_error: the ErrorEstimate of the stored coordinates
    #: q (point-wise (nt, nout) errors, judged by their largest change), else None
    error: object = None
    steps: dict | None = None
    #: the design simulated (user units, the order of Problem.variables) when the result comes
    #: from flexmbs.problem.Problem, else None
    design: np.ndarray | None = None

    def position_derivative(self, node):
        """(nt, 2, nv) design derivatives of a node's position (needs design_derivatives)."""
        if self.dq is None:
            raise ModelError("no design derivatives: simulate with "
                             "derivatives=DesignDerivatives(properties=...)")
        node = self._node(node)
        cols = []
        for d in (3 * node, 3 * node + 1):
            k = np.searchsorted(self.sens_dofs, d)
            if k >= len(self.sens_dofs) or self.sens_dofs[k] != d:
                raise ModelError(f"node {node} is not among the sensitivity coordinates")
            cols.append(k)
        return self.dq[:, cols, :]

    @staticmethod
    def _node(node):
        if isinstance(node, (bool, np.bool_)) or not isinstance(node, (int, np.integer)):
            raise ModelError(f"expected a node id (int), got {node!r}")
        return int(node)

    def _col(self, dof):
        idx = np.searchsorted(self.dofs, dof)
        if idx >= len(self.dofs) or self.dofs[idx] != dof:
            raise ModelError(f"coordinate {dof} was not stored; pass store=[...] including its node")
        return idx

    def position(self, node):
        """(nt, 2) positions of a node."""
        node = self._node(node)
        return np.column_stack([self.q[:, self._col(3 * node)], self.q[:, self._col(3 * node + 1)]])

    def rotation(self, node):
        """(nt,) rotation of a node (rad)."""
        return self.q[:, self._col(3 * self._node(node) + 2)]

    def velocity(self, node):
        """(nt, 3) velocities (x, y, phi) of a node."""
        node = self._node(node)
        return np.column_stack([self.qd[:, self._col(3 * node + k)] for k in range(3)])

    def coordinates(self, dofs):
        """(nt, len(dofs)) history of the given coordinates."""
        d = np.asarray(dofs) if not isinstance(dofs, (str, bytes)) else np.asarray([])
        if d.ndim != 1 or (d.size and d.dtype.kind not in "iu"):
            raise ModelError(f"coordinates: expected a list of coordinate indices (int), got {dofs!r}")
        return self.q[:, [self._col(int(k)) for k in d]]

    def animate(self, path, problem, *, evaluation=None, **options):
        """Write this motion as a film, .gif or .mp4 (flexmbs.visual.animation.animate: every body,
        the deflection magnified over the rigid reference, coloured by a response, the
        constrained histories of `evaluation` underneath). The result must come from
        `problem` with store='all': ``problem.animate(result, path, ...)`` does the same.
        Returns flexmbs.visual.animation.Animation."""
        return problem.animate(self, path, evaluation=evaluation, **options)

    def to_vtk(self, path, problem, *, frames=None):
        """Write this motion as a ParaView time series, a .pvd file and a folder of .vtu
        frames (flexmbs.visual.export.to_vtk: every body's nodes and elements with displacement,
        rotation, strains, stress and deviation). The result must come from `problem` with
        store='all': ``problem.to_vtk(result, path, ...)`` does the same. Returns (pvd path,
        vtu paths, steps)."""
        return problem.to_vtk(self, path, frames=frames)

    @property
    def mean_newton_iterations(self):
        """Newton iterations per time step."""
        return self.stats["newton_iterations"] / max(self.stats["steps"], 1)


def _messages(model, status, info, max_cuts, diagnosis=""):
    t, res, it, extra = info
    if diagnosis and status in (Status.NEWTON_FAILED, Status.SINGULAR, Status.STATIC_FAILED,
                                 Status.INITIAL_SINGULAR, Status.NONFINITE):
        where = ("static equilibrium at t = 0" if status == Status.STATIC_FAILED else
                 "the initial system [M Phi_q^T; Phi_q 0]" if status == Status.INITIAL_SINGULAR
                 else f"t = {t:.6g} s")
        kind = {Status.NEWTON_FAILED: "Newton-Raphson did not converge",
                Status.SINGULAR: "singular iteration matrix", Status.STATIC_FAILED: "no solution",
                Status.INITIAL_SINGULAR: "singular",
                Status.NONFINITE: "non-finite values (NaN/Inf)"}[status]
        return f"{where}: {kind}: {diagnosis}"
    if status == Status.NEWTON_FAILED:
        return (f"Newton-Raphson did not converge at t = {t:.6g} s even after cutting the "
                f"step {max_cuts} times: scaled increment {res:.3g} after {int(it)} iterations")
    if status == Status.SINGULAR:
        return (f"singular iteration matrix at t = {t:.6g} s (Newton iteration {int(it)}): "
                "the mechanism may be underconstrained (a body not held, a free rotation "
                "without stiffness) or in a singular posture")
    if status == Status.STATIC_FAILED:
        if extra >= 10:
            return (f"static equilibrium at t = 0: singular stiffness matrix (Newton iteration "
                    f"{int(it)}, largest residual {res:.3g}): the mechanism is not held (a body "
                    "or a rotation without support or stiffness)")
        return (f"static equilibrium at t = 0 not found (scaled increment {res:.3g} after "
                f"{int(it)} iterations): the mechanism may not be held against its loads")
    if status == Status.INITIAL_SINGULAR:
        return ("the initial system [M Phi_q^T; Phi_q 0] is singular: a coordinate has no mass "
                "and no constraint, or constraints are redundant")
    if status == Status.INCONSISTENT_INITIAL:
        r = int(extra) - 1
        return (f"the initial configuration violates constraint '{model.row_label(r)}' by "
                f"{res:.3g}: start from 'static' or make the laws match the model at t = 0")
    if status == Status.NONFINITE:
        return f"non-finite values (NaN/Inf) appeared at t = {t:.6g} s (iteration {int(it)})"
    if status == Status.BAD_INPUT:
        return "invalid settings passed to the core"
    if status == Status.LINEAR_SOLVER:
        why = {SolverStatus.INVALID: ": KLU rejected the sparsity pattern, or the model's KLU analysis "
                  "(flexmbs.core.KluAnalysis) is of another pattern"}.get(int(extra), "")
        return f"the sparse linear solver could not be set up (code {int(extra)}){why}"
    return f"simulation failed with status {status}"




def _no_memory_error(cm, solver, info):
    """ResourceError for status 9 of the core: what was being allocated and its size."""
    t, nbytes, _, what = info
    what = int(what)
    n = cm.n
    size = format_bytes(nbytes) if nbytes >= 0 else "size unknown"
    subject = {
        1: f"the iteration matrix values of {n} unknowns"
           + (" (dense: n^2 values)" if solver == "dense" else ""),
        2: f"dense LU of {n} unknowns",
        3: f"the KLU factorization of {n} unknowns",
        4: f"the integration state of {n} unknowns",
        5: f"the design-derivative work arrays of {n} unknowns",
        6: f"the model arrays ({cm.nel} elements, {n} unknowns)",
    }.get(what, f"work arrays of {n} unknowns")
    when = f" at t = {t:.6g} s" if t > 0 else ""
    hint = ("use solver='klu' (memory grows like n, not n^2) or fewer elements"
            if solver == "dense" else "use fewer elements, or free memory")
    return ResourceError(f"out of memory in the core{when}: could not allocate {subject}: {size}; "
                         f"{hint}", required=float(nbytes) if nbytes >= 0 else None)


def _numeric_array(name, value, kind=float):
    """np.asarray(value, kind), or a ModelError naming the argument (strings, ragged lists)."""
    if isinstance(value, (str, bytes)) or np.asarray(value, dtype=object).dtype.kind not in "biufO":
        raise ModelError(f"{name} must be an array of numbers, got {value!r}")
    if has_complex(value):
        raise ModelError(f"{name} must be an array of real numbers, got complex values "
                         f"(numpy dtype {np.asarray(value).dtype})")
    try:
        if kind is int and np.asarray(value).dtype.kind not in "iu":
            raise TypeError
        return np.asarray(value, kind)
    except (TypeError, ValueError, OverflowError):
        raise ModelError(f"{name} must be an array of numbers, got {value!r}") from None


def newton_mode(newton="auto", reuse_jacobian=None):
    """The Newton strategy of `simulate` from its `newton` and deprecated `reuse_jacobian`
    arguments: 'auto', 'full' or 'reuse'. reuse_jacobian=True means 'reuse', False 'full'
    (a DeprecationWarning says so); given together with a different `newton`, ModelError."""
    if not isinstance(newton, str) or newton not in NEWTON_MODES:
        raise ModelError(f"newton must be one of {', '.join(map(repr, NEWTON_MODES))}, "
                         f"got {newton!r}")
    if reuse_jacobian is None:
        return newton
    _check_flag("reuse_jacobian", reuse_jacobian)
    alias = "reuse" if reuse_jacobian else "full"
    if newton not in ("auto", alias):
        raise ModelError(f"reuse_jacobian={bool(reuse_jacobian)} (deprecated: newton={alias!r}) "
                         f"contradicts newton={newton!r}: give newton alone")
    warnings.warn(f"simulate(reuse_jacobian={bool(reuse_jacobian)}) is deprecated: use "
                  f"newton={alias!r} (the default newton='auto' reuses the iteration matrix while "
                  "Newton contracts well)", DeprecationWarning, stacklevel=3)
    return alias


def _drives_move_at_start(cm, margs):
    """Whether a driven constraint row has a non-zero rate at t = 0."""
    rows = cm.c_law[:cm.nc]
    used = rows[rows > 0] - 1
    return bool(used.size) and bool(np.any(np.asarray(margs["law_der"])[used, 0] != 0.0))


def _static_start_note(model, cm, margs):
    """Why a static start with drives moving at t = 0 may fail, and what to do instead."""
    rows = cm.c_law[:cm.nc]
    rate = np.asarray(margs["law_der"])[:, 0]
    laws = model.laws()

    def name(r):          # the law's name (a case's drive: 'drive motor'), else the row's
        law = getattr(laws[rows[r] - 1], "name", None)
        return law if law and law != "law" else model.row_label(r)
    moving = list(dict.fromkeys(name(r) for r in range(cm.nc)
                                if rows[r] > 0 and rate[rows[r] - 1] != 0.0))
    return (f"start = 'static' assumes the mechanism at rest at t = 0, but "
            f"{', '.join(moving)} already move{'s' * (len(moving) == 1)} then (the velocity "
            f"jumps in the first step): use start = 'rest' (the velocities the drives impose "
            f"at t = 0) or a law that starts at zero speed (ramp_to_speed, smooth_step)")


def stored_dofs(model, store="all"):
    """The coordinates (sorted 0-based indices of q) that `simulate(model, store=store)` keeps
    at every step: every one for 'all', else the three of each node and those of each body
    (Body objects) listed."""
    if isinstance(store, str):
        if store != "all":
            raise ModelError(f"store must be 'all' or a list of nodes/bodies, got {store!r}")
        return np.arange(model.ndof)
    if not isinstance(store, (list, tuple, np.ndarray)):
        raise ModelError(f"store must be 'all' or a list of nodes/bodies, got {store!r}")
    dofs = []
    for item in store:
        if hasattr(item, "dofs"):
            if model.bodies.get(getattr(item, "name", None)) is not item:
                raise ModelError(f"store: body {getattr(item, 'name', item)!r} is not a body "
                                 "of this model")
            dofs.extend(item.dofs)
        else:
            node = model._check_node(item, "store")
            dofs.extend([3 * node, 3 * node + 1, 3 * node + 2])
    out = np.unique(np.asarray(dofs, int))
    if out.size == 0:
        raise ModelError("store is empty")
    return out


#: The part of a MemoryEstimate holding the adjoint's tape (simulate(tape=True)).
TAPE_PART = "tape of every (sub-)step (adjoint)"
#: The part of a MemoryEstimate holding a checkpointed run's states (simulate(checkpoints=K)).
CHECKPOINT_PART = "checkpoints of the full state (adjoint)"


def _core_every(checkpoints, nsteps):
    """The checkpoint interval given to the core (a C int): any interval beyond the run keeps
    the initial state only, as nsteps + 1 does (a K of 10**20 overflowed the C int)."""
    return int(min(checkpoints, int(nsteps) + 1)) if checkpoints else 0


def checkpoint_rows(ndof, nc):
    """Numbers of one checkpoint (simulate(checkpoints=K), generalized_alpha.f90 ckpt_rows):
    q, qd, qdd, a, the predictor's previous qdd, mu, the previous step, k and p."""
    return 5 * ndof + nc + 3


def checkpoint_count(nsteps, every):
    """Checkpoints of a run of nsteps steps kept every `every` time points (t = 0 included)."""
    return nsteps // every + 1


def checkpoint_bytes(model, nsteps, every):
    """Bytes of the checkpoints of simulate(checkpoints=every) over nsteps steps."""
    return 8.0 * checkpoint_count(nsteps, every) * checkpoint_rows(model.ndof, len(model._rows))


def tape_columns(nsteps):
    """Columns a tape is first allocated with: every grid point and room for a quarter more
    sub-steps (at least 64) than steps."""
    return nsteps + 1 + max(64, nsteps // 4)


def _tape_bytes(model, ncol):
    """Bytes of a tape of ncol columns: q, qd, qdd of every coordinate, every multiplier
    (3 ndof + nc numbers), the step h and the grid index (1.5)."""
    return 8.0 * ncol * (3 * model.ndof + max(len(model._rows), 1) + 1.5)


def _estimate(model, nsteps, out, solver, design_derivatives, sensitivity_dofs, want_dmu):
    nv = 0
    if design_derivatives is not None:
        shape = np.shape(design_derivatives)
        nv = shape[2] if len(shape) == 3 else 0
    nsens = out.size if sensitivity_dofs is None else np.size(sensitivity_dofs)
    return estimate_memory(n=model.ndof + len(model._rows), ndof=model.ndof, nc=len(model._rows),
                           nel=len(model._elements), nt=nsteps + 1, nout=out.size, solver=solver,
                           nlaw=len(model.laws()), nv=nv, nsens=nsens, dmu=bool(want_dmu))


def memory_estimate(model: Model, t_end, h=5e-4, settings=None, *, initial=None,
                    derivatives=None, tape=False, checkpoints=None, steps=None, **deprecated):
    """The memory `simulate(model, t_end, h, settings, ...)` with these arguments would need,
    without running it (flexmbs.resources.MemoryEstimate: `total` bytes and its `parts`; with
    tape=True the part TAPE_PART, as first allocated: a run cutting more steps than a quarter
    of them needs more; with checkpoints=K the part CHECKPOINT_PART, `checkpoint_bytes`).
    Takes simulate's arguments (and its deprecated keywords, with the same warnings); only
    those that change the estimate are read (settings.store and settings.solver, the
    derivatives, tape, checkpoints and steps)."""
    if not isinstance(model, Model):
        raise ModelError(f"memory_estimate expects a flexmbs Model, got {type(model).__name__}")
    settings, _, derivatives, _ = _arguments("memory_estimate", settings, initial, derivatives,
                                             deprecated)
    store, solver = settings.store, settings.solver
    design_derivatives, sensitivity_dofs, constraint_force_derivatives = (
        (None, None, False) if derivatives is None else
        (derivatives.properties, derivatives.dofs, derivatives.constraint_forces))
    nsteps = time_steps(t_end, h, math.inf)
    if steps is not None:     # a non-uniform step grid: its steps (outputs on the j h grid)
        nsteps = max(nsteps, step_grid(steps, nsteps * h).size - 1)
    n_unknowns = model.ndof + len(model._rows)
    if isinstance(solver, str) and solver == "auto":
        solver = "dense" if n_unknowns <= DENSE_MAX_UNKNOWNS else "klu"
    if not isinstance(solver, str) or solver not in _SOLVERS:
        raise ModelError(f"solver must be 'auto', 'dense' or 'klu', got {solver!r}")
    want_dmu = bool(constraint_force_derivatives) and design_derivatives is not None
    est = _estimate(model, nsteps, stored_dofs(model, store), solver, design_derivatives,
                    sensitivity_dofs, want_dmu)
    if tape:
        est.parts[TAPE_PART] = _tape_bytes(model, tape_columns(nsteps))
    if checkpoints:
        est.parts[CHECKPOINT_PART] = checkpoint_bytes(model, nsteps, int(checkpoints))
    return est


#: simulate's former keywords that are settings (SimulationSettings fields), of the initial
#: state (InitialConditions) and of the design derivatives (DesignDerivatives): still taken,
#: with a DeprecationWarning naming the new spelling
_SETTING_KEYWORDS = ("rho_inf", "start", "store", "solver", "newton", "tol", "max_iter",
                     "max_cuts", "kscale", "penalty", "memory_limit", "validity", "polish")
_INITIAL_KEYWORDS = {"q0": "q0", "qd0": "qd0"}
#: the error of a request of d(mu)/dp without the design's property derivatives
_FORCES_NEED_PROPERTIES = ("DesignDerivatives.constraint_forces=True needs "
                           "DesignDerivatives.properties (the design's property derivatives)")
_DERIVATIVE_KEYWORDS = {"design_derivatives": "properties", "sensitivity_dofs": "dofs",
                        "constraint_force_derivatives": "constraint_forces"}


def _arguments(where, settings, initial, derivatives, old):
    """(SimulationSettings, InitialConditions, DesignDerivatives or None, reuse_jacobian) of
    `where`'s arguments; `old`: its deprecated keywords (each a DeprecationWarning naming the
    new spelling; TypeError for a keyword it never took)."""
    unknown = sorted(set(old) - set(_SETTING_KEYWORDS) - set(_INITIAL_KEYWORDS)
                     - set(_DERIVATIVE_KEYWORDS) - {"reuse_jacobian"})
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}")
    settings = SimulationSettings.coerce(settings)
    changes = {k: old[k] for k in _SETTING_KEYWORDS if k in old}
    if changes:
        spelled = ", ".join(f"{k}=..." for k in changes)
        warnings.warn(f"{where}({spelled}) is deprecated: use {where}(..., "
                      f"settings=SimulationSettings({spelled}))", DeprecationWarning,
                      stacklevel=3)
        settings = settings.replace(**changes)
    init = {v: old[k] for k, v in _INITIAL_KEYWORDS.items() if k in old}
    if init:
        if initial is not None:
            raise ModelError(f"{where}: give the initial state once, initial= (not with "
                             f"{', '.join(init)}=)")
        spelled = ", ".join(f"{k}=..." for k in init)
        warnings.warn(f"{where}({spelled}) is deprecated: use {where}(..., "
                      f"initial=InitialConditions({spelled}))", DeprecationWarning, stacklevel=3)
        initial = InitialConditions(**init)
    if initial is None:
        initial = InitialConditions()
    if not isinstance(initial, InitialConditions):
        raise ModelError(f"initial must be an InitialConditions(q0=..., qd0=...) or None, got "
                         f"{type(initial).__name__}")
    der = {v: old[k] for k, v in _DERIVATIVE_KEYWORDS.items() if k in old}
    if der:
        if derivatives is not None:
            raise ModelError(f"{where}: give the design derivatives once, derivatives= (not "
                             f"with {', '.join(k for k in _DERIVATIVE_KEYWORDS if k in old)}=)")
        given = ", ".join(f"{k}=..." for k in _DERIVATIVE_KEYWORDS if k in old)
        spelled = ", ".join(f"{k}=..." for k in der)
        warnings.warn(f"{where}({given}) is deprecated: use {where}(..., "
                      f"derivatives=DesignDerivatives({spelled}))", DeprecationWarning,
                      stacklevel=3)
        cf = der.get("constraint_forces", False)
        if not isinstance(cf, (bool, np.bool_)):
            raise ModelError(f"constraint_force_derivatives must be True or False, got {cf!r}")
        if der.get("properties") is None:
            if cf:
                raise ModelError(_FORCES_NEED_PROPERTIES)
        else:
            derivatives = DesignDerivatives(**der)
    derivatives = DesignDerivatives.coerce(derivatives)
    return settings, initial, derivatives, old.get("reuse_jacobian")


def simulate(model: Model, t_end, h=5e-4, settings=None, *, initial=None, derivatives=None,
             tape=False, checkpoints=None, steps=None, **deprecated):
    """Simulate a model with generalized-alpha (eqs. 3-6) and Newton-Raphson (eq. 7).

    ``simulate(model, t_end, h, SimulationSettings(tol=1e-12, newton="full"))``: how the run
    integrates, iterates, solves and checks is one `settings` object
    (flexmbs.analysis.settings.SimulationSettings, whose docstring is the table of its fields
    and defaults); the other arguments are what this run computes. simulate's former keywords
    (rho_inf=, tol=, store=, ... q0=, qd0=, design_derivatives=, sensitivity_dofs=,
    constraint_force_derivatives=) are still taken, each with a DeprecationWarning naming the
    new spelling.

    Parameters
    ----------
    model : Model
    t_end : float
        End time (s); a whole number of steps.
    h : float, default 5e-4
        Time step (s).
    settings : SimulationSettings, dict of its fields, or None (the defaults)
        How the run integrates, iterates, solves and checks (its fields: Notes).
    initial : InitialConditions(q0, qd0), optional
        Initial coordinates q0 (default: reference) and velocities qd0 (default: the
        start's, see `start`).
    derivatives : DesignDerivatives, or the properties array alone, optional
        The design derivatives asked for (its fields: Notes).
    tape : bool, default False
        Keep every converged state, of every sub-step of a cut step too, in Result.tape (what
        the discrete adjoint runs backwards over: flexmbs.analysis.adjoint): 3 ndof + nc numbers per
        (sub-)step, counted in the memory estimate (room for a quarter more sub-steps than
        steps; a run that cuts more is repeated once with room for every step cut max_cuts
        times).
    checkpoints : int, optional
        Keep the full integration state at every `checkpoints`-th time point (t = 0 included)
        in Result.checkpoints, `checkpoint_rows` numbers each (counted in the memory
        estimate): what the discrete adjoint restarts segments of the run from instead of a
        tape (flexmbs.analysis.adjoint, checkpointing). Not with tape or design_derivatives.
    steps : array of times, optional
        A non-uniform step grid from 0 to t_end (`step_grid`); outputs on t_j = j h.
    **deprecated
        simulate's former keywords: each a SimulationSettings field, q0/qd0 or
        design_derivatives/sensitivity_dofs/constraint_force_derivatives, taken with a
        DeprecationWarning naming the new spelling; reuse_jacobian (True: newton='reuse',
        False: 'full').

    Returns
    -------
    Result, its `settings` the RunSettings that ran (solver and newton resolved, h and
    t_end), its `initial` the InitialConditions it started from (arrays).

    Raises
    ------
    ModelError for invalid input, SimulationError when no solution is found (the message
    tells redundant constraints, a body not held and an overflowing input apart),
    ResourceError when the run does not fit in memory (before the run, or when an allocation
    fails), InvalidResultError when the result converged outside the model's validity.

    Notes
    -----
    The fields of `settings` (SimulationSettings) and of `derivatives` (DesignDerivatives):

    - `rho_inf` (float in [0, 1], default 0.5):
      Spectral radius at infinite frequency (1: no numerical damping).
    - `start` ({'rest', 'static'}, default 'rest'):
      'rest': the reference configuration (or q0) moving with the rigid-body velocity
      field the drives impose at t = 0 (flexmbs.model.kinematics.drive_velocities: every body
      moves rigidly; zero when no drive moves at t = 0), unless qd0 is given;
      'static': static equilibrium under the loads at the drives' initial positions.
    - `store` ('all', or a list of node ids / Body objects, default 'all'):
      Which coordinates to keep at every step (memory for long runs).
    - `solver` ({'auto', 'dense', 'klu'}, default 'auto'):
      Dense LAPACK LU up to DENSE_MAX_UNKNOWNS unknowns (currently none: KLU was faster at
      every size measured), SuiteSparse KLU above.
    - `newton` ({'auto', 'full', 'reuse'}, default 'auto'):
      Newton strategy. 'full': the iteration matrix of eq. (7) assembled and factored at
      every iteration. 'auto': the factorization is kept across iterations and steps while
      the scaled increment contracts by at least 0.3 per iteration, and refreshed when it does
      not, when a step needs a 4th iteration, when the observed contraction would need more
      further iterations than a refresh costs (a cost model: generalized_alpha.f90,
      auto_refresh_cost), or after a step that needed 3 or had to refresh; an increment
      below `tol` (full Newton's test) is accepted once the estimated remaining error
      (contraction / (1 - contraction) x increment) is at the level full Newton's quadratic
      convergence leaves (tol^2, or the rounding of the coordinates), because modified
      Newton's errors have the same sign from step to step and the velocities integrate them;
      a step it cannot converge is retried with full Newton before being cut. Same responses
      as 'full' (tests/test_newton.py: 1e-11 m on the robot), 2x faster on the robot.
      'reuse': the former modified Newton, fewest factorizations, accepted at `tol` (its
      responses differ from full Newton's by ~250 tol qscale on the robot). With
      design_derivatives, 'auto' and 'reuse' take full Newton steps from a step's second
      iteration: the derivative solve needs that factorization (the tangent within `tol` of
      the converged state) anyway, and it serves the next step's first iteration too.
    - `tol` (float, default 1e-10):
      Newton tolerance on max|dq| / max(1, max|q_ref|, element length).
    - `max_iter`, `max_cuts` (int, default 20 and 6):
      Newton iterations per step, step halvings before failing.
    - `kscale`, `penalty` (float or None):
      k and p of eq. (1); None: the mean diagonal of the iteration matrix.
    - `properties` of DesignDerivatives (array (5, nel, nv); formerly design_derivatives=):
      d[EA, kGA, EI, rhoA, rhoI]/dp of every element for nv design variables p.
      When given, the discrete generalized-alpha equations (and the static start
      and initial accelerations) are differentiated directly, in Fortran, after
      every converged step, and `Result.dq` holds dq/dp.
    - `dofs` of DesignDerivatives (array of int, optional; formerly sensitivity_dofs=):
      Coordinates (0-based) whose derivatives are kept (default: the stored ones).
    - `constraint_forces` of DesignDerivatives (bool, default False; formerly
      constraint_force_derivatives=): with the properties: also return d(mu)/dp of every constraint row (the physical
      multipliers of eq. 1, as in Result.mu) in `Result.dmu` (nt, nc, nv). The same
      solve gives them (no extra factorization); off by default, as they take
      nt * nc * nv numbers.
    - `memory_limit` (float (bytes), None or math.inf, default None):
      Before the run, the memory it needs is estimated (flexmbs.resources.estimate_memory:
      stored outputs over the time grid, constraint forces, design derivatives, the dense
      n x n matrix and LU factors or the KLU ones, the model's arrays) and compared with this
      limit; a run that does not fit raises ResourceError with the estimate, the limit and
      what to change. None: the environment variable FLEXMBS_MEMORY_LIMIT (bytes, e.g. "8G";
      "none" disables the check) if set, else the memory available now (MemAvailable,
      bounded by RLIMIT_AS). math.inf: no check (an allocation that then fails in the core
      still raises ResourceError naming what was allocated and its size).
    - `validity` ({'warn', 'error', 'off'} or flexmbs.analysis.validity.ValidityLimits,
      default 'warn'):
      Checks of the converged result (Result.validity): largest axial and bending strain of
      every beam element against the linear-elastic range (warning above 1 %, error above
      10 %), constraint drift, energy growth of a free system. 'warn': ValidityWarning above
      the warning limits, InvalidResultError above the failure limits; 'error': both raise;
      'off': no checks. Only stored coordinates are checked.
    - `polish` (bool, default False):
      With newton 'auto' or 'reuse' (which then takes 'auto''s refresh rules): every step
      converged to the rounding level, as full Newton's states are (the discrete adjoint,
      flexmbs.analysis.adjoint, linearizes about them):
      a step is accepted when its increment is at the rounding level *and* the observed
      contraction bounds the remaining error below it ('auto' accepts on either). With
      'auto''s states, 8e-12 m off, the robot's KS gradient was 2e-6 off; polished, 5e-10.
      The extra work is held iterations (a residual and a solve each): on the robot 0.47
      factorizations and 2.6 solves per step, against 0.35 and 2.5 unpolished.
    """
    t_start = time.perf_counter()
    if not isinstance(model, Model):
        raise ModelError(f"simulate expects a flexmbs Model, got {type(model).__name__}")
    # the step count alone here (one reading of the available memory per call, below:
    # check_memory's estimate contains the grid and stored outputs time_steps would check)
    nsteps = time_steps(t_end, h, math.inf)
    settings, initial, derivatives, reuse_jacobian = _arguments(
        "simulate", settings, initial, derivatives, deprecated)
    rho_inf, start, store, solver, tol, max_iter, max_cuts, kscale, penalty, memory_limit, \
        polish = (getattr(settings, k) for k in (
            "rho_inf", "start", "store", "solver", "tol", "max_iter", "max_cuts", "kscale",
            "penalty", "memory_limit", "polish"))
    limits = settings.validity
    newton = newton_mode(settings.newton, reuse_jacobian)
    q0, qd0 = initial.q0, initial.qd0
    design_derivatives, sensitivity_dofs, constraint_force_derivatives = (
        (None, None, False) if derivatives is None else
        (derivatives.properties, derivatives.dofs, derivatives.constraint_forces))
    if design_derivatives is None:
        sensitivity_dofs = None
    _check_flag("tape", tape)
    tg = None if steps is None else step_grid(steps, nsteps * h)
    ncore = nsteps if tg is None else tg.size - 1
    if checkpoints is not None:
        if isinstance(checkpoints, (bool, np.bool_)) or not isinstance(checkpoints, (int, np.integer)) \
                or checkpoints < 1:
            raise ModelError(f"checkpoints must be an integer >= 1 (time points between "
                             f"checkpoints) or None, got {checkpoints!r}")
        if tape or design_derivatives is not None:
            raise ModelError("checkpoints= is not allowed with tape=True or design derivatives "
                             "(DesignDerivatives.properties; a checkpointed run replaces the "
                             "tape of the adjoint)")
        checkpoints = int(checkpoints)
    if not model._nodes:
        raise ModelError("the model has no nodes")
    n_unknowns = model.ndof + len(model._rows)
    if isinstance(solver, str) and solver == "auto":
        solver = "dense" if n_unknowns <= DENSE_MAX_UNKNOWNS else "klu"
    if not isinstance(solver, str) or solver not in _SOLVERS:
        raise ModelError(f"solver must be 'auto', 'dense' or 'klu', got {solver!r}")

    out = stored_dofs(model, store)
    # memory: estimated and checked before anything of the model's or the grid's size is built
    if not isinstance(constraint_force_derivatives, (bool, np.bool_)):
        raise ModelError(f"DesignDerivatives.constraint_forces must be True or False, got "
                         f"{constraint_force_derivatives!r}")
    if constraint_force_derivatives and design_derivatives is None:
        raise ModelError(_FORCES_NEED_PROPERTIES)
    want_dmu = bool(constraint_force_derivatives)
    est = _estimate(model, max(nsteps, ncore), out, solver, design_derivatives, sensitivity_dofs,
                    want_dmu)
    ntape = tape_columns(ncore) if tape else 1

    def tape_bytes(ncol):
        return _tape_bytes(model, ncol)

    if tape:
        est.parts[TAPE_PART] = tape_bytes(ntape)
    nckr = checkpoint_rows(model.ndof, len(model._rows))
    nck = checkpoint_count(ncore, checkpoints) if checkpoints else 1
    if checkpoints:
        est.parts[CHECKPOINT_PART] = checkpoint_bytes(model, ncore, checkpoints)
    check_memory(est, memory_limit, what=f"simulate (solver={solver!r}, {n_unknowns} unknowns, "
                                         f"{nsteps} steps, {out.size} stored coordinates)")

    t = h * np.arange(nsteps + 1)
    cm = model.compile()
    pat = model.pattern(solver)
    props = model.element_properties()
    law_t, law_k = law_times(h, nsteps, tg)
    margs = core_model_args(model, solver, law_t, props)

    q_init = cm.qref.copy() if q0 is None else _numeric_array("q0", q0).copy()
    qd_init = np.zeros(cm.ndof) if qd0 is None else _numeric_array("qd0", qd0).copy()
    if qd0 is None and start == "rest" and q_init.shape == (cm.ndof,) \
            and _drives_move_at_start(cm, margs):
        # the rigid-body velocity field the drives impose (every body moving rigidly), not
        # zero velocities of the nodes the drives do not hold: those would start a spurious
        # vibration of the flexible bodies
        qd_init = drive_velocities(model, q_init, float(t[0]))
    for name, v in (("q0", q_init), ("qd0", qd_init)):
        if v.shape != (cm.ndof,) or not np.all(np.isfinite(v)):
            raise ModelError(f"{name} must be a finite array of {cm.ndof} coordinates")
    if start == "static" and qd0 is None and _drives_move_at_start(cm, margs):
        warnings.warn(_static_start_note(model, cm, margs), SettingWarning, stacklevel=2)

    nel = cm.el_dofs.shape[1]
    if design_derivatives is not None:
        dprop = _numeric_array("DesignDerivatives.properties", design_derivatives)
        if dprop.ndim != 3 or dprop.shape[:2] != (5, cm.nel) or not np.all(np.isfinite(dprop)):
            raise ModelError(f"DesignDerivatives.properties must be a finite array of shape "
                             f"(5, {cm.nel}, nv), got shape {dprop.shape}")
        nv = dprop.shape[2]
        sdofs = out if sensitivity_dofs is None else np.unique(
            _numeric_array("DesignDerivatives.dofs", sensitivity_dofs, int))
        if sdofs.size == 0 or sdofs.min() < 0 or sdofs.max() >= cm.ndof:
            raise ModelError(f"DesignDerivatives.dofs must be coordinates in [0, {cm.ndof}), "
                             f"got {sdofs.tolist()!r:.80}")
        dprop_f = np.zeros((5, nel, max(nv, 1)), order="F")
        dprop_f[:, :cm.nel, :nv] = dprop
    else:
        nv, sdofs = 0, np.zeros(1, int)
        dprop_f = np.zeros((5, nel, 1), order="F")
    def run(ncol):
        return run_interruptible(
            simulate_arrays, est.stack, **margs, nsteps=ncore, q0=q_init, qd0=qd_init,
            ap=pat["ap"], ai=pat["ai"], h=float(h),
            rho_inf=float(rho_inf), tol=float(tol), max_iter=int(max_iter),
            max_cuts=int(max_cuts), solver=_SOLVERS[solver], newton=NEWTON_MODES[newton],
            static_start=int(start == "static"), kscale=float(kscale or 0.0),
            penalty=float(penalty or 0.0), out_dofs=(out + 1).astype(np.int32),
            nv=nv, dprop=dprop_f, sens_dofs=(sdofs + 1).astype(np.int32),
            want_dmu=int(want_dmu), ndmu=max(cm.nc, 1) if want_dmu else 1, polish=int(polish),
            ntape=ncol, nckr=nckr, nck=nck, ckpt_every=_core_every(checkpoints, ncore), restart=0,
            x_start=np.zeros(nckr), j_start=0, klu_analysis=klu_analysis(model, solver),
            tg=np.zeros(1) if tg is None else tg)

    try:
        core_out = run(ntape)
        if core_out.status == Status.TAPE_FULL:
            # more sub-steps than room: once more with room for every step cut max_cuts times
            ntape = ncore * 2 ** int(max_cuts) + 1
            est.parts[TAPE_PART] = tape_bytes(ntape)
            check_memory(est, memory_limit, what=f"simulate with a tape of {ntape} sub-steps")
            core_out = run(ntape)
    except MemoryError as exc:    # the wrapper could not allocate the output arrays
        if isinstance(exc, ResourceError):
            raise
        raise ResourceError(f"the outputs of {nsteps + 1} time points could not be allocated "
                            f"(estimate of the run: {format_bytes(est.total)}; {est.largest()}): "
                            "store fewer outputs (store=[...]), use a coarser step h or a shorter "
                            "t_end", required=est.total) from exc
    st = dict(zip(("newton_iterations", "factorizations", "residual_evaluations", "step_cuts",
                   "static_iterations", "steps", "sensitivity_factorizations",
                   "symbolic_analyses"),
                  (int(v) for v in core_out.stats)))
    status, info = core_out.status, core_out.info
    st["newton"] = newton
    st["solver"] = solver
    st["unknowns"] = cm.n
    st["memory_estimate"] = est.total        # bytes, the estimate checked before the run
    if status == Status.NO_MEMORY:
        raise _no_memory_error(cm, solver, info)
    if status != 0:
        try:
            diagnosis = diagnose_failure(model, int(status), q=q_init,
                                         law_val=margs["law_val"][:, ::law_k],
                                         props=props)
        except Exception as exc:     # the diagnosis must never hide the failure itself
            diagnosis = f"(no diagnosis: {type(exc).__name__}: {exc})"
        message = _messages(model, int(status), info, max_cuts, diagnosis)
        if start == "static" and qd0 is None and _drives_move_at_start(cm, margs):
            message += f"; {_static_start_note(model, cm, margs)}"
        raise SimulationError(message,
                              time=float(info[0]), residual=float(info[1]),
                              iterations=int(info[2]), code=int(status))
    dq_t = np.transpose(core_out.dq[:, :nv, :], (2, 0, 1)) if nv else None
    dmu_t = np.transpose(core_out.dmu[:cm.nc, :nv, :], (2, 0, 1)) if want_dmu else None
    q_out, qd_out, qdd_out = core_out.q.T, core_out.qd.T, core_out.qdd.T
    mu_out = core_out.mu[:cm.nc].T
    if tg is not None:       # from the step grid to the output grid
        w = interpolation_matrix(tg, t)
        q_out, qd_out, qdd_out, mu_out = (w @ a for a in (q_out, qd_out, qdd_out, mu_out))
        if nv:
            dq_t = (w @ dq_t.reshape(tg.size, -1)).reshape(t.size, *dq_t.shape[1:])
        if want_dmu:
            dmu_t = (w @ dmu_t.reshape(tg.size, -1)).reshape(t.size, *dmu_t.shape[1:])
    run_settings = RunSettings(**{**{k: getattr(settings, k) for k in
                                     settings.__dataclass_fields__},
                                  "solver": solver, "newton": newton, "h": h, "t_end": t_end})
    # what the former dict Result.settings also held (its deprecated dict reading)
    object.__setattr__(run_settings, "_run", {"q0": q_init, "qd0": qd_init, "steps": tg})
    res = Result(t=t, q=q_out, qd=qd_out, qdd=qdd_out, mu=mu_out, dofs=out,
                  stats=st, wall_time=time.perf_counter() - t_start,
                  settings=run_settings,
                  initial=InitialConditions(q0=q_init, qd0=qd_init),
                  sens_dofs=sdofs if nv else None, dq=dq_t, dmu=dmu_t,
                  steps=None if tg is None else dict(t=tg, matrix=w))
    if tape:
        res.tape = core_out.tape(cm.nc)
    if checkpoints:
        res.checkpoints = dict(every=checkpoints, states=core_out.checkpoints)
    res.validity = check_result(model, res, limits, law_val=margs["law_val"][:, ::law_k],
                                tol=float(tol),
                                props=props)
    apply_validity(res.validity, res)
    return res
