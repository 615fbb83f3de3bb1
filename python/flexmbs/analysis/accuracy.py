"""How accurate a response is: time-discretisation error estimates and verified designs.

Generalized-alpha (eqs. 3-6) is second-order accurate: a response computed with step h differs
from its converged value by about C h^2 once h resolves the motion (the asymptotic range). The
estimates here are Richardson's: the same design simulated with h, h/2, h/4 (a *ladder*), and
h/8 when those three are ambiguous,

    d_k = R(h/2^(k-1)) - R(h/2^k),   r_k = d_k / d_(k+1)   (signed; 4 at order 2).

The rule (docs/accuracy.md, "The rule"): changes at the rounding of the response (FLOOR_REL of
its size) are 'converged'; a ratio below MIN_RATIO, or negative (changes of opposite sign), is
'not asymptotic' (the error given is the largest change seen, which is no bound); on three
levels, a ratio whose observed order log2 r lies within CLEAR_ORDER of ORDER is 'asymptotic',
any other ratio >= MIN_RATIO is 'unconfirmed' and asks for a fourth level; on four levels, the
estimate is 'asymptotic' when both ratios agree: both fall at least about as fast as second
order (observed orders >= ORDER - CLEAR_ORDER; a faster fall is capped at second order), or
both are >= MIN_RATIO with observed orders within AGREE_ORDER of each other (one steady lower
order); else 'not asymptotic'. In the asymptotic range the error of the finest
value is |d_last| / (r - 1) with r the finest ratio capped at MAX_RATIO = 4 (second order: a
faster fall met by chance never claims a smaller error than second order would), and that of
R(h) adds the changes above it (three levels: |d1| r / (r - 1)). Two levels only (h, h/2) give
the estimate without a check (status 'unchecked').

A history is judged by its maximum over time (what limits and summaries use; the peak may move
between the levels), and its point-wise error at the time points of the coarsest level is
kept too (`ErrorEstimate.pointwise`). The maximum of a history is a sampled one: its error
also holds how far the peak may lie above the largest sample, estimated by the parabola
through the largest sample and its two neighbours (`peak_sampling`), added to the estimate.

`verify(problem, x)` checks a design at converged resolution: it walks down the ladder (h/2,
h/4, ... h/2^MAX_LEVEL) until every constraint's largest value and the objective are estimated
to within `rtol` (constraints are relative to their limits) and in their asymptotic range, and
tells whether the design is feasible there (`Verification`). The optimizers call it on their
final design (`flexmbs.optimize`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flexmbs.analysis.simulate import simulate
from flexmbs.errors import ModelError

__all__ = ["ErrorEstimate", "Verification", "ConvergenceCheck", "richardson", "estimate_errors",
           "verify", "convergence_check", "simulate_with_error", "peak_sampling",
           "describe_verification", "needs_fourth_level",
           "ORDER", "MIN_RATIO", "MAX_RATIO", "CLEAR_ORDER", "AGREE_ORDER", "FLOOR_REL",
           "MAX_LEVEL", "VERIFY_RTOL", "MARGIN_FRACTION"]

#: order of accuracy of generalized-alpha (second order for any rho_inf)
ORDER = 2
#: observed ratio of successive changes below which a response is not in its asymptotic range
#: (its changes fall more slowly than at first order)
MIN_RATIO = 2.0
#: the observed ratio is capped at the scheme's own (second order) when it extrapolates: a
#: larger ratio met by chance would claim too small an error
MAX_RATIO = 2.0 ** ORDER
#: on three levels, a ratio is clearly the scheme's when its observed order log2(r) lies within
#: this of ORDER (r in [2.83, 5.66]); any other ratio >= MIN_RATIO asks for a fourth level
CLEAR_ORDER = 0.5
#: on four levels, two ratios below 2^(ORDER - CLEAR_ORDER) agree when their observed orders
#: differ by at most this
AGREE_ORDER = 0.5
#: changes below this fraction of a response's size are rounding (Newton's tolerance is 1e-10)
FLOOR_REL = 1e-8
#: the finest level of a verification ladder: h / 2**MAX_LEVEL
MAX_LEVEL = 5
#: default accuracy a verification asks of the constraints (relative to their limits) and of
#: the objective: 0.1 %
VERIFY_RTOL = 1e-3
#: a constraint far from its limit is verified when its error (or, not reliable, the largest
#: change seen) is below this fraction of its margin -g
MARGIN_FRACTION = 0.25

_STATUS = ("converged", "asymptotic", "not asymptotic", "unconfirmed", "unchecked")


@dataclass
class ErrorEstimate:
    """The estimated time-discretisation error of one value.

    value : the value estimated (at step `h`).
    error : estimated |value - converged value| (same units as value).
    h : the step of `value`; levels : the steps of the ladder used (coarsest first: 2, 3 or
        4 of them; `n_levels`).
    changes : the successive changes R(h_k-1) - R(h_k) along the ladder.
    ratio : the finest ratio d_(n-2) / d_(n-1), signed (negative: changes of opposite sign;
        None with two levels); ratios : every successive ratio, coarsest first.
    status : 'converged' (changes at rounding), 'asymptotic' (the rule of the module's
        docstring holds: the error is reliable), 'not asymptotic' (the changes do not fall
        steadily: the error is no bound, refine h), 'unconfirmed' (three levels whose ratio
        falls but not clearly at second order: a fourth level decides, `needs_fourth_level`)
        or 'unchecked' (two levels: no ratio).
    pointwise : for a history, the error at each of its time points (those of the coarsest
        level), else None.
    reference : what `relative` divides by: None for |value|, 1.0 for a constraint value g
        (already relative to its limit).
    unresolved : the lightly damped modes the value sees that its step does not resolve
        (flexmbs.analysis.modes.UnresolvedMode, lowest first): with any, the value depends on
        the integrator's numerical damping and its estimate is not reliable.
    """
    value: float
    error: float
    h: float
    levels: tuple
    changes: tuple
    ratio: float | None
    status: str
    pointwise: np.ndarray | None = field(default=None, repr=False)
    reference: float | None = None
    unresolved: tuple = ()
    ratios: tuple = ()

    @property
    def n_levels(self):
        """The number of steps of the ladder the estimate used."""
        return len(self.levels)

    @property
    def reliable(self):
        """The error is an estimate one can act on (converged or in the asymptotic range, and
        no unresolved lightly damped mode in the value)."""
        return self.status in ("converged", "asymptotic") and not self.unresolved

    @property
    def relative(self):
        """error / |value| (or / reference; inf for a zero value with an error)."""
        if self.reference is not None:
            return self.error / self.reference
        if self.value == 0:
            return 0.0 if self.error == 0 else math.inf
        return self.error / abs(self.value)

    @property
    def order(self):
        """The observed order log2(ratio), or None."""
        if self.ratio is None or not self.ratio > 0 or not math.isfinite(self.ratio):
            return None
        return math.log2(self.ratio)

    def describe(self, scale=1.0, unit=""):
        """'± 0.0012 mm (0.12 %, asymptotic, observed order 2.1)'."""
        u = f" {unit}" if unit else ""
        rel = self.relative
        rel_text = f"{100 * rel:.2g} %" if math.isfinite(rel) else "relative n/a"
        order = self.order
        how = self.status + (f", observed order {order:.1f}" if order is not None
                             and self.status != "converged" else "")
        text = f"± {self.error * scale:.3g}{u} ({rel_text}, {how})"
        if self.status == "not asymptotic":
            text += ": not in its asymptotic range, refine the time step"
        elif self.status == "unconfirmed":
            text += ": not confirmed by a fourth level, refine the time step"
        if self.unresolved:
            text += "; NOT reliable: " + self.unresolved[0].describe()
        return text

    def to_json(self):
        return {"value": float(self.value), "error": float(self.error),
                "relative_error": (float(self.relative) if math.isfinite(self.relative)
                                   else None),
                "status": self.status, "reliable": self.reliable, "h": float(self.h),
                "levels": [float(h) for h in self.levels], "n_levels": self.n_levels,
                "changes": [float(c) for c in self.changes],
                "ratio": None if self.ratio is None or not math.isfinite(self.ratio)
                else float(self.ratio),
                "ratios": [float(r) if math.isfinite(r) else None for r in self.ratios],
                "observed_order": self.order,
                "unresolved_modes": [u.to_json() for u in self.unresolved]}


def _ratio_status(changes, floor):
    """(ratios, status) of a ladder's changes (signed scalars; for histories their sizes):
    the rule of the module's docstring."""
    c = [float(x) for x in changes]
    a = [abs(x) for x in c]
    ratios = tuple(c[k] / c[k + 1] if c[k + 1] != 0 else math.copysign(math.inf, c[k] or 1.0)
                   for k in range(len(c) - 1))
    if all(x <= floor for x in a):
        return ratios, "converged"
    if len(c) < 2:
        return ratios, "unchecked"
    if a[-1] <= floor:
        # the finest change is rounding: judged by the changes above it
        return ratios, ("asymptotic" if all(r >= MIN_RATIO for r in ratios[:-1]) else
                        "not asymptotic")
    if any(not r >= MIN_RATIO for r in ratios):
        return ratios, "not asymptotic"
    orders = [math.log2(r) if math.isfinite(r) else math.inf for r in ratios]
    if len(ratios) == 1:
        return ratios, ("asymptotic" if abs(orders[0] - ORDER) <= CLEAR_ORDER
                        else "unconfirmed")
    steady = (min(orders) >= ORDER - CLEAR_ORDER            # both fall about as fast as order 2
              or max(orders) - min(orders) <= AGREE_ORDER)  # or at one steady order
    return ratios, "asymptotic" if steady else "not asymptotic"


