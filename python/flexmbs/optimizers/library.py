"""Library optimizers (NLopt) for the fully coupled method on a general-format problem.

`run_nlopt(P, mon, x0, algorithm)` minimizes a `flexmbs.methods.fully.ScaledProblem`
with one of NLopt's gradient-based algorithms for inequality-constrained problems:

    'nlopt-mma'    Svanberg's MMA (NLopt's LD_MMA, the globally convergent CCSA form)
    'nlopt-ccsaq'  CCSA with quadratic conservative approximations (LD_CCSAQ)
    'nlopt-slsqp'  Kraft's SLSQP (LD_SLSQP)

The design is mapped to the unit box z in [0, 1], so that every variable has the same range
for the optimizer's move limits and asymptotes: linearly, z = (x - lower) / (upper - lower),
or logarithmically, z = log(x / lower) / log(upper / lower), for a variable whose bounds span
a decade or more (``log_scale``, default; on the four-bar, 15-500 mm, the linear map sent
CCSAQ from 250 mm to the lower bounds in one step and into an infeasible stationary point,
docs/optimizers.md). NLopt's CCSA dual problem is solved to 1e-8 (``dual_ftol_rel``) in at
most 200 evaluations instead of NLopt's 1e-14 and 100000. The constraints go in as ONE vector constraint with its Jacobian (``add_inequality_mconstraint``),
not one Python callback per row.

Screening of the per-step constraints (``screen``, default -0.3): a problem with
``over = "every_step"`` has one row per time step (1001 on the four-bar, 1301 on the robot),
and the optimizers' own subproblems grow with the number of rows (NLopt's MMA dual solver and
SLSQP's QP are dense in them). Only the peaks of each constraint's history near the limit
(g > screen) or near the worst row (within |screen| of it), each with its two neighbouring
steps, are passed to the optimizer (the paper's active set: the steps where the constraint
binds).
Every simulation still computes all rows, so each iterate is checked on all of them: when the
largest violation lies in a row left out, the screened set is enlarged (the rows g > screen
and the local maxima at that design are added) and the optimizer restarts from that design.
``screen=None`` passes every row.

NLopt may report success at an infeasible point; the design returned here is chosen by this
module from all the designs simulated (checked on all rows): the converged iterate if the
stopping test of `flexmbs.methods.fully._Monitor` held, else the lightest one with violation
below the tolerance, else the least violated one.
"""
from __future__ import annotations

import numpy as np

from flexmbs.errors import ModelError, SimulationError
from flexmbs.optimizers.loops import kkt_residual

__all__ = ["NLOPT_ALGORITHMS", "run_nlopt", "screened_rows", "preload"]

#: optimizer name -> NLopt algorithm name
NLOPT_ALGORITHMS = {"nlopt-mma": "LD_MMA", "nlopt-ccsaq": "LD_CCSAQ", "nlopt-slsqp": "LD_SLSQP"}


def preload():
    """Import now what the optimizers import on first use (scipy.linalg for the ESL,
    scipy.optimize, nlopt when installed), for a command line that handles Ctrl-C. CPython
    marks a KeyboardInterrupt as unhandled when it escapes an exec() or eval() of a string,
    which imports run (dataclasses, namedtuples), even when the caller then handles it: a
    Ctrl-C that landed in such an import mid-run printed the resume line and then ended the
    process by SIGINT (Py_RunMain's exit_sigint) instead of exit status 130 (one early Ctrl-C
    in four on `flexmbs optimize robot_2dof`, measured; none in 70 with this)."""
    import importlib
    for name in ("scipy.linalg", "scipy.optimize", "nlopt"):
        try:
            importlib.import_module(name)
        except ImportError:    # nlopt's optimizers say so when they are asked for
            pass


def screened_rows(g, names, screen):
    """Indices of the rows of g kept by screening: the local maxima of each constraint's
    history (a run of rows of the same response; a single row is its own maximum) that lie
    above `screen` or within |screen| of the largest value, each with its two neighbours in the
    history (so that a peak moving by a time step stays represented).

    Parameters
    ----------
    g : (ng,) constraint values (g <= 0 feasible, relative to the limit).
    names : (ng,) the response of each row (Evaluation.constraint_names).
    screen : float or None
        Threshold (e.g. -0.3: within 30 % of the limit); None keeps every row.
    """
    g = np.asarray(g, float)
    if screen is None or g.size == 0:
        return np.arange(g.size)
    level = min(screen, g.max() + screen)
    keep = np.zeros(g.size, bool)
    start = 0
    for k in range(1, g.size + 1):
        if k == g.size or names[k] != names[start]:
            seg = g[start:k]
            left = np.concatenate([[-np.inf], seg[:-1]])
            right = np.concatenate([seg[1:], [-np.inf]])
            peak = (seg >= left) & (seg >= right) & (seg > level)
            near = peak.copy()
            near[1:] |= peak[:-1]
            near[:-1] |= peak[1:]
            keep[start:k] = near
            start = k
    return np.flatnonzero(keep)


