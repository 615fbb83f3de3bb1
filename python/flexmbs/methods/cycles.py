"""The cycles of the weakly coupled method (paper 5.3), independent of what is optimized: the
stopping decisions and their diagnosis, the best feasible design seen, the checks of the
method's options, the move limits and the damped design update. `flexmbs.methods.weakly`
runs the cycles.

Every run ends with one diagnosis (`CycleControl.diagnosis`):

* 'converged': the paper's test (25), relative ESL change below eps, in 1 + confirm_cycles
  consecutive cycles (the test can fire on an unstable fixed point, hence the confirmation);
  or, when `design_tol` is given, a criterion of the kind of OptiStruct's ESLM outer loop: the
  relative design change between two cycles below design_tol with the cycle's design feasible
  (simulated), also in 1 + confirm_cycles consecutive cycles. The design change is the step
  the static optimization proposed (`observe`'s `step`), before damping: a damped update
  shrinks the step without the cycles converging;
* 'oscillating': the designs repeat with a period of 2 to 6 cycles (`_oscillation`; the
  paper's Table 5; OptiStruct stops when six objective values alternate around the optimum);
  with a shrinking move limit (`ShrinkingMoveLimit`, option shrink of the weakly coupled
  method) an oscillation is not a stop: the cycles go on with move limits that shrink;
* 'diverging': the ESL change of eq. (25) grew in each of the last `DIVERGING_CYCLES` cycles,
  to at least twice its value before them, and the largest simulated constraint value grew in
  each of them too (`_diverging`);
* 'cap': the maximum number of cycles was reached.

Whatever the diagnosis, the control keeps the best feasible design seen (`best`): the lightest
(lowest objective) cycle design whose simulation satisfies every constraint. Remedies against
oscillation (measured in docs/optimizers.md): relative move limits (`move_limited_bounds`),
move limits that shrink once the designs oscillate (`ShrinkingMoveLimit`), a damped design
update (`damped_update`), and ESL averaged over the last two cycles (`flexmbs.methods.weakly`,
option esl_blend). `what_to_try` names the remedies a run that did not converge did not use.
"""
from __future__ import annotations

import numpy as np

from types import SimpleNamespace

from flexmbs.errors import ModelError
from flexmbs.model.sections import real_number
from flexmbs.problem import FEASIBILITY_TOL

__all__ = ["CycleControl", "check_remedies", "move_limited_bounds", "ShrinkingMoveLimit",
           "what_to_try",
           "damped_update", "DIAGNOSES", "DIVERGING_CYCLES", "SHRINK_DESIGN_TOL"]

#: the diagnoses a run of cycles ends with
DIAGNOSES = ("converged", "oscillating", "diverging", "cap")
#: 'diverging': the ESL change grew in each of this many consecutive cycles
DIVERGING_CYCLES = 4
#: the design-change criterion of the cycles once a shrinking move limit acts (when the run
#: gives no design_tol): the static optimization moves no variable by 1e-3 (relative) or more
SHRINK_DESIGN_TOL = 1e-3


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


def _diverging(changes, violations, n=DIVERGING_CYCLES):
    """Whether the ESL change (eq. 25) grew in each of the last n cycles, to at least twice
    its value n cycles back, while the largest simulated constraint value grew in each of them
    too (the designs move away from feasibility; skipped when the constraint values are None).
    A bounded oscillation whose ESL change happens to grow for a while is not divergence."""
    last = changes[-(n + 1):]
    if len(last) < n + 1 or any(c is None for c in last):
        return False
    if not (all(b > a for a, b in zip(last, last[1:])) and last[-1] >= 2.0 * last[0]):
        return False
    g = violations[-(n + 1):]
    return any(v is None for v in g) or all(b > a for a, b in zip(g, g[1:]))


def check_remedies(damping, esl_blend, design_tol):
    """The anti-oscillation options, checked: damping in (0, 1], esl_blend in [0, 1),
    design_tol None or positive (ModelError naming the option)."""
    damping = real_number("damping", damping, positive=True)
    if damping > 1.0:
        raise ModelError(f"damping must lie in (0, 1] (1: the static optimum itself), "
                         f"got {damping!r}")
    esl_blend = real_number("esl_blend", esl_blend)
    if not 0.0 <= esl_blend < 1.0:
        raise ModelError(f"esl_blend must lie in [0, 1) (the previous cycle's share of the ESL), "
                         f"got {esl_blend!r}")
    if design_tol is not None:
        design_tol = real_number("design_tol (or None)", design_tol, positive=True)
    return damping, esl_blend, design_tol