def needs_fourth_level(estimates):
    """Whether any of the ErrorEstimates (an iterable; None items skipped) is 'unconfirmed'
    on three levels and asks for a fourth (h/8)."""
    return any(e is not None and e.status == "unconfirmed" for e in estimates)


def richardson(values, levels, finest=False, floor=None):
    """The error estimate of one value from a ladder of steps.

    values : 2, 3 or 4 values of the same quantity at steps levels = (h, h/2[, h/4[, h/8]]);
        scalars, or arrays of one shape (then judged by their largest change, with `pointwise`
        errors).
    finest : False: the error of values[0] (the coarsest, what a run at h gives); True: that
        of values[-1].
    floor : changes at most this big count as rounding (default FLOOR_REL x the largest |value|).

    The status follows the rule of the module's docstring; on four levels the error is that
    of the finest three levels' extrapolation (plus, for values[0], the changes above them).
    """
    if len(values) not in (2, 3, 4) or len(levels) != len(values):
        raise ModelError(f"richardson needs 2, 3 or 4 values on as many levels, got "
                         f"{len(values)} values and {len(levels)} levels")
    v = [np.asarray(a, float) for a in values]
    d = [v[k] - v[k + 1] for k in range(len(v) - 1)]
    size = max(float(np.max(np.abs(a))) if a.size else 0.0 for a in v)
    if floor is None:
        floor = FLOOR_REL * size
    scalar = v[0].ndim == 0
    norms = [float(np.max(np.abs(c))) if c.size else 0.0 for c in d]
    ratios, status = _ratio_status([float(c) for c in d] if scalar else norms, floor)
    ratio = ratios[-1] if ratios else None
    rc = (2.0 ** ORDER if ratio is None or status not in ("asymptotic", "unconfirmed")
          or not ratio >= MIN_RATIO else min(ratio, MAX_RATIO))
    if status == "not asymptotic":
        err = np.abs(d[0])
        for dk in d[1:]:
            err = np.maximum(err, np.abs(dk))
    elif finest:
        err = np.abs(d[-1]) / (rc - 1.0)
    elif len(d) < 3:
        err = np.abs(d[0]) * rc / (rc - 1.0)
    else:
        err = np.abs(d[0]) + np.abs(d[-2]) * rc / (rc - 1.0)
    k = -1 if finest else 0
    return ErrorEstimate(value=float(v[k]) if scalar else float(np.max(v[k])),
                         error=float(err) if scalar else float(np.max(err)),
                         h=float(levels[k]), levels=tuple(float(h) for h in levels),
                         changes=tuple(norms if not scalar else [float(c) for c in d]),
                         ratio=ratio, status=status,
                         pointwise=None if scalar else np.asarray(err), ratios=ratios)