class _Restart(Exception):
    """The screened set misses the most violated row: enlarge it and start again."""


class _Feasible(Exception):
    """The feasibility phase found a feasible design."""


class _Finished(Exception):
    """The monitor's stopping test or a limit ended the run."""


def run_nlopt(P, mon, x0, optimizer, *, screen=-0.3, max_restarts=20, xtol_rel=1e-8,
              ftol_rel=1e-10, params=None, initial_step=None, log_scale=True,
              feasibility_phase=True):
    """Run an NLopt algorithm on the scaled problem P from x0, recording every new design
    simulated with `mon` (a fully._Monitor), which applies the stopping test.

    feasibility_phase: from an infeasible start, first minimize the largest constraint value
    (min s subject to g_i(x) <= s, the same algorithm and screened rows) until a simulated
    design is feasible on all rows, then minimize the objective from there.

    Returns
    -------
    (final ScaledEvaluation, details dict: nlopt_result, restarts, failed_simulations,
    feasibility_simulations (simulations of the feasibility phase), screened_rows (rows given
    to the optimizer in its last run), total_rows, screen)
    """
    import nlopt

    if optimizer not in NLOPT_ALGORITHMS:
        raise ModelError(f"optimizer must be one of {tuple(NLOPT_ALGORITHMS)} here, "
                         f"got {optimizer!r}")
    if screen is not None and not (isinstance(screen, (int, float)) and -np.inf < screen <= 0):
        raise ModelError(f"screen must be a number <= 0 (e.g. -0.3) or None, got {screen!r}")
    algorithm = getattr(nlopt, NLOPT_ALGORITHMS[optimizer])
    lo, hi = np.asarray(P.lower, float), np.asarray(P.upper, float)
    # z in [0, 1]: linear, or logarithmic for variables whose bounds span a decade or more
    log = np.zeros(lo.size, bool) if not log_scale else (lo > 0) & (hi > 10 * lo)
    a = np.where(log, np.log(np.where(log, lo, 1.0)), lo)
    b = np.where(log, np.log(np.where(log, hi, 1.0)), hi)
    width = np.where(b > a, b - a, 1.0)
    nv = P.nv

    def to_x(z):
        u = a + np.clip(z, 0.0, 1.0) * width
        return np.where(log, np.exp(u), u)

    def to_z(x):
        return (np.where(log, np.log(np.where(log, x, 1.0)), x) - a) / width

    def dx_dz(x):
        return np.where(log, x, 1.0) * width

    seen = set()
    state = dict(rows=None, restarts=0, result=None, failures=0, phase=1, feasibility_sims=0)

    def analyse(z):
        ev = P.evaluate(to_x(z[:nv]), gradient=True)
        key = ev.x.tobytes()
        if key not in seen:
            seen.add(key)
            if state["phase"] == 0:
                state["feasibility_sims"] += 1
            if mon.record(ev):
                raise _Finished
            if P.simulations >= mon.max_simulations:
                mon.reason = f"maximum number of simulations ({mon.max_simulations}) reached"
                raise _Finished
            if state["phase"] == 0 and ev.violation <= mon.constraint_violation:
                state["restart_at"] = ev
                raise _Feasible
            rows = state["rows"]
            if ev.g.size and rows.size < ev.g.size and state["restarts"] < max_restarts:
                worst = int(np.argmax(ev.g))
                if ev.g[worst] > mon.constraint_violation and worst not in set(rows.tolist()):
                    state["restart_at"] = ev
                    raise _Restart
        return ev

    ev = P.evaluate(x0, gradient=True)
    names = ev.evaluation.constraint_names
    state["rows"] = screened_rows(ev.g, names, screen)
    z = to_z(np.asarray(x0, float))
    if feasibility_phase and ev.violation > mon.constraint_violation:
        state["phase"] = 0
    step = initial_step
    while True:
        rows = state["rows"]
        phase = state["phase"]
        n = nv + (1 if phase == 0 else 0)
        opt = nlopt.opt(algorithm, n)
        zl, zu = np.zeros(n), np.ones(n)
        if phase == 0:
            # s, the largest constraint value: from that of z down to -1
            g0 = P.evaluate(to_x(z), gradient=True).g
            s0 = float(g0[rows].max()) if rows.size else 0.0
            zl[-1], zu[-1] = -1.0, max(s0, 0.0) + 1.0
            z = np.append(np.clip(z, 0.0, 1.0), s0)
        opt.set_lower_bounds(zl)
        opt.set_upper_bounds(zu)
        opt.set_xtol_rel(xtol_rel)
        opt.set_ftol_rel(ftol_rel)
        opt.set_maxeval(max(mon.max_simulations - P.simulations, 1) * 4)
        if algorithm != nlopt.LD_SLSQP:
            # the CCSA dual problem solved to 1e-8 in at most 200 evaluations: NLopt's
            # defaults (1e-14, 100000) made its own time 45-95 % of a run (docs/optimizers.md)
            opt.set_param("dual_ftol_rel", 1e-8)
            opt.set_param("dual_maxeval", 200)
        if step is not None or phase == 0:
            # the feasibility phase with NLopt's default step crept on the four-bar (0.01 %
            # design change per simulation); 0.1 of the unit box found a feasible design
            st = np.full(n, float(0.1 if step is None else step))
            if phase == 0:
                st[-1] = max(0.1 * (zu[-1] - zl[-1]), 1e-3)
            opt.set_initial_step(st)
        for key, value in (params or {}).items():
            opt.set_param(key, value)

        def objective(zz, grad, phase=phase):
            if phase == 0:
                if grad.size:
                    grad[:] = 0.0
                    grad[-1] = 1.0
                return float(zz[-1])
            e = analyse(zz)
            if grad.size:
                grad[:] = e.df * dx_dz(e.x)
            return float(e.f)

        def constraints(result, zz, grad, rows=rows, phase=phase):
            e = analyse(zz)
            result[:] = e.g[rows] - (zz[-1] if phase == 0 else 0.0)
            if grad.size:
                grad[:, :nv] = e.dg[rows] * dx_dz(e.x)[None, :]
                if phase == 0:
                    grad[:, -1] = -1.0

        opt.set_min_objective(objective)
        if rows.size:
            opt.add_inequality_mconstraint(constraints, np.full(rows.size, 1e-9))
        try:
            opt.optimize(np.clip(z, zl, zu))
            state["result"] = int(opt.last_optimize_result())
            if phase == 0:
                # no feasible design found: go on with the objective from the least violated
                state["phase"] = 1
                best = min(mon.iterates, key=lambda e: e.violation)
                z = to_z(best.x)
                continue
            if not mon.reason:
                mon.reason = f"NLopt stopped ({_result_name(nlopt, state['result'])})"
            break
        except _Finished:
            state["result"] = "stopped by flexmbs"
            break
        except _Feasible:
            state["phase"] = 1
            z = to_z(state.pop("restart_at").x)
        except _Restart:
            at = state.pop("restart_at")
            state["restarts"] += 1
            state["rows"] = np.union1d(rows, screened_rows(at.g, names, screen))
            z = to_z(at.x)
        except nlopt.RoundoffLimited:
            if phase == 0:
                state["phase"] = 1
                z = to_z(min(mon.iterates, key=lambda e: e.violation).x)
                continue
            state["result"] = "roundoff limited"
            mon.reason = mon.reason or "NLopt stopped: roundoff errors limited the progress"
            break
        except SimulationError as exc:
            # a trial design whose simulation fails (e.g. Newton does not converge on a very
            # flexible design): start again from the last design simulated, with half the
            # initial step (0.05 the first time)
            if not mon.iterates or state["restarts"] >= max_restarts:
                state["result"] = "simulation failed"
                mon.reason = mon.reason or f"a trial design's simulation failed: {exc}"
                break
            state["restarts"] += 1
            state["failures"] += 1
            step = 0.05 if step is None else 0.5 * step
            z = to_z(mon.iterates[-1].x)
    final = _choose(mon)
    if not mon.converged and final is not None and not mon.reason.startswith("maximum"):
        kkt = _kkt(mon, final)
        if final.violation < mon.constraint_violation and kkt < mon.kkt_tol:
            mon.converged = True
            mon.reason = (f"{mon.reason}; the returned design is feasible (violation "
                          f"{final.violation:.1e}) with KKT residual {kkt:.1e} < "
                          f"{mon.kkt_tol:g}")
    return final, dict(nlopt_result=state["result"], restarts=state["restarts"],
                       failed_simulations=state["failures"],
                       feasibility_simulations=state["feasibility_sims"],
                       screened_rows=int(state["rows"].size), total_rows=int(ev.g.size),
                       screen=screen)


def _kkt(mon, ev):
    P = mon.P
    return kkt_residual(ev.df, ev.g, ev.dg, ev.x, P.lower, P.upper, mon.active_tol)[0]


def _choose(mon):
    """The design to return: the converged iterate, else the lightest feasible one, else the
    least violated one (all rows checked)."""
    its = mon.iterates
    if not its:
        return None
    if mon.converged:
        return its[-1]
    feas = [e for e in its if e.violation < mon.constraint_violation]
    if feas:
        return min(feas, key=lambda e: e.f)
    return min(its, key=lambda e: (e.violation, e.f))


def _result_name(nlopt, code):
    names = {nlopt.SUCCESS: "success", nlopt.STOPVAL_REACHED: "stopval reached",
             nlopt.FTOL_REACHED: "relative objective change below ftol_rel",
             nlopt.XTOL_REACHED: "relative design change below xtol_rel",
             nlopt.MAXEVAL_REACHED: "maximum evaluations reached",
             nlopt.MAXTIME_REACHED: "maximum time reached"}
    return names.get(code, f"code {code}")