def damped_update(x, x_star, damping):
    """The next cycle's design x + damping (x_star - x): damping 1 takes the static optimum
    x_star, smaller values move part of the way (a convex combination: within the bounds
    whenever x and x_star are)."""
    x = np.asarray(x, float)
    return x + damping * (np.asarray(x_star, float) - x)


def move_limited_bounds(x, lower, upper, move_limit):
    """The bounds of the next static optimization: the variables' bounds, narrowed to
    x (1 -/+ move_limit) when a relative move limit is given."""
    if move_limit is None:
        return lower.copy(), upper.copy()
    return np.maximum(lower, x * (1 - move_limit)), np.minimum(upper, x * (1 + move_limit))


def what_to_try(diagnosis, shrink, damping=1.0, max_cycles=None):
    """What to try when the cycles end with `diagnosis` other than 'converged' (a sentence for
    the result's reason; '' for 'converged'): shrink, damping and max_cycles are the options
    the run had (docs/optimizers.md, "Weakly coupled cycles", measures the remedies)."""
    if diagnosis == "converged":
        return ""
    tips = []
    if diagnosis == "oscillating" and shrink == 0:
        tips.append("shrink=0.5 (--shrink 0.5: move limits that shrink on the oscillation)")
    if diagnosis == "cap" and max_cycles is not None:
        tips.append(f"more cycles (--max-cycles {2 * max_cycles})")
    if shrink > 0.3 and diagnosis in ("cap", "oscillating"):
        tips.append("a faster shrink (--shrink 0.3)")
    if damping > 0.5:
        tips.append("a damped update (--damping 0.5)")
    tips.append("a design-change criterion (--design-tol 0.01)")
    tips.append("the fully coupled method (--method fully)")
    return "to try: " + ", ".join(tips)


class ShrinkingMoveLimit:
    """Relative move limits, one per variable, that shrink where the cycles oscillate.

    Off until `oscillation` is called (the cycles' designs repeat: `CycleControl.period`);
    each call sets every limit to shrink times the smaller of its current value and the
    oscillation's amplitude (the largest relative spread of any variable over the repeating
    designs). From then on, `step` shrinks the limit of each variable whose change reverses
    its direction from one cycle to the next by the factor `shrink` (a variable that keeps
    its direction keeps its limit). A bounded sequence whose steps reverse with a limit that
    shrinks geometrically settles: the designs converge, and the cycles' design-change
    criterion (`CycleControl`, SHRINK_DESIGN_TOL unless design_tol is given) ends the run.

    shrink in (0, 1); move_limit: the run's fixed relative move limit (None: none), the
    limits' first value before an oscillation shrinks them.
    """

    def __init__(self, shrink, move_limit=None):
        self.shrink, self.move_limit = float(shrink), move_limit
        self.limits, self.cycle, self.shrinks, self.periods = None, None, 0, []

    @property
    def active(self):
        """Whether an oscillation has set the limits."""
        return self.limits is not None

    def oscillation(self, cycle, designs, period):
        """An oscillation of `period` cycles seen at `cycle` in the designs so far: every
        limit becomes shrink * min(its value, the oscillation's amplitude)."""
        recent = np.array(designs[-(period + 1):], float)
        scale = np.maximum(np.abs(recent).max(axis=0), 1e-300)
        amplitude = float(np.max((recent.max(axis=0) - recent.min(axis=0)) / scale))
        current = (np.full(recent.shape[1], np.inf) if self.limits is None else self.limits)
        if self.limits is None and self.move_limit is not None:
            current = np.full(recent.shape[1], float(self.move_limit))
        self.limits = self.shrink * np.minimum(current, amplitude)
        self.cycle = cycle if self.cycle is None else self.cycle
        self.shrinks += 1

    def step(self, x_before, x_prev, x):
        """The cycle went x_before -> x_prev -> x: the limit of every variable whose change
        reversed its sign shrinks by `shrink`."""
        if self.limits is None:
            return
        reversed_ = (np.asarray(x, float) - x_prev) * (np.asarray(x_prev, float) - x_before) < 0
        self.limits = np.where(reversed_, self.shrink * self.limits, self.limits)

    def bounds(self, x, lower, upper):
        """The next static optimization's bounds: the variables' bounds narrowed to
        x (1 -/+ limit) (the fixed move limit, or none, before an oscillation)."""
        if self.limits is None:
            return move_limited_bounds(x, lower, upper, self.move_limit)
        return move_limited_bounds(x, lower, upper, self.limits)