def simulate_with_error(model, t_end, h, levels=3, **kw):
    """`flexmbs.simulate(model, t_end, h, **kw)` with the estimated time-discretisation error
    of its stored coordinates in `Result.error` (an ErrorEstimate: point-wise errors of shape
    q's, judged by the largest change over every coordinate and time point); the model is
    simulated again at h/2 (and h/4 with levels=3, and h/8 when those three are ambiguous:
    the rule of the module's docstring) with the same keywords."""

    if isinstance(levels, bool) or levels not in (2, 3):
        raise ModelError(f"simulate_with_error: levels must be 2 or 3, got {levels!r}")
    runs = [simulate(model, t_end, h / 2 ** k, **kw) for k in range(levels)]
    nt0 = runs[0].t.size
    common = [r.q[::2 ** k][:nt0] for k, r in enumerate(runs)]
    runs[0].error = richardson(common, [h / 2 ** k for k in range(levels)])
    if needs_fourth_level([runs[0].error]):
        common.append(simulate(model, t_end, h / 8, **kw).q[::8][:nt0])
        runs[0].error = richardson(common, [h / 2 ** k for k in range(4)])
    return runs[0]


# ----------------------------------------------------------------------------- responses
def _history_max(v):
    return float(np.max(v)) if np.ndim(v) else float(v)


