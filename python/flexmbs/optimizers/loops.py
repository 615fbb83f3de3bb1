"""The optimizer loops of the fully coupled method (paper sections 4 and 5.4), independent
of what is optimized: they work on any scaled problem P (`flexmbs.methods.fully.ScaledProblem`)
with lower, upper (scaled bounds), simulations, gradient_evaluations, sensitivity,
objective_hessian, record_fields(ev, active_tol), record_tail(ev, active_tol) and
evaluate(x, gradient) returning evaluations with x, f, df, g, dg and violation.

Optimizers. docs/paper-cases.md reports that plain SLSQP fails from three of the paper's four robot
starts: the deviation grows like p^-3 to p^-4, the first linearized step lands on the bounds
with hundreds of violated steps, and the late time steps are vibration samples whose
linearizations hold only for small design changes (on the four-bar a sample can cross the
limit for a change of p of 0.01 mm). Hence:

``_run_mma`` (default)
    Svanberg's globally convergent method of moving asymptotes, GCMMA
    (`flexmbs.optimizers.mma`): each iteration minimizes convex, separable, reciprocal-type
    approximations of the objective and of every constraint between moving asymptotes, the
    conservative approximation of structural optimization codes; inner iterations (one
    simulation each) raise the curvature of any approximation found not conservative at the
    new design. Converges from all four of the paper's starts (Table 6) in 7-8 iterations.
``_run_sqp``
    An active-set SQP in a relative trust region |d_i| <= r x_i. Each iteration solves the QP
    min grad f . d + 1/2 d'Bd s.t. g + J d <= t, the bounds and the trust region, with an
    elastic variable t >= 0 (l_inf penalty, so it always has a solution), by the
    least-distance programming route of Lawson & Hanson (scipy's NNLS), the same core as
    SLSQP's QP solver. B starts at the Hessian of the objective (exact for a mass) and is
    updated by damped BFGS on the Lagrangian (Powell); steps are accepted on the ratio of
    actual to predicted decrease of the l_inf merit function f + nu max(0, max g) (Nocedal &
    Wright, Numerical Optimization, 2nd ed., sections 18.5 and 15.5), with one second-order
    correction against the Maratos effect, and rejected when a constraint near its limit
    differs from its linearization by more than `model_fidelity`; r grows or shrinks with
    the ratio.
``_run_slsqp``
    scipy's SLSQP as it is (the paper's kind of optimizer, without move limits), kept as a
    baseline: it stalls on the bounds from the starts docs/paper-cases.md names.

Stopping test (`_Monitor`, every optimizer, applied to the iterates; iteration 0 is the
start): the paper's, i.e. the relative change of the objective between two iterations < 1e-3
and the relative constraint violation max(0, max g) <= FEASIBILITY_TOL (flexmbs.problem,
1e-6; optionally also the relative
change of the design variables < 1e-3, as the paper's four-bar); together with a first-order
test, so that it cannot stop on a plateau: the KKT residual
||grad f + sum lambda_j grad g_j - mu_lo + mu_up|| / ||grad f|| (lambda, mu >= 0 by NNLS over
the constraints within `active_tol` of their limit and the bounds touched) must be below
`kkt_tol`. A run whose design stops changing (5 iterations) ends as not converged.
"""
from __future__ import annotations

import time

import numpy as np

from flexmbs.errors import SimulationError

__all__ = ["kkt_residual", "solve_qp"]


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
    from scipy.linalg import cho_solve, solve_triangular
    from scipy.optimize import nnls

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
    df : (n,) objective gradient
    g : (m,) constraints (<= 0 feasible, relative: 0 is the limit)
    dg : (m, n) their gradients
    x, lower, upper : (n,) the design and its bounds (same scaling as df and dg)
    active_tol : float, default 1e-3

    Returns
    -------
    residual : float; lam : (m,) the multipliers (zero for the constraints left out).
    """
    from scipy.optimize import nnls

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
    violation (flexmbs.methods.fully.ScaledProblem).
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
        if ev.violation <= self.constraint_violation and kkt is not None and kkt < self.kkt_tol:
            self.converged = True
            self.reason = (f"{why}: constraint violation {ev.violation:.1e} <= "
                           f"{self.constraint_violation:g} and KKT residual {kkt:.1e} < "
                           f"{self.kkt_tol:g}")
        else:
            self.reason = (f"{why}, but not a converged point (the last iterate's constraint "
                           f"violation {ev.violation:.1e}, KKT residual {kkt:.1e})")

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
        take_log = getattr(P, "take_log", None)
        self.writer.write(record, file_extra=None if take_log is None else take_log())
        if self.progress is not None:
            self.progress(self.writer.records[-1])
        if prev is not None:
            paper = (obj_change < self.objective_rel_change
                     and ev.violation <= self.constraint_violation
                     and (self.design_rel_change is None or des_change < self.design_rel_change))
            if paper and self.paper_test_iteration is None:
                self.paper_test_iteration = k
            if paper and kkt < self.kkt_tol:
                self.converged = True
                self.reason = (f"relative objective change {obj_change:.2e} < "
                               f"{self.objective_rel_change:g}, constraint violation "
                               f"{ev.violation:.1e} <= {self.constraint_violation:g}"
                               + ("" if self.design_rel_change is None else
                                  f", relative design change {des_change:.2e} < "
                                  f"{self.design_rel_change:g}")
                               + f" and KKT residual {kkt:.1e} < {self.kkt_tol:g}")
                return True
        self.stalled = self.stalled + 1 if (des_change is not None and des_change < 1e-10) else 0
        if self.stalled >= 5:
            self.reason = ("no progress: the design did not change in 5 iterations (the last "
                           f"iterate's KKT residual {kkt:.1e}, constraint violation "
                           f"{ev.violation:.1e})")
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
    from scipy.optimize import linprog

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
    from scipy.optimize import minimize

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