class CycleControl:
    """The stopping decisions of the weakly coupled cycles and their diagnosis (module
    docstring), and the best feasible design seen.

    Parameters: eps (eq. 25), confirm_cycles, max_cycles, stop_on_oscillation (stop on a
    diagnosis 'oscillating' or 'diverging'; else only note it and go on to the cap),
    design_tol (None: eq. 25 only), feasibility_tol (a design is feasible when its largest
    simulated constraint value g <= feasibility_tol, default flexmbs.problem.FEASIBILITY_TOL).

    Attributes: designs, changes (ESL change per cycle), design_changes (relative, per cycle),
    converged, diagnosis (one of DIAGNOSES, '' while running), reason, period (oscillation
    period or None), paper_cycle (first cycle of the current run of eq. (25) below eps), best
    (None or a namespace cycle, design, objective, violation, data: the best feasible design
    seen and what `observe` was given with it)."""

    def __init__(self, eps, confirm_cycles, max_cycles, stop_on_oscillation, design_tol=None,
                 feasibility_tol=FEASIBILITY_TOL):
        self.eps, self.confirm_cycles = eps, confirm_cycles
        self.max_cycles, self.stop_on_oscillation = max_cycles, stop_on_oscillation
        self.design_tol, self.feasibility_tol = design_tol, feasibility_tol
        self.designs, self.changes, self.design_changes, self.violations = [], [], [], []
        self.consecutive, self.paper_cycle, self.consecutive_design = 0, None, 0
        self.converged, self.reason, self.period = False, "", None
        self.diagnosis, self.best, self.diverging = "", None, False

    def observe(self, cycle, design, change, record, objective=None, violation=None, data=None,
                step=None):
        """Take a cycle's design, ESL change and (simulated) objective and largest constraint
        value; `step`: the largest relative change x* - x the last static optimization
        proposed (default: the change from the previous design). The design change, an
        oscillation or a divergence are noted in `record`."""
        x = np.array(design, float).copy()
        dx = None if step is None else float(step)
        if self.designs and dx is None:
            prev = self.designs[-1]
            dx = float(np.max(np.abs(x - prev) / np.maximum(np.abs(prev), 1e-300)))
        self.designs.append(x)
        self.changes.append(change)
        self.violations.append(violation)
        self.design_changes.append(dx)
        record["design_change"] = dx
        feasible = violation is None or violation <= self.feasibility_tol
        if objective is not None and feasible and (self.best is None
                                                   or objective < self.best.objective):
            self.best = SimpleNamespace(cycle=cycle, design=x.copy(), objective=float(objective),
                                        violation=violation, data=data)
        if change is not None and change < self.eps:
            self.consecutive += 1
            if self.paper_cycle is None:
                self.paper_cycle = cycle
        else:
            self.consecutive, self.paper_cycle = 0, None
        if self.design_tol is not None and dx is not None and dx < self.design_tol and feasible:
            self.consecutive_design += 1
        else:
            self.consecutive_design = 0
        if self.consecutive > self.confirm_cycles:
            self.converged, self.diagnosis = True, "converged"
            self.reason = (f"relative ESL change (eq. 25) {change:.3g} < {self.eps:g} in "
                           f"{self.consecutive} consecutive cycles")
        elif self.consecutive_design > self.confirm_cycles:
            self.converged, self.diagnosis = True, "converged"
            self.reason = (f"relative design change {dx:.3g} < {self.design_tol:g} with the "
                           f"design feasible in {self.consecutive_design} consecutive cycles")
        elif change is not None:
            self.period = _oscillation(self.designs, self.changes)
            if self.period is not None:
                record["oscillation_period"] = self.period
            self.diverging = _diverging(self.changes, self.violations)
            if self.diverging:
                record["diverging"] = True

    def stop(self, cycle):
        """Whether the cycles end after this one (`diagnosis` and `reason` say why)."""
        if self.converged:
            return True
        if self.period is not None and self.stop_on_oscillation:
            self.diagnosis = "oscillating"
            self.reason = (f"oscillation: the designs repeat with period {self.period} cycles "
                           f"(eq. 25 change {self.changes[-1]:.3g})")
            return True
        if self.diverging and self.stop_on_oscillation:
            self.diagnosis = "diverging"
            self.reason = (f"diverging: the ESL change (eq. 25) grew in each of the last "
                           f"{DIVERGING_CYCLES} cycles, to {self.changes[-1]:.3g}")
            return True
        if cycle >= self.max_cycles:
            self.diagnosis = "cap"
            self.reason = f"maximum number of cycles ({self.max_cycles}) reached"
            if self.period is not None:
                self.reason += f" (the designs repeat with period {self.period} cycles)"
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