def peak_sampling(v):
    """How far the peak of a sampled history may lie above its largest sample: the vertex
    of the parabola through the largest sample and its neighbours, minus that sample (0 at
    either end of the history or where the samples do not curve down)."""
    v = np.asarray(v, float)
    if v.ndim == 0 or v.size < 3:
        return 0.0
    j = int(np.argmax(v))
    if j == 0 or j == v.size - 1:
        return 0.0
    a, b, c = v[j - 1], v[j], v[j + 1]
    curve = a - 2 * b + c
    return float((a - c) ** 2 / (-8 * curve)) if curve < 0 else 0.0


def _constraint_maxima(ev):
    """{response: largest normalised constraint value g} of an Evaluation (smoothness rows,
    which need no simulation, left out)."""
    out = {}
    for g, name in zip(np.asarray(ev.constraints, float), ev.constraint_names):
        if name.endswith(" max_step"):
            continue
        out[name] = max(out.get(name, -math.inf), float(g))
    return out


def _common_points(values, nt0):
    """The values of histories on a finer grid at the time points of the coarsest (nt0 points:
    the finer grids hold them every 2**k points)."""
    out = []
    for k, v in enumerate(values):
        v = np.asarray(v, float)
        if v.ndim:
            step = 2 ** k
            v = v[::step][:nt0]
        out.append(v)
    return out


def estimate_errors(evaluations, levels, finest=False, unresolved=None, objective_response=None):
    """Error estimates of every response, the objective and each constraint's largest value
    from the Evaluations of one design at the steps `levels` (h, h/2[, h/4]).

    Returns (responses, objective, constraints): {name: ErrorEstimate} of each response (a
    history: of its maximum, with point-wise errors at the coarsest grid's time points); the
    objective's (or None); {response: ErrorEstimate} of each constrained response's largest
    normalised value g (relative to its limit).
    unresolved : {response: [UnresolvedMode]} at the step of the values estimated
        (flexmbs.analysis.modes.ModalCheck.unresolved): put into each estimate of that
        response (its own, its constraint's) and into the objective's when it is
        `objective_response`'s.
    """
    first = evaluations[0]
    nt0 = np.asarray(first.t).size
    responses = {}
    for name, v in first.values.items():
        ladder = [ev.values[name] for ev in evaluations]
        if np.ndim(v):
            peak = richardson([_history_max(a) for a in ladder], levels, finest)
            peak.error += peak_sampling(ladder[-1 if finest else 0])
            points = richardson(_common_points(ladder, nt0), levels, finest)
            peak.pointwise = points.pointwise if not finest else None
            responses[name] = peak
        else:
            responses[name] = richardson([float(a) for a in ladder], levels, finest)
    objective = None
    if first.objective is not None:
        objective = richardson([float(ev.objective) for ev in evaluations], levels, finest)
    maxima = [_constraint_maxima(ev) for ev in evaluations]
    constraints = {}
    for name in maxima[0]:
        # g = r / |limit| - 1: its rounding is that of r / |limit|, not of g near 0
        ladder = [m[name] for m in maxima]
        constraints[name] = richardson(ladder, levels, finest,
                                       floor=FLOOR_REL * max(1.0, 1.0 + abs(ladder[0])))
        constraints[name].reference = 1.0
    for name, found in (unresolved or {}).items():
        for est in (responses.get(name), constraints.get(name)):
            if est is not None:
                est.unresolved = tuple(found)
        if objective is not None and objective_response == name:
            objective.unresolved = tuple(found)
    return responses, objective, constraints


