"""The fully coupled method: dynamic response optimization on the flexible simulation.

The paper's sections 4 and 5.4. Every optimizer iteration runs the flexible multibody
simulation of the current design and works on its time responses directly: minimize the
beam mass m(p) subject to the deviation limit at every time step (the paper's local
formulation, problems (27) and (32)),

    g_n(p) = dl_n(p) / limit - 1 <= 0   (or (dl_n / limit)^2 - 1 <= 0),   n = 1 .. n_end,

and the bounds on p; or, as eq. (22) suggests, the same constraints aggregated over all the
steps or over time windows (Kreisselmeier-Steinhauser or p-norm), so that long horizons do
not need thousands of constraints.

Design variables are scaled for the optimizer as x = p / p_start (the run's starting design,
so x = 1 at the start), the objective as m(p) / m(p_start); the constraints are already
relative (1 = the limit). One simulation per design serves the objective, the constraints and
their gradients (a cache keyed on the design); simulations and gradient evaluations are
counted. Sensitivities: direct differentiation through the simulation (default, exact, one
simulation per design, `flexmbs.sensitivity`), or the paper's forward finite differences with
a relative step of 1e-6 (n_v + 1 simulations per gradient).

Optimizers (``optimizer=``). CASES.md reports that plain SLSQP fails from three of the
paper's four starts: the deviation grows like p^-3 to p^-4, the first linearized step lands on
the bounds with hundreds of violated steps, and the late time steps are vibration samples
whose linearizations hold only for small design changes (on the four-bar a sample can cross
the limit for a change of p of 0.01 mm). Hence:

``'mma'`` (default)
    Svanberg's globally convergent method of moving asymptotes, GCMMA
    (`flexmbs.optimize.mma`): each iteration minimizes convex, separable, reciprocal-type
    approximations of the mass and of every constraint between moving asymptotes, the
    conservative approximation of structural optimization codes; inner iterations (one
    simulation each) raise the curvature of any approximation found not conservative at the
    new design. Converges from all four of the paper's starts (Table 6) in 7-8 iterations.
``'sqp'``
    An active-set SQP in a relative trust region |d_i| <= r x_i. Each iteration solves the QP
    min grad f . d + 1/2 d'Bd s.t. g + J d <= t, the bounds and the trust region, with an
    elastic variable t >= 0 (l_inf penalty, so it always has a solution), by the
    least-distance programming route of Lawson & Hanson (scipy's NNLS), the same core as
    SLSQP's QP solver. B starts at the exact Hessian of the (quadratic) mass and is updated
    by damped BFGS on the Lagrangian (Powell); steps are accepted on the ratio of actual to
    predicted decrease of the l_inf merit function f + nu max(0, max g) (Nocedal & Wright,
    Numerical Optimization, 2nd ed., sections 18.5 and 15.5), with one second-order
    correction against the Maratos effect, and rejected when a constraint near its limit
    differs from its linearization by more than `model_fidelity`; r grows or shrinks with
    the ratio.
``'slsqp'``
    scipy's SLSQP as it is (the paper's kind of optimizer, without move limits), kept as a
    baseline: it stalls on the bounds from the starts CASES.md names.

Stopping test (every optimizer, applied to the iterates; iteration 0 is the start): the
paper's, as it states it, i.e. the relative change of the objective between two iterations
< 1e-3 and the relative constraint violation max(0, max g) < 1e-6 (the four-bar: also the
relative change of the design variables < 1e-3), read from the case file's [optimizer.fully]
table; together with a first-order test, so that it cannot stop on a plateau: the KKT
residual ||grad f + sum lambda_j grad g_j - mu_lo + mu_up|| / ||grad f|| (lambda, mu >= 0 by
NNLS over the constraints within `active_tol` of their limit and the bounds touched) must be
below `kkt_tol`. A run whose design stops changing (5 iterations) ends as not converged.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import linprog, minimize, nnls

from flexmbs.cases import as_case
from flexmbs.errors import CaseError, ModelError, SimulationError
from flexmbs.optimize.weakly import _progress_callback
from flexmbs.sections import real_number, whole_number
from flexmbs.optimize.mma import MMA
from flexmbs.optimize.result import HistoryWriter, OptimizationResult
from flexmbs.responses.aggregate import DEFAULT_PARAMETER, aggregate_constraints
from flexmbs.sensitivity import case_gradients

__all__ = ["optimize_fully", "FullyCoupledProblem", "Evaluation", "kkt_residual", "solve_qp",
           "aggregate_constraints",
           "OPTIMIZERS", "SENSITIVITIES", "AGGREGATIONS", "CONSTRAINT_FORMS"]

OPTIMIZERS = ("mma", "sqp", "slsqp")
SENSITIVITIES = ("direct", "fd")
AGGREGATIONS = ("none", "ks", "pnorm")
CONSTRAINT_FORMS = ("linear", "squared")
_DEFAULT_AGGREGATION_PARAMETER = DEFAULT_PARAMETER


# ============================================================================ the problem
@dataclass
class Evaluation:
    """One design analysed: responses, scaled objective and constraints, and gradients.

    Attributes
    ----------
    x : (nv,) scaled design (p / p_scale); design_mm : (nv,) the design in mm.
    mass : beam mass (kg); t : (nt,) time grid; deviation : (nt,) deviation history (m).
    d_deviation : (nt, nv) its derivatives w.r.t. p (m/mm), None until a gradient is computed.
    f : objective m / m_ref; df : (nv,) its gradient w.r.t. x.
    g : (ncon,) constraints (feasible when <= 0, relative: 0 is the limit).
    dg : (ncon, nv) their gradients w.r.t. x, None until computed.
    """
    x: np.ndarray
    design_mm: np.ndarray
    mass: float
    t: np.ndarray
    deviation: np.ndarray
    d_deviation: np.ndarray | None
    f: float
    df: np.ndarray
    g: np.ndarray
    dg: np.ndarray | None

    @property
    def max_deviation(self):
        return float(self.deviation.max())

    @property
    def step_at_max(self):
        """1-based time step of the maximum deviation (t_n = (n - 1) h, as the paper counts)."""
        return int(np.argmax(self.deviation)) + 1

    @property
    def violation(self):
        """Relative constraint violation max(0, max g)."""
        return float(max(0.0, self.g.max()))


class FullyCoupledProblem:
    """The dynamic response optimization problem of a case, scaled for an optimizer.

    Parameters
    ----------
    case : flexmbs.cases.Case
    scale_mm : (nv,) array, optional
        Design scale: x = p / scale_mm. Default: the case's start design.
    sensitivity : {'direct', 'fd'}, default 'direct'
        Direct differentiation through the simulation, or forward finite differences.
    fd_step : float, default 1e-6
        Relative step of the finite differences (the paper's kind; CASES.md: 1e-3 is
        2.5-13 % wrong on the robot's late time steps).
    constraint_form : {'linear', 'squared'}, default 'linear'
        g_n = dl_n / limit - 1, or (dl_n / limit)^2 - 1 (smooth where dl_n = 0).
    aggregation : {'none', 'ks', 'pnorm'}, default 'none'
        'none': one constraint per time step (the paper's local formulation). 'ks':
        Kreisselmeier-Steinhauser max(g) + ln(sum exp(rho (g_n - max g))) / rho over each
        window; 'pnorm': (sum r_n^P)^(1/P) - 1 with r_n = g_n + 1 >= 0. Both are
        conservative upper bounds of the window's maximum.
    aggregation_parameter : float, optional
        rho of KS (default 100) or P of the p-norm (default 50).
    windows : int, default 1
        Number of consecutive time windows, each aggregated into one constraint.
    simulate_kw : dict, optional
        Overrides of the simulation settings (t_end, h, rho_inf, solver, ...).

    Attributes
    ----------
    simulations : simulations run; gradient_evaluations : gradients computed;
    evaluations : distinct designs analysed.
    """

    def __init__(self, case, scale_mm=None, *, sensitivity="direct", fd_step=1e-6,
                 constraint_form="linear", aggregation="none", aggregation_parameter=None,
                 windows=1, simulate_kw=None):
        if sensitivity not in SENSITIVITIES:
            raise ModelError(f"sensitivity must be one of {SENSITIVITIES}, got {sensitivity!r}")
        if constraint_form not in CONSTRAINT_FORMS:
            raise ModelError(f"constraint_form must be one of {CONSTRAINT_FORMS}, "
                             f"got {constraint_form!r}")
        aggregation = "none" if aggregation is None else str(aggregation).lower()
        if aggregation not in AGGREGATIONS:
            raise ModelError(f"aggregation must be one of {AGGREGATIONS}, got {aggregation!r}")
        if isinstance(windows, (bool, np.bool_)) or not (isinstance(windows, (int, np.integer))
                                                         and windows >= 1):
            raise ModelError(f"windows must be an integer >= 1, got {windows!r}")
        if not (0 < real_number("fd_step", fd_step) < 1):
            raise ModelError(f"fd_step must lie in (0, 1), got {fd_step!r}")
        case = as_case(case, "FullyCoupledProblem: case")
        self.case = case
        self.nv = len(case.design_names)
        try:
            scale = case._design(scale_mm)
        except CaseError:
            raise ModelError(f"scale_mm must be {self.nv} positive values, got {scale_mm!r}") from None
        self.scale = scale
        self.lower = np.asarray(case.lower_mm, float) / scale
        self.upper = np.asarray(case.upper_mm, float) / scale
        self.limit = float(case.limit_m)
        self.sensitivity = sensitivity
        self.fd_step = float(fd_step)
        self.constraint_form = constraint_form
        self.aggregation = aggregation
        if aggregation != "none":
            par = (_DEFAULT_AGGREGATION_PARAMETER[aggregation] if aggregation_parameter is None
                   else real_number("aggregation_parameter", aggregation_parameter))
            least = 1.0 if aggregation == "pnorm" else 0.0
            if not par > least:
                raise ModelError(f"aggregation_parameter must be > {least:g} for "
                                 f"{aggregation!r}, got {aggregation_parameter!r}")
            self.aggregation_parameter = par
        else:
            self.aggregation_parameter = None
        self.windows = int(windows)
        self.simulate_kw = dict(simulate_kw or {})
        self.mass_ref = float(case.mass(scale))
        self.simulations = 0
        self.gradient_evaluations = 0
        self.evaluations = 0
        self._cache = {}
        self._order = []
        self._cache_size = 32
        self._windows_idx = None
        # exact Hessian of the scaled objective: the beam mass is quadratic in p
        g0 = self._mass_gradient_x(np.ones(self.nv))
        self.objective_hessian = np.column_stack(
            [self._mass_gradient_x(np.ones(self.nv) + e) - g0 for e in np.eye(self.nv)])
        self.objective_hessian = 0.5 * (self.objective_hessian + self.objective_hessian.T)

    # ------------------------------------------------------------------ scaling
    def design_mm(self, x):
        """The design (mm) of a scaled design x."""
        return np.asarray(x, float) * self.scale

    def to_x(self, design_mm):
        """The scaled design of a design in mm."""
        return np.asarray(design_mm, float) / self.scale

    def _mass_gradient_x(self, x):
        grad = np.asarray(self.case.mass_gradient(x * self.scale), float)
        return grad * self.scale / self.mass_ref

    @property
    def constraint_name(self):
        """Name of the deviation measure, e.g. 'eq28'."""
        return f"eq{self.case.formulation}"

    def constraint_labels(self, nt):
        """A label per constraint: the 1-based time step, or the window's step range."""
        if self.aggregation == "none":
            return [str(n) for n in range(1, nt + 1)]
        return [f"{w[0] + 1}-{w[-1] + 1}" for w in self._window_index(nt)]

    def _window_index(self, nt):
        if self._windows_idx is None or self._windows_idx[0] != nt:
            if self.windows > nt:
                raise ModelError(f"windows = {self.windows} exceeds the {nt} time steps")
            self._windows_idx = (nt, np.array_split(np.arange(nt), self.windows))
        return self._windows_idx[1]

    # ------------------------------------------------------------------ history records
    def record_fields(self, ev, active_tol):
        """The problem's part of an iterate's history record (read by the optimizers' monitor):
        design, mass, deviation maximum, violation and active time steps."""
        active = (np.flatnonzero(ev.deviation >= (1.0 - active_tol) * self.limit) + 1).tolist()
        return dict(design_mm=ev.design_mm, mass_kg=ev.mass, max_deviation_m=ev.max_deviation,
                    t_at_max_s=float(ev.t[ev.step_at_max - 1]), step_at_max=ev.step_at_max,
                    max_violation=ev.violation, active_steps={self.constraint_name: active})

    def record_tail(self, ev, active_tol):
        """Fields appended to the record after the monitor's own: the active aggregated
        constraints (their windows' step ranges) when the constraints are aggregated."""
        if self.aggregation == "none":
            return {}
        labels = self.constraint_labels(ev.deviation.size)
        return {"active_constraints": [labels[j] for j in np.flatnonzero(ev.g >= -active_tol)]}

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, x, gradient=True):
        """Analyse the scaled design x (cached: one simulation per design).

        With sensitivity 'direct' every analysis computes the derivatives too (they cost a
        fraction of the simulation). With 'fd' the gradient is computed on request only, by
        n_v more simulations (forward differences, relative step fd_step).

        Raises
        ------
        flexmbs.errors.SimulationError
            If the simulation of the design fails (counted as a simulation).
        """
        x = np.clip(np.asarray(x, float), self.lower, self.upper)
        key = x.tobytes()
        ev = self._cache.get(key)
        if ev is None:
            ev = self._analyse(x)
            self._cache[key] = ev
            self._order.append(key)
            if len(self._order) > self._cache_size:
                self._cache.pop(self._order.pop(0), None)
        if gradient and ev.dg is None:
            self._fd_gradient(ev)
        return ev

    def _analyse(self, x):
        p = self.design_mm(x)
        kw = dict(self.simulate_kw)
        if self.sensitivity == "direct":
            self.simulations += 1
            cg = case_gradients(self.case, p, method="direct", **kw)
            dev, ddev, t = np.asarray(cg.deviation), np.asarray(cg.d_deviation), np.asarray(cg.t)
            self.gradient_evaluations += 1
        else:
            dev, t = self._deviation(p)
            ddev = None
        self.evaluations += 1
        f = float(self.case.mass(p)) / self.mass_ref
        df = self._mass_gradient_x(x)
        g, dg = self._constraints(dev, ddev)
        return Evaluation(x=x, design_mm=p, mass=float(self.case.mass(p)), t=t, deviation=dev,
                          d_deviation=ddev, f=f, df=df, g=g, dg=dg)

    def _deviation(self, p):
        kw = dict(self.simulate_kw)
        kw.setdefault("store", [])
        self.simulations += 1
        r = self.case.simulate(p, **kw)
        return np.asarray(r.deviation, float), np.asarray(r.t, float)

    def _fd_gradient(self, ev):
        ddev = np.zeros((ev.deviation.size, self.nv))
        for i in range(self.nv):
            step = self.fd_step * max(abs(ev.design_mm[i]), 1.0)
            p = ev.design_mm.copy()
            p[i] += step
            dev, _ = self._deviation(p)
            ddev[:, i] = (dev - ev.deviation) / step
        self.gradient_evaluations += 1
        ev.d_deviation = ddev
        ev.g, ev.dg = self._constraints(ev.deviation, ddev)

    def _constraints(self, dev, ddev):
        """Constraints and their x-gradients from the deviation history (m) and its derivatives."""
        r = dev / self.limit
        dr = None if ddev is None else ddev * (self.scale[None, :] / self.limit)
        if self.constraint_form == "squared":
            if dr is not None:
                dr = 2.0 * r[:, None] * dr
            r = r * r
        if self.aggregation == "none":
            return r - 1.0, dr
        return aggregate_constraints(r, dr, self.aggregation, self.aggregation_parameter,
                                     self._window_index(r.size))


# ============================================================================ QP and KKT
def solve_qp(c, H, A, b):
    """Solve the convex QP  min c.v + 1/2 v'Hv  s.t.  A v <= b  (H positive definite).

    Lawson & Hanson's route (Solving Least Squares Problems, ch. 23), used by SLSQP: with
    H = L L' and z = L'v + L^-1 c the problem is a least-distance program min ||z|| s.t.
    G z >= h, whose solution follows from the nonnegative least-squares problem
    min ||E u - e|| (u >= 0), E = [G'; h'], solved by scipy.optimize.nnls.

    Returns
    -------
    v : (n,) solution; lam : (m,) multipliers of A v <= b (>= 0).

    Raises
    ------
    ValueError
        If the constraints are incompatible.
    """
    H = np.asarray(H, float)
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    n = H.shape[0]
    L = np.linalg.cholesky(H)
    Hinv_c = cho_solve((L, True), np.asarray(c, float))
    G = -solve_triangular(L, A.T, lower=True).T          # -A L^-T
    h = -(b + A @ Hinv_c)
    norms = np.linalg.norm(G, axis=1)
    norms[norms == 0] = 1.0
    Gs, hs = G / norms[:, None], h / norms
    E = np.vstack([Gs.T, hs[None, :]])
    e = np.zeros(n + 1)
    e[-1] = 1.0
    u, _ = nnls(E, e, maxiter=50 * max(E.shape))
    r = E @ u - e
    if -r[-1] <= 1e-12:
        raise ValueError("QP constraints are incompatible")
    z = -r[:-1] / r[-1]
    lam = u / (-r[-1]) / norms
    v = solve_triangular(L.T, z, lower=False) - Hinv_c
    return v, lam


def kkt_residual(df, g, dg, x, lower, upper, active_tol=1e-3):
    """Relative first-order optimality (KKT) residual of a design.

        min over lambda, mu_lo, mu_up >= 0 of ||df + J_A' lambda - mu_lo + mu_up|| / ||df||

    (an NNLS problem) over the constraints A within `active_tol` of their limit
    (g_j >= -active_tol) and the bounds that x touches. Zero at a KKT point whose active
    constraints are within active_tol of their limits; about 1 far from the constraints.

    Why a threshold rather than a complementarity term: the vibration samples of the paper's
    mechanisms have design gradients up to 10^4 times the objective's (a deviation sample
    can cross the limit for a change of p of 0.01 mm), so the linearized distance to a
    constraint says nothing about whether it matters; the threshold is on the value.

    Parameters
    ----------
    df : (n,) objective gradient; g : (m,) constraints (<= 0 feasible, relative: 0 is the
    limit); dg : (m, n) their gradients; x, lower, upper : (n,) the design and its bounds
    (same scaling as df and dg).
    active_tol : float, default 1e-3

    Returns
    -------
    residual : float; lam : (m,) the multipliers (zero for the constraints left out).
    """
    df = np.asarray(df, float)
    g = np.asarray(g, float)
    n = df.size
    act = np.flatnonzero(g >= -active_tol)
    btol = 1e-6 * (np.asarray(upper, float) - np.asarray(lower, float))   # bound touched
    at_lo = np.flatnonzero(x <= lower + btol)
    at_up = np.flatnonzero(x >= upper - btol)
    A = np.hstack([np.asarray(dg, float)[act].T,
                   -np.eye(n)[:, at_lo], np.eye(n)[:, at_up]])
    lam = np.zeros(g.size)
    scale = max(np.linalg.norm(df), 1e-300)
    if A.shape[1] == 0:
        return float(np.linalg.norm(df) / scale), lam
    u, rnorm = nnls(A, -df, maxiter=50 * max(A.shape))
    lam[act] = u[:act.size]
    return float(rnorm / scale), lam


# ============================================================================ monitor
class _Stop(Exception):
    """Raised inside scipy's SLSQP callbacks to end the run."""


class _Monitor:
    """Records the iterates, writes the history, applies the stopping test.

    Works on any scaled problem P with lower, upper (scaled bounds), simulations,
    gradient_evaluations, record_fields(ev, active_tol) and record_tail(ev, active_tol)
    (the problem's fields of a history record), whose evaluations have x, f, df, g, dg and
    violation: FullyCoupledProblem here, the general-format problems of problem_fully.py.
    """

    def __init__(self, problem, writer, progress, *, objective_rel_change, constraint_violation,
                 design_rel_change, kkt_tol, active_tol, max_iterations, max_simulations, t0):
        self.P = problem
        self.writer = writer
        self.progress = progress
        self.objective_rel_change = objective_rel_change
        self.constraint_violation = constraint_violation
        self.design_rel_change = design_rel_change
        self.kkt_tol = kkt_tol
        self.active_tol = active_tol
        self.max_iterations = max_iterations
        self.max_simulations = max_simulations
        self.t0 = t0
        self.iterates = []
        self.converged = False
        self.reason = ""
        self.paper_test_iteration = None
        self.last_kkt = None
        self.stalled = 0

    def stationary(self, ev, why):
        """The optimizer cannot move from the last iterate ev: converged if it is feasible and
        satisfies the first-order test (the paper's objective change is then zero)."""
        kkt = self.last_kkt
        if ev.violation < self.constraint_violation and kkt is not None and kkt < self.kkt_tol:
            self.converged = True
            self.reason = (f"{why}: constraint violation {ev.violation:.1e} < "
                           f"{self.constraint_violation:g} and KKT residual {kkt:.1e} < "
                           f"{self.kkt_tol:g}")
        else:
            self.reason = (f"{why}, but not a converged point (constraint violation "
                           f"{ev.violation:.1e}, KKT residual {kkt:.1e})")

    @property
    def iteration(self):
        """Iterations done (the start is iteration 0)."""
        return max(len(self.iterates) - 1, 0)

    def record(self, ev, **extra):
        """Record an iterate; return True when the run must stop (converged or a limit)."""
        P = self.P
        kkt, _ = kkt_residual(ev.df, ev.g, ev.dg, ev.x, P.lower, P.upper, self.active_tol)
        self.last_kkt = kkt
        prev = self.iterates[-1] if self.iterates else None
        k = len(self.iterates)
        obj_change = None if prev is None else abs(ev.f - prev.f) / max(abs(ev.f), 1e-300)
        des_change = (None if prev is None else
                      float(np.max(np.abs(ev.x - prev.x) / np.maximum(np.abs(ev.x), 1e-300))))
        record = dict(iteration=k)
        record.update(P.record_fields(ev, self.active_tol))
        record.update(objective_rel_change=obj_change, design_rel_change=des_change,
                      kkt_residual=kkt, simulations=P.simulations,
                      gradient_evaluations=P.gradient_evaluations,
                      wall_time_s=time.perf_counter() - self.t0)
        record.update(P.record_tail(ev, self.active_tol))
        record.update(extra)
        self.iterates.append(ev)
        self.writer.write(record)
        if self.progress is not None:
            self.progress(self.writer.records[-1])
        if prev is not None:
            paper = (obj_change < self.objective_rel_change
                     and ev.violation < self.constraint_violation
                     and (self.design_rel_change is None or des_change < self.design_rel_change))
            if paper and self.paper_test_iteration is None:
                self.paper_test_iteration = k
            if paper and kkt < self.kkt_tol:
                self.converged = True
                self.reason = (f"relative objective change {obj_change:.2e} < "
                               f"{self.objective_rel_change:g}, constraint violation "
                               f"{ev.violation:.1e} < {self.constraint_violation:g}"
                               + ("" if self.design_rel_change is None else
                                  f", relative design change {des_change:.2e} < "
                                  f"{self.design_rel_change:g}")
                               + f" and KKT residual {kkt:.1e} < {self.kkt_tol:g}")
                return True
        self.stalled = self.stalled + 1 if (des_change is not None and des_change < 1e-10) else 0
        if self.stalled >= 5:
            self.reason = ("no progress: the design did not change in 5 iterations (KKT residual "
                           f"{kkt:.1e}, constraint violation {ev.violation:.1e})")
            return True
        if k >= self.max_iterations:
            self.reason = f"maximum number of iterations ({self.max_iterations}) reached"
            return True
        if P.simulations >= self.max_simulations:
            self.reason = f"maximum number of simulations ({self.max_simulations}) reached"
            return True
        return False


# ============================================================================ optimizers
def _model_merit(ev, d, B, nu):
    lin = ev.g + ev.dg @ d
    return float(ev.df @ d + 0.5 * d @ B @ d + nu * max(0.0, lin.max()))


def _sqp_step(ev, B, x, lo, hi, nu, g=None):
    """Solve the elastic trust-region QP at ev; return (d, t, lam_c).

    min df.d + 1/2 d'Bd + nu (t + t^2 / 2)  s.t.  g + J d <= t, t >= 0, lo <= d <= hi.
    Raises FloatingPointError if the solution is not accurate (ill-conditioned B).
    """
    n = x.size
    g = ev.g if g is None else g
    m = g.size
    H = np.zeros((n + 1, n + 1))
    H[:n, :n] = B
    H[n, n] = nu                       # nu (t + t^2 / 2): exact penalty, balanced scaling
    A = np.zeros((m + 1 + 2 * n, n + 1))
    A[:m, :n] = ev.dg
    A[:m, n] = -1.0
    A[m, n] = -1.0
    A[m + 1:m + 1 + n, :n] = np.eye(n)
    A[m + 1 + n:, :n] = -np.eye(n)
    bb = np.concatenate([-g, [0.0], hi, -lo])
    v, lam = solve_qp(np.concatenate([ev.df, [nu]]), H, A, bb)
    tol = 1e-8 * (1.0 + np.abs(bb))
    if not np.all(np.isfinite(v)) or np.any(A @ v - bb > tol):
        raise FloatingPointError("inaccurate QP solution")
    return v[:n], max(v[n], 0.0), lam[:m]


def _floor_eigenvalues(B, ratio=1e-4):
    """B symmetrized with its eigenvalues raised to at least ratio * the largest one."""
    w, V = np.linalg.eigh(0.5 * (B + B.T))
    w = np.maximum(w, ratio * max(w.max(), 1e-12))
    return (V * w) @ V.T


def _least_violation(ev, lo, hi):
    """The smallest linearized violation max(0, max(g + J d)) within lo <= d <= hi (an LP)."""
    n = lo.size
    m = ev.g.size
    A = np.hstack([ev.dg, -np.ones((m, 1))])
    res = linprog(np.concatenate([np.zeros(n), [1.0]]), A_ub=A, b_ub=-ev.g,
                  bounds=list(zip(lo, hi)) + [(0.0, None)], method="highs")
    return float(res.x[n]) if res.status == 0 else 0.0


def _run_sqp(P, mon, x0, *, radius0, radius_max, eta=0.05, nu0=10.0, nu_max=1e4, fidelity=0.1):
    """Trust-region SQP with an l_inf elastic QP, second-order correction and damped BFGS.

    Iteration: QP step d in the relative trust region |d_i| <= r x_i; if the l_inf merit
    f + nu max(0, max g) does not decrease by at least eta times the model's prediction, one
    second-order correction (the QP again with the constraint values corrected by the
    trial's, g(x+d) - J d: a step back onto the curved constraints, the cure of the Maratos
    effect) is tried, then the radius shrinks. The penalty nu grows when the multipliers
    require it (nu >= 1.5 sum lambda) or when the step does not reduce the linearized
    violation by half of what the trust region allows.
    """
    ev = P.evaluate(x0, gradient=True)
    B = P.objective_hessian.copy()
    nu = nu0
    r = radius0
    rejected = 0
    soc_steps = 0
    if mon.record(ev, trust_radius=r, rejected_steps=0, penalty=nu):
        return

    def qp(nu, g=None):
        nonlocal B
        try:
            return _sqp_step(ev, B, ev.x, lo, hi, nu, g)
        except FloatingPointError:
            B = P.objective_hessian.copy()          # restart the quasi-Newton matrix
            return _sqp_step(ev, B, ev.x, lo, hi, nu, g)

    while True:
        x = ev.x
        lo = np.maximum(P.lower - x, -r * np.abs(x))
        hi = np.minimum(P.upper - x, r * np.abs(x))
        viol0 = max(0.0, ev.g.max())
        try:
            d, t, lam_c = qp(nu)
            if t > 1e-9 and nu < nu_max:
                # infeasible linearization: the step must remove at least half of the
                # violation that the trust region allows to remove
                t_min = _least_violation(ev, lo, hi)
                while viol0 - t < 0.5 * (viol0 - t_min) and nu < nu_max:
                    nu = min(10.0 * nu, nu_max)
                    d, t, lam_c = qp(nu)
        except FloatingPointError:
            mon.reason = "the QP subproblem could not be solved accurately"
            return
        if t <= 1e-9:
            nu = max(nu, 1.5 * float(lam_c.sum()))
        pred = nu * viol0 - _model_merit(ev, d, B, nu)
        step_rel = float(np.max(np.abs(d) / np.abs(x)))
        if pred <= 1e-14 * max(abs(ev.f), 1.0) or step_rel < 1e-12:
            mon.stationary(ev, "the QP step vanished (a stationary point of the model)")
            return
        phi0 = ev.f + nu * viol0
        xt = np.clip(x + d, P.lower, P.upper)
        try:
            evt = P.evaluate(xt, gradient=(P.sensitivity == "direct"))
            rho = (phi0 - (evt.f + nu * evt.violation)) / pred
        except SimulationError:
            evt, rho = None, -np.inf
        if rho < eta and evt is not None and evt.violation > 0:
            # second-order correction
            try:
                d2, _, _ = qp(nu, g=evt.g - ev.dg @ d)
                xs = np.clip(x + d2, P.lower, P.upper)
                evs = P.evaluate(xs, gradient=(P.sensitivity == "direct"))
                rho_s = (phi0 - (evs.f + nu * evs.violation)) / pred
            except (SimulationError, FloatingPointError):
                rho_s = -np.inf
            if rho_s >= eta:
                evt, rho, xt, d = evs, rho_s, xs, d2
                soc_steps += 1
        if fidelity is not None and rho >= eta:
            lin = ev.g + ev.dg @ (xt - x)
            near = np.maximum(ev.g, evt.g) > -0.25
            if near.any() and np.max(np.abs(evt.g[near] - lin[near])) > fidelity:
                rho = -np.inf
        if rho >= eta:
            evt = P.evaluate(xt, gradient=True)
            # damped BFGS on the Lagrangian (Powell), multipliers of the QP
            s = evt.x - x
            y = (evt.df + evt.dg.T @ lam_c) - (ev.df + ev.dg.T @ lam_c)
            Bs = B @ s
            sBs = float(s @ Bs)
            sy = float(s @ y)
            if sBs > 0:
                if sy < 0.2 * sBs:
                    theta = 0.8 * sBs / (sBs - sy)
                    y = theta * y + (1.0 - theta) * Bs
                    sy = float(s @ y)
                B = _floor_eigenvalues(B + np.outer(y, y) / sy - np.outer(Bs, Bs) / sBs)
            if rho > 0.75 and step_rel > 0.9 * r:
                r = min(2.0 * r, radius_max)
            elif rho < 0.25:
                r = 0.5 * r
            ev = evt
            if mon.record(ev, trust_radius=r, rejected_steps=rejected, penalty=nu,
                          step_ratio=rho, second_order_corrections=soc_steps):
                return
            rejected = 0
        else:
            rejected += 1
            r = 0.5 * min(r, step_rel)
            if r < 1e-10:
                mon.reason = f"the trust region collapsed (radius {r:.1e}): no further progress"
                return
            if P.simulations >= mon.max_simulations:
                mon.reason = f"maximum number of simulations ({mon.max_simulations}) reached"
                return


def _run_mma(P, mon, x0, opt, max_inner=20):
    """Svanberg's MMA, or GCMMA with inner iterations (the default), on the scaled problem."""
    ev = P.evaluate(x0, gradient=True)
    if mon.record(ev, mma_inner_iterations=0):
        return
    while True:
        xt = opt.step(ev.x, ev.f, ev.df, ev.g, ev.dg)
        failures = 0
        while True:
            try:
                evt = P.evaluate(xt, gradient=(P.sensitivity == "direct"))
            except SimulationError:
                failures += 1
                if failures > max_inner:
                    raise
                xt = 0.5 * (xt + ev.x)        # a failed simulation: fall back halfway
                continue
            if opt.conservative(evt.f, evt.g) or opt.inner >= max_inner:
                break
            xt = opt.tighten(evt.f, evt.g)
        ev = P.evaluate(xt, gradient=True)
        if mon.record(ev, mma_inner_iterations=opt.inner):
            return
        if P.simulations >= mon.max_simulations:
            mon.reason = f"maximum number of simulations ({mon.max_simulations}) reached"
            return


def _run_slsqp(P, mon, x0, ftol=1e-10):
    """scipy's SLSQP without move limits; iterates recorded where the Jacobian is requested."""
    def fun(x):
        ev = P.evaluate(x, gradient=False)
        return ev.f

    def jac(x):
        ev = P.evaluate(x, gradient=True)
        if mon.record(ev):
            raise _Stop
        return ev.df

    def cons(x):
        return -P.evaluate(x, gradient=False).g

    def cons_jac(x):
        return -P.evaluate(x, gradient=True).dg

    try:
        res = minimize(fun, x0, jac=jac, method="SLSQP", bounds=list(zip(P.lower, P.upper)),
                       constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}],
                       options=dict(maxiter=mon.max_iterations + 1, ftol=ftol))
        if not mon.reason:
            mon.reason = f"SLSQP stopped: {res.message}"
    except _Stop:
        pass


