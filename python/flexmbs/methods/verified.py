"""The end of every optimization: its design verified at converged resolution.

An optimizer works at the case's time step h, and it can walk into designs where h
under-predicts a response (a vibration peak resolved to 6-25 %: the optimum then violates its
limit at a converged step). `finish` re-simulates the final design down a ladder of steps
(`flexmbs.analysis.accuracy.verify`: h/2, h/4, ... until the objective and every constraint are known
to `rtol`) and, when the design is infeasible there, continues the same optimization on that
step from the design, then verifies again (a continued design infeasible on a still finer step
is continued there once more). A design whose responses do not settle (not in their asymptotic
range down to the finest step) is not continued: the result says it is not verified. The
result states the verification (`OptimizationResult.verification`, details["verification"]),
the step its objective and max_violation were simulated on (details["h"]: the case's, or the
last continuation's) and, after a continuation, the coarse run it started from (details["continued_from"]) and each
continuation (details["continuations"]).
"""
from __future__ import annotations

import numpy as np

from flexmbs.analysis.accuracy import VERIFY_RTOL, verify as verify_design
from flexmbs.model.options import check_verify_value
from flexmbs.output import response_unit
from flexmbs.responses.kinds import kind_of

__all__ = ["finish", "check_verify", "verify_rtol", "objective_unit", "MAX_CONTINUATIONS"]

#: continuations on finer steps at most (each on a finer step than the one before)
MAX_CONTINUATIONS = 2


def check_verify(verify):
    """A `verify` option: True (verify to VERIFY_RTOL, continue on the finer step when the
    design is infeasible there), a relative accuracy in (0, 0.1] (the same to that accuracy),
    'check' (verify to VERIFY_RTOL and report, never continue: what a reproduction of
    published results runs) or False (flexmbs.model.options.check_verify_value)."""
    return check_verify_value(verify)


def verify_rtol(verify):
    """The accuracy a `verify` option asks for (None: no verification)."""
    if verify is False:
        return None
    return VERIFY_RTOL if verify is True or verify == "check" else float(verify)


def objective_unit(problem):
    """The unit of `problem`'s objective (flexmbs.output.units: 'kg' for a mass, '... s' for
    an integral), None when unknown."""
    d = getattr(problem, "description", None)
    obj = getattr(d, "objective", None)
    if obj is None:
        return None
    r = next((r for r in getattr(d, "responses", ()) if r.name == obj.response), None)
    unit = None if r is None else response_unit(r, d)
    if unit is not None and getattr(obj, "over", None) == "integral":
        unit = f"{unit} s"
    return unit


def _can_verify(problem):
    """A Problem with a time step and at least one simulated response."""
    if not hasattr(problem, "refined") or not hasattr(problem, "used_responses"):
        return False
    return any(kind_of(r).timed for r in problem.description.responses)


def finish(problem, result, rerun, verify, coarse=None):
    """`result` of an optimization of `problem`, its design verified (see the module).

    rerun(fine_problem, x0) runs the same optimization on a refined problem from x0, without
    verification. coarse: the final design's Evaluation at the case's h, when the caller has it.
    A continued design that is infeasible at a finer step than the one it was optimized on is
    continued once more there (at most MAX_CONTINUATIONS in all).
    """
    rtol = verify_rtol(verify)
    time = getattr(getattr(problem, "description", None), "time", None)
    if hasattr(time, "grid_h"):
        # the step the result's objective and max_violation were simulated on
        result.details["h"] = float(time.grid_h)
    result.details.setdefault("objective_unit", objective_unit(problem))
    if rtol is None or not _can_verify(problem):
        return result
    v = verify_design(problem, result.design, rtol=rtol, coarse=coarse)
    level, steps = 0, []
    first = result
    # a design is continued only where its values settled: a response not in its asymptotic
    # range has no converged value to optimize against (the verification says so instead)
    while (verify != "check" and v.verified and not v.feasible and v.level > level
           and len(steps) < MAX_CONTINUATIONS):
        level = v.level
        # an adaptive case: its frozen grid with every step divided (Problem.refined), the
        # grid the verification found the design infeasible on (docs/accuracy.md,
        # "Continuation grids": measured as accurate per step as one chosen afresh)
        fine = problem.refined(2 ** level)
        cont = rerun(fine, np.asarray(result.design, float))
        steps.append(dict(h=v.h, design=np.asarray(cont.design).tolist(),
                          objective=float(cont.objective), iterations=int(cont.iterations),
                          simulations=int(cont.simulations)))
        grid = fine.grid_summary() if hasattr(fine, "grid_summary") else None
        if grid is not None:
            steps[-1]["grid"] = dict(grid, subdivided=2 ** level)
        cont.simulations += result.simulations
        cont.wall_time_s += result.wall_time_s
        cont.history = list(result.history) + [dict(r, refined_h=v.h) for r in cont.history]
        if result is first:
            cont.details["continued_from"] = dict(
                h=float(problem.description.time.grid_h), design=np.asarray(first.design).tolist(),
                objective=float(first.objective), iterations=int(first.iterations),
                simulations=int(first.simulations), verification=v.to_json(),
                reason=first.reason)
        else:
            cont.details["continued_from"] = result.details["continued_from"]
        cont.details["continuations"] = steps
        prev = v
        result = cont
        v = verify_design(problem, result.design, rtol=rtol)
        result.reason = (f"{result.reason} (continued at h = {prev.h:.4g} s from a design "
                         f"infeasible there by {prev.max_violation:.3g})")
    return _attach(result, v)


def _attach(result, v):
    result.verification = v
    result.details["verification"] = v.to_json()
    if not v.verified:
        loose = [n for n, e in v.constraints.items() if not e.reliable]
        result.reason += (f"; verification: the objective and constraints did not settle to "
                          f"{v.rtol:g} down to h = {v.h:.4g} s"
                          + (f" ({', '.join(loose)} not in the asymptotic range: a response "
                             f"set by modes that only the integrator damps; material damping "
                             f"gives it a converged value)" if loose else ""))
    elif not v.feasible:
        result.reason += (f"; verification: infeasible at h = {v.h:.4g} s by "
                          f"{v.max_violation:.3g}")
    return result