# ----------------------------------------------------------------------------- verification
@dataclass
class Verification:
    """A design checked at converged resolution (see `verify`).

    verified : the objective and every constraint's largest value are estimated to within
        `rtol` in their asymptotic range at step `h`.
    feasible : every constraint holds there within rtol (largest g <= rtol).
    h : the step of the values reported; case_h : the case's own step;
    level : h = case_h / 2**level.
    objective, constraints : ErrorEstimates of the objective and of each constrained response's
        largest g at h (g relative to the limit).
    responses : {name: ErrorEstimate} of every response at h (a history: its maximum).
    max_violation : largest g at h (<= 0: feasible).
    evaluation : the Evaluation at h (not in JSON).
    rtol : the accuracy asked.
    """
    verified: bool
    feasible: bool
    h: float
    case_h: float
    level: int
    rtol: float
    objective: ErrorEstimate | None
    constraints: dict
    responses: dict
    max_violation: float
    evaluation: object = field(default=None, repr=False)

    def summary(self):
        """One line for people (`describe_verification`)."""
        return describe_verification({"verification": self.to_json()})

    def to_json(self):
        return {"verified": self.verified, "feasible": self.feasible, "h": self.h,
                "case_h": self.case_h, "level": self.level, "rtol": self.rtol,
                "max_violation": self.max_violation,
                "objective": None if self.objective is None else self.objective.to_json(),
                "constraints": {k: e.to_json() for k, e in self.constraints.items()},
                "responses": {k: e.to_json() for k, e in self.responses.items()}}


def describe_verification(record):
    """One line on a run's verification from its JSON record (an OptimizationResult's
    details or JSON, a multi-start's best start: keys ``verification`` (Verification.to_json)
    and, after a continuation on a finer step, ``continued_from``); None without a
    verification."""
    v = record.get("verification")
    if not v:
        return None
    text = (f"{'verified' if v['verified'] else 'NOT verified'} at h = {v['h']:.4g} s (the "
            f"case's h / {2 ** v['level']}): {'feasible' if v['feasible'] else 'INFEASIBLE'} "
            f"within {v['rtol']:g}, largest g = {v['max_violation']:.3g}")
    worst = max((v.get("constraints") or {}).items(), key=lambda kv: kv[1]["value"],
                default=None)
    if worst is not None:
        # g = (r - limit) / |limit|: its error is a fraction of the limit
        text += (f" ({worst[0]}: g ± {worst[1]['error']:.3g}, g and its error relative to the "
                 f"limit, {worst[1]['status']})")
    else:
        text += " (g relative to the limits)"
    c = record.get("continued_from")
    if c:
        unit = record.get("objective_unit")
        text += (f"; continued on a finer step from the design of objective "
                 f"{c['objective']:.6g}{' ' + unit if unit else ''} found at h = {c['h']:.4g} s, "
                 f"infeasible at h = "
                 f"{c['verification']['h']:.4g} s by {c['verification']['max_violation']:.3g}")
    return text