# ============================================================================ driver
def _check_stopping(obj_tol, viol_tol, des_tol, kkt_tol, active_tol, max_iterations,
                    max_simulations):
    """Check the stopping settings (ModelError naming the bad one); return the two limits as
    integers."""
    for name, val in (("objective_rel_change", obj_tol), ("constraint_violation", viol_tol),
                      ("kkt_tol", kkt_tol), ("active_tol", active_tol)):
        real_number(name, val, positive=True)
    if des_tol is not None:
        real_number("design_rel_change (or None)", des_tol, positive=True)
    return (whole_number("max_iterations", max_iterations, 1),
            whole_number("max_simulations", max_simulations, 1))


def _mma_settings(mma_options):
    """MMA keyword arguments and the GCMMA inner-iteration limit from `mma_options`."""
    if mma_options is not None and not isinstance(mma_options, dict):
        raise ModelError(f"mma_options must be a dict or None, got {mma_options!r}")
    mma_kw = dict(mma_options or {})
    max_inner = whole_number("mma_options max_inner", mma_kw.pop("max_inner", 20), 1)
    return mma_kw, max_inner


def optimize_fully(case, start_mm=None, *, sensitivity="direct", optimizer="mma",
                   constraint_form="linear", aggregation="none", aggregation_parameter=None,
                   windows=1, fd_step=1e-6, scale_mm=None, objective_rel_change=None,
                   constraint_violation=None, design_rel_change=None, kkt_tol=1e-3,
                   active_tol=1e-3, max_iterations=None, max_simulations=1000,
                   trust_radius=0.2, max_trust_radius=0.5, model_fidelity=0.1,
                   mma_options=None, history=None, progress=None, simulate_kw=None):
    """Optimize a case with the fully coupled method (paper 4 and 5.4).

    Parameters
    ----------
    case : flexmbs.cases.Case, or a case name, path or dict (then loaded with load_case)
    start_mm : array, optional
        Starting design (mm); default `case.start_mm`.
    sensitivity : {'direct', 'fd'}, default 'direct'
        Direct differentiation (exact, one simulation per design) or the paper's forward
        finite differences (relative step `fd_step`, n_v more simulations per gradient).
    optimizer : {'mma', 'sqp', 'slsqp'}, default 'mma'
        Svanberg's globally convergent MMA (GCMMA), the trust-region SQP, or plain scipy
        SLSQP (see the module docstring).
    constraint_form : {'linear', 'squared'}, default 'linear'
        dl_n / limit - 1 <= 0 or (dl_n / limit)^2 - 1 <= 0.
    aggregation : {'none', 'ks', 'pnorm'}, default 'none'
        Local formulation (one constraint per time step), or aggregated constraints, eq. (22).
    aggregation_parameter : float, optional
        KS rho (default 100) or p-norm P (default 50).
    windows : int, default 1
        Number of time windows aggregated separately.
    fd_step : float, default 1e-6
        Relative finite-difference step.
    scale_mm : array, optional
        Design scale, x = p / scale_mm; default the start design (x = 1 at the start).
    objective_rel_change, constraint_violation, design_rel_change : float, optional
        The paper's stopping test; defaults from the case file's [optimizer.fully] table
        (robot: 1e-3 and 1e-6; four-bar: also 1e-3 on the design), else 1e-3, 1e-6, none.
    kkt_tol : float, default 1e-3
        The first-order test that must hold too (relative KKT residual, see kkt_residual).
    active_tol : float, default 1e-3
        A time step counts as active when its deviation is >= (1 - active_tol) limit (history,
        Table 8); constraints within active_tol of 0 enter the KKT test.
    max_iterations : int, optional
        Default: [optimizer.fully] max_iterations of the case file, else 100.
    max_simulations : int, default 1000
    trust_radius, max_trust_radius : float, default 0.2 and 0.5
        SQP: initial and largest relative trust region, |p_i - p_i,k| <= r p_i,k.
    model_fidelity : float or None, default 0.1
        SQP: a step is also rejected when a constraint near its limit (g > -0.25 at either end)
        differs from its linearization by more than this (0.1: a tenth of the limit); keeps
        the steps where the linearized vibration samples mean something. None: merit only.
    mma_options : dict, optional
        Keyword arguments of `flexmbs.optimize.mma.MMA` (conservative, move, asyinit, ...)
        and max_inner (GCMMA inner iterations per iteration, default 20).
    history : str, path or HistoryWriter, optional
        File receiving one JSON line per iteration as the run goes (iteration 0: the start).
    progress : callable, optional
        Called with each history record.
    simulate_kw : dict, optional
        Overrides of the simulation settings (t_end, h, rho_inf, solver, ...).

    Returns
    -------
    OptimizationResult
        method 'fully'; iterations = optimizer iterations (accepted designs after the start);
        inner_iterations None; simulations = all simulations (trial designs, GCMMA inner
        iterations and finite differences included); details: gradient_evaluations,
        optimizer, sensitivity, kkt_residual, max_violation, active_steps,
        paper_test_iteration (the first iteration at which the paper's test alone held),
        settings.

    Raises
    ------
    CaseError
        Bad start design. ModelError: bad option.
    SimulationError
        If the simulation of the start design fails.
    """
    t0 = time.perf_counter()
    if not isinstance(optimizer, str) or optimizer not in OPTIMIZERS:
        raise ModelError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")
    case = as_case(case, "optimize_fully: case")
    p0 = case.start_design(start_mm)
    progress = _progress_callback(progress)
    settings = dict(getattr(case, "optimizer", {}).get("fully", {}))
    obj_tol = (settings.get("objective_rel_change", 1e-3) if objective_rel_change is None
               else objective_rel_change)
    viol_tol = (settings.get("constraint_violation", 1e-6) if constraint_violation is None
                else constraint_violation)
    des_tol = settings.get("design_rel_change") if design_rel_change is None else design_rel_change
    max_it = settings.get("max_iterations", 100) if max_iterations is None else max_iterations
    max_it, max_simulations = _check_stopping(obj_tol, viol_tol, des_tol, kkt_tol, active_tol,
                                              max_it, max_simulations)
    real_number("trust_radius", trust_radius, positive=True)
    real_number("max_trust_radius", max_trust_radius, positive=True)
    if not (trust_radius <= max_trust_radius):
        raise ModelError(f"need 0 < trust_radius <= max_trust_radius, got {trust_radius!r}, "
                         f"{max_trust_radius!r}")
    if model_fidelity is not None:
        real_number("model_fidelity (or None)", model_fidelity, positive=True)
    if simulate_kw is not None and not isinstance(simulate_kw, dict):
        raise ModelError(f"simulate_kw must be a dict of simulate's keyword arguments or None, "
                         f"got {simulate_kw!r}")
    mma_kw, max_inner = _mma_settings(mma_options)

    problem = FullyCoupledProblem(
        case, p0 if scale_mm is None else scale_mm, sensitivity=sensitivity, fd_step=fd_step,
        constraint_form=constraint_form, aggregation=aggregation,
        aggregation_parameter=aggregation_parameter, windows=windows, simulate_kw=simulate_kw)
    if optimizer == "mma":
        opt = MMA(problem.lower, problem.upper, **mma_kw)     # validates the options early
    writer = history if isinstance(history, HistoryWriter) else HistoryWriter(history)
    own_writer = not isinstance(history, HistoryWriter)
    mon = _Monitor(problem, writer, progress, objective_rel_change=obj_tol,
                   constraint_violation=viol_tol, design_rel_change=des_tol, kkt_tol=kkt_tol,
                   active_tol=active_tol, max_iterations=int(max_it),
                   max_simulations=int(max_simulations), t0=t0)
    x0 = problem.to_x(p0)
    try:
        if optimizer == "sqp":
            _run_sqp(problem, mon, x0, radius0=trust_radius, radius_max=max_trust_radius,
                     fidelity=model_fidelity)
        elif optimizer == "mma":
            _run_mma(problem, mon, x0, opt, max_inner=max_inner)
        else:
            _run_slsqp(problem, mon, x0)
    finally:
        if own_writer:
            writer.close()
    if not mon.iterates:
        raise ModelError("the fully coupled optimization recorded no iterate")
    ev = mon.iterates[-1]                     # the result: the last accepted design
    last = writer.records[-1]
    details = dict(
        gradient_evaluations=problem.gradient_evaluations, optimizer=optimizer,
        sensitivity=sensitivity, formulation=str(case.formulation),
        constraint_form=constraint_form, aggregation=problem.aggregation,
        aggregation_parameter=problem.aggregation_parameter, windows=problem.windows,
        kkt_residual=mon.last_kkt, max_violation=ev.violation,
        active_steps=last["active_steps"], paper_test_iteration=mon.paper_test_iteration,
        t_end=float(ev.t[-1]), step_at_max=ev.step_at_max, scale_mm=problem.scale,
        stopping=dict(objective_rel_change=obj_tol, constraint_violation=viol_tol,
                      design_rel_change=des_tol, kkt_tol=kkt_tol, active_tol=active_tol),
        fd_step=fd_step if sensitivity == "fd" else None)
    if optimizer == "mma":
        details["mma_inner_iterations"] = sum(r.get("mma_inner_iterations") or 0
                                              for r in writer.records)
    elif optimizer == "sqp":
        details["rejected_steps"] = sum(r.get("rejected_steps") or 0 for r in writer.records)
        details["second_order_corrections"] = last.get("second_order_corrections", 0)
    return OptimizationResult(
        method="fully", case=getattr(case, "name", "case"), design_mm=ev.design_mm.copy(),
        mass_kg=float(ev.mass), iterations=mon.iteration, inner_iterations=None,
        simulations=problem.simulations, converged=mon.converged,
        reason=mon.reason or "stopped", history=list(writer.records),
        max_deviation_m=ev.max_deviation, wall_time_s=time.perf_counter() - t0,
        start_mm=p0.copy(), details=details, t=ev.t.copy(), deviation=ev.deviation.copy())
