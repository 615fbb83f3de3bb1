"""The cycles of the weakly coupled method (paper 5.3), independent of what is optimized: the
stopping decisions (eq. 25 below eps, confirmed; oscillation; the cycle cap), the checks of the
method's options and the move limits. `flexmbs.optimize.weakly` runs the cycles.

Beyond the paper's algorithm: convergence of eq. (25) is confirmed over `confirm_cycles` more
cycles (the test can fire on an unstable fixed point), an oscillation between designs (the
paper's Table 5) is detected and reported, and optional move limits bound the design change
per cycle.
"""
from __future__ import annotations

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.sections import real_number, whole_number

__all__ = ["CycleControl", "check_cycle_options", "move_limited_bounds"]


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
    see `_oscillation`), the cycle cap. 

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