def verify(problem, x, rtol=VERIFY_RTOL, max_level=MAX_LEVEL, coarse=None):
    """Check design x of `problem` at converged resolution.

    The design is simulated at the case's h / 2, h / 4, ... (down to h / 2**max_level) until,
    on the finest three levels (four when a ratio there is 'unconfirmed': the rule of the
    module's docstring), the objective and every constraint's largest value have a reliable
    estimated error (`richardson`, finest=True) below `rtol` (relative to the objective, to the
    constraints' limits); a constraint far from its limit may instead have an error (or, not
    reliable, largest change seen) below MARGIN_FRACTION of its margin.
    Returns a `Verification`; the values it reports are those of the finest level reached.
    `coarse`: the Evaluation of x at the case's h when the caller has it (saves a
    simulation).
    """
    if not (isinstance(rtol, (int, float)) and not isinstance(rtol, bool) and 0 < rtol < 1):
        raise ModelError(f"verify: rtol must be a number in (0, 1), e.g. 1e-3, got {rtol!r}")
    if isinstance(max_level, bool) or not isinstance(max_level, int) or not 2 <= max_level <= 8:
        raise ModelError(f"verify: max_level must be an integer in [2, 8], got {max_level!r}")
    h = float(problem.description.time.grid_h)
    evs = [coarse if coarse is not None else problem.evaluate(x, gradient=False)]
    # the lowest modes along the motion: a value seeing one its step leaves unresolved and
    # lightly damped is not verified at that step (flexmbs.analysis.modes)
    modal = problem.modal_check(x) if hasattr(problem, "modal_check") else None
    obj = getattr(problem.description, "objective", None)
    level = 0
    est = None
    while level < max_level:
        level += 1
        evs.append(problem.refined(2 ** level).evaluate(x, gradient=False))
        if level < 2:
            continue
        ladder = [h / 2 ** k for k in (level - 2, level - 1, level)]
        seen = dict(unresolved=None if modal is None else modal.unresolved(
                        ladder[-1], problem.description.time.rho_inf),
                    objective_response=None if obj is None else obj.response)
        est = estimate_errors(evs[-3:], ladder, finest=True, **seen)
        if level >= 3 and needs_fourth_level([est[1], *est[2].values()]):
            est = estimate_errors(evs[-4:], [h / 2 ** (level - 3)] + ladder, finest=True, **seen)
        if _verified(est, rtol):
            break
    responses, objective, constraints = est
    fine = evs[-1]
    maxg = max((e.value for e in constraints.values()), default=-math.inf)
    return Verification(verified=_verified(est, rtol), feasible=bool(maxg <= rtol),
                        h=h / 2 ** level, case_h=h, level=level, rtol=float(rtol),
                        objective=objective, constraints=constraints, responses=responses,
                        max_violation=float(maxg), evaluation=fine)


def _verified(est, rtol):
    _, objective, constraints = est
    ok = all((e.reliable and e.error <= rtol)
             or (e.value < 0 and e.error <= MARGIN_FRACTION * -e.value and not e.unresolved)
             for e in constraints.values())
    if objective is not None:
        ok = ok and objective.reliable and objective.error <= rtol * max(abs(objective.value),
                                                                           1e-300)
    return ok


# ----------------------------------------------------------------------------- convergence check
@dataclass
class ConvergenceCheck:
    """A case's responses at its own resolution beside their changes under refinement
    (`convergence_check`).

    rows : one dict per response: name, value (a history: its maximum), unit (of the value,
        the changes and the error; None when unknown), time (ErrorEstimate
        from h, h/2, h/4), mesh_change (value with twice the elements of every beam minus value;
        None when the mesh was not refined), verdict.
    h : the case's step; rtol : the relative accuracy asked; mesh_note : why the mesh was not
        refined, or None.
    """
    case: str
    h: float
    rtol: float
    rows: list
    mesh_note: str | None = None

    @property
    def converged(self):
        """Every response settled to rtol in the time step and the mesh."""
        return all(r["verdict"].startswith("converged") for r in self.rows)

    def summary(self):
        eighth = any(r["time"].n_levels > 3 for r in self.rows)
        lines = [f"convergence check of {self.case}: step h = {self.h:g} s against h/2"
                 + (", h/4 and h/8" if eighth else " and h/4")
                 + ("" if self.mesh_note else ", mesh against twice the elements")
                 + f", accuracy asked {self.rtol:g} (relative)",
                 f"  {'response':18s} {'value':>12s} {'unit':6s} {'change h/2':>11s} "
                 f"{'est. error':>10s} {'change mesh':>11s}  verdict"]
        for r in self.rows:
            e = r["time"]
            mesh = "-" if r["mesh_change"] is None else f"{r['mesh_change']:.3g}"
            lines.append(f"  {r['name']:18s} {r['value']:12.6g} {r.get('unit') or '-':6s} "
                         f"{-e.changes[0]:11.3g} {e.error:10.3g} {mesh:>11s}  {r['verdict']}")
        if self.mesh_note:
            lines.append(f"  mesh not refined: {self.mesh_note}")
        lines.append("  verdict: " + ("every response converged to the accuracy asked"
                                      if self.converged else "NOT converged (see above)"))
        return "\n".join(lines)

    def to_json(self):
        return {"case": self.case, "h": self.h, "rtol": self.rtol, "converged": self.converged,
                "mesh_note": self.mesh_note,
                "responses": {r["name"]: {"value": r["value"], "unit": r.get("unit"),
                                          "time": r["time"].to_json(),
                                          "mesh_change": r["mesh_change"],
                                          "verdict": r["verdict"]} for r in self.rows}}


def settled(e, tol):
    """Whether an ErrorEstimate that is not in its asymptotic range has settled within `tol`:
    no unresolved lightly damped mode in it, its later changes at most half its first (in
    magnitude, whatever their signs), and the whole movement seen over the ladder (the sum of
    the changes' magnitudes, from h to the finest step) and its stated error at most `tol`. What it states is the
    movement observed, not an asymptotic estimate (docs/accuracy.md, "The rule")."""
    c = np.abs(np.asarray(e.changes, dtype=float))
    if e.unresolved or c.size < 2 or not np.all(np.isfinite(c)):
        return False
    return bool(np.all(c[1:] <= 0.5 * c[0]) and max(c.sum(), e.error) <= tol)


def convergence_check(problem, x=None, rtol=1e-2):
    """Each simulated response of `problem` at design x (default: its start) at the case's
    step h, its estimated time-discretisation error (h, h/2, h/4: `richardson`), and its change
    with twice the elements of every beam, with a verdict: 'converged' (both within rtol of the
    value; a response not in its asymptotic range counts as converged in time when it has
    `settled` within rtol), 'time step not converged' (an error above rtol, or not in the
    asymptotic range and not settled),
    'mesh not converged' (a mesh change above rtol) or both."""
    if not (isinstance(rtol, (int, float)) and not isinstance(rtol, bool) and 0 < rtol < 1):
        raise ModelError(f"convergence_check: rtol must be a number in (0, 1), got {rtol!r}")
    ev = problem.evaluate(x, gradient=False, error=True)
    mesh, note = problem.refined_mesh()
    fine = None if mesh is None else mesh.evaluate(ev.x, gradient=False)
    rows = []
    for name, e in (ev.errors or {}).items():
        v = ev.values[name]
        if not np.ndim(v) and e.error == 0 and e.status == "converged":
            continue            # a value that needs no simulation (a mass)
        value = _history_max(v)
        scale = max(abs(value), 1e-300)
        dmesh = None if fine is None else _history_max(fine.values[name]) - value
        bad = []
        if e.unresolved:
            bad.append("time step not converged (" + e.unresolved[0].describe() + ")")
        elif not e.reliable and not settled(e, rtol * scale):
            bad.append("time step not converged (not in its asymptotic range)")
        elif e.reliable and e.error > rtol * scale:
            bad.append("time step not converged")
        if dmesh is not None and abs(dmesh) > rtol * scale:
            bad.append("mesh not converged")
        ok = "converged"
        if not bad and not e.reliable:
            ok += (f" (settled: not asymptotic, moved {float(np.abs(e.changes).sum()):.3g} "
                   f"from h to h/{2 ** (len(e.levels) - 1)})")
        rows.append(dict(name=name, value=value, time=e, mesh_change=dmesh,
                         verdict="; ".join(bad) or ok,
                         unit=((ev.units or {}).get("responses") or {}).get(name)))
    return ConvergenceCheck(case=problem.description.case.name,
                            h=float(problem.description.time.grid_h), rtol=float(rtol), rows=rows,
                            mesh_note=note)
