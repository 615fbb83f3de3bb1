"""Error-controlled step grids: `time.h = "auto"` (docs/accuracy.md, "Error-controlled steps").

A case with ``[time] h = "auto"`` and a tolerance (``tol``, absolute in the responses' units,
and/or ``rtol``, relative to each response's largest magnitude) is integrated on a
non-uniform step grid (flexmbs.analysis.simulate's `steps`) chosen here from the responses
themselves (goal-oriented: only what the responses read sets the steps), and its outputs are
interpolated onto the response grid t_j = j output (flexmbs.analysis.simulate.interpolation_matrix).

The choice (`choose_steps`), at one design:

1. two pilot runs on uniform grids H and H/2 (H twice the response grid's spacing, or the
   spacing itself when t_end is an odd number of it); the difference of their response
   histories is the coarse run's error, e_H = 4/3 max_t |r_H - r_H/2| / tol_r
   (generalized-alpha is second order), per response r with its tolerance
   tol_r = tol + rtol max_t |r|;
2. the error density w(t) = max_r |r'''(t)| / tol_r from third differences of the finer
   pilot's histories, widened by a running maximum over a few pilot steps (an oscillation's
   zero crossings must not open a long step);
3. the error model e(grid) = c sum_n h_n^3 w(t_n) (the per-step errors h^2 w of a second
   order scheme, accumulated: a phase error grows linearly in time), calibrated on the
   coarse pilot: c = e_H / (H^2 int w dt);
4. the steps minimising their number for e = 1 (the tolerance): h(t) = K w(t)^(-1/3),
   K^2 int w^(1/3) dt = 1 / c; bounded by h_max and H / 1024 (`SHORTEST`; where the
   tolerance asks for shorter steps, the grid is *saturated*: those steps are H / 1024 and
   K is solved again, by scipy.optimize.brentq, for e = 1 with the bounded steps), by a
   growth ratio of `GROWTH` between neighbours, and rounded down to the ladder
   H 2^(k/4), so that runs of equal steps keep modified Newton's held factorizations
   (generalized_alpha.f90 refactors when the step changes).

A tolerance that steps of H / 1024 throughout do not reach (e_H / 1024^2 > 1) is refused,
a CaseError naming the tolerance they reach; one whose grid would hold more steps than the
core counts, a ResourceError. The tolerances enter as s u (s = max(tol, rtol) a scalar, u
of ordinary size): e_H, w and c are computed relative to u, and s only through log(s) and
the steps' sqrt(s), so that no positive finite tolerance overflows or underflows them.

Within an optimization run the grid is chosen once (at the problem's start design, or at
another by Problem.adapt) and then frozen: the responses are then smooth functions of
the design, and their direct and adjoint derivatives are exact on that grid.
"""
from __future__ import annotations

import numpy as np

from flexmbs.errors import CaseError, ResourceError
from flexmbs.resources import MAX_STEPS
from flexmbs.responses.aggregate import trapezoid_weights

__all__ = ["choose_steps", "check_tolerance", "pilot_steps", "subdivide", "GROWTH", "LADDER",
           "SHORTEST"]

#: Largest ratio of neighbouring steps.
GROWTH = 1.5
#: the shortest step: 1/SHORTEST of the coarse pilot's (a smaller time.h_max is an error)
SHORTEST = 1024
#: Steps are H 2**(k / LADDER) (k integer), H the coarse pilot's step.
LADDER = 4
#: Pilot steps the error density's running maximum spans on either side.
WINDOW = 4


def subdivide(steps, factor):
    """The grid `steps` with every step divided into `factor` equal ones."""
    tg = np.asarray(steps, float)
    s = np.arange(factor) / factor
    out = (tg[:-1, None] + s[None, :] * np.diff(tg)[:, None]).ravel()
    return np.append(out, tg[-1])


def pilot_steps(n):
    """Time steps of `choose_steps`'s two pilot runs together, on a response grid of n steps:
    H = 2 h and h (n even), or h and h / 2 (n odd)."""
    return 3 * (n // 2) if n % 2 == 0 else 3 * n


def _histories(values, nt):
    """(nt, k) columns of the response histories among `values` (name -> value)."""
    cols = [np.asarray(v, float).reshape(nt, -1) for v in values.values()
            if np.ndim(v) >= 1 and np.shape(v)[0] == nt]
    return np.hstack(cols) if cols else np.zeros((nt, 0))


def check_tolerance(key, value):
    """`value` of the tolerance `key` (time.tol or time.rtol) checked: None, or a positive
    finite number (CaseError naming the key, the value and the range otherwise)."""
    if value is None:
        return None
    ok = (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
          and np.isfinite(value) and value > 0)
    if not ok:
        raise CaseError(f"{key} = {value!r}: a tolerance is a positive finite number "
                        f"(0 < {key} < inf), or None")
    return float(value)


def _scaled_tolerances(r, tol, rtol):
    """(s, u): each history's tolerance tol + rtol max|r| as s u, s = max(tol, rtol) a scalar
    and u = tol / s + (rtol / s) max|r| an array of ordinary size (no tolerance between
    1e-308 and 1e308 underflows or overflows in u); u = inf where it is 0 (a history that
    is zero throughout, with rtol alone: nothing to control)."""
    s = max(tol or 0.0, rtol or 0.0)
    u = (tol or 0.0) / s + (rtol or 0.0) / s * np.abs(r).max(axis=0)
    return s, np.where(u > 0, u, np.inf)


def _tolerance_text(tol, rtol, log_factor=0.0):
    """'time.tol = a, time.rtol = b' (the ones given), each times exp(log_factor)."""
    with np.errstate(over="ignore"):
        return ", ".join(f"time.{k} = {np.exp(np.log(v) + log_factor):.3g}"
                         for k, v in (("tol", tol), ("rtol", rtol)) if v)


def choose_steps(problem, x=None, *, tol=None, rtol=None, h_max=None, info=None):
    """A non-uniform step grid (times from 0 to t_end) for design x (default: the start) of
    `problem` (flexmbs.Problem) whose responses' histories are estimated to be within the
    tolerance (tol + rtol max|r| each; default: the case's time.tol, time.rtol, time.h_max).
    The module docstring tells how. `info`, a dict, receives the pilots' cost and estimates:
    pilot_steps, pilot_seconds, coarse_error (e_H, in tolerances), predicted_steps,
    estimated_error (the error model's estimate for the grid, in tolerances: at most 1 when
    the tolerance is reached), shortest_step (the shortest allowed, H / SHORTEST, s) and
    saturated (the fraction of the run, 0 to 1, where the tolerance asks for steps shorter
    than that: they run at the shortest, the other steps shortened to make up for it).

    A tolerance the shortest steps allowed do not reach (the error model's estimate on a
    uniform grid of them, e_H / SHORTEST^2, above 1) is a CaseError naming the tolerance
    they reach."""
    import time

    from scipy.optimize import brentq

    ts = problem.description.time
    tol = check_tolerance("time.tol", ts.tol if tol is None else tol)
    rtol = check_tolerance("time.rtol", ts.rtol if rtol is None else rtol)
    if not tol and not rtol:
        raise CaseError("choose_steps needs a tolerance: time.tol and/or time.rtol")
    mech = problem.mechanism
    t_end, h = mech.t_end, mech.h
    n = mech.t.size - 1
    h_max = ts.h_max if h_max is None else h_max
    h_max = t_end / 20 if h_max is None else float(h_max)
    # pilots: H = 2 h (h the response grid's spacing) and h; one H = h and h / 2 on an odd grid
    big = 2 if n % 2 == 0 else 1
    hc = big * h
    h_min = hc / SHORTEST
    if h_max < h_min:
        raise CaseError(f"time.h_max = {h_max:g} s is below the shortest step the grid takes, "
                        f"1/{SHORTEST} of the coarse pilot's {hc:g} s ({h_min:g} s): "
                        "give a larger h_max, or a fixed step time.h")
    nc = int(round(t_end / hc))
    t0 = time.perf_counter()
    rc = _histories(problem.values_on(x, np.linspace(0.0, t_end, nc + 1)), n + 1)
    rf = _histories(problem.values_on(x, np.linspace(0.0, t_end, 2 * nc + 1)), n + 1)
    seconds = time.perf_counter() - t0
    if info is not None:
        info.update(pilot_steps=pilot_steps(n), pilot_seconds=seconds, shortest_step=h_min)
    if rf.shape[1] == 0:      # nothing to control: the longest steps allowed
        m = max(1, int(np.ceil(t_end / h_max)))
        if info is not None:
            info.update(coarse_error=0.0, predicted_steps=m, estimated_error=0.0, saturated=0.0)
        return np.linspace(0.0, t_end, m + 1)
    # the tolerances as s u (s a scalar): the error measures below are in units of u, and
    # s enters only through logarithms and sqrt(s), so that no tolerance overflows them
    s, u = _scaled_tolerances(rf, tol, rtol)
    e_u = 4.0 / 3.0 * float(np.max(np.abs(rc - rf) / u))     # e_H = e_u / s
    # the finer pilot's histories on the response grid (its step or a multiple of it)
    r, hf = rf, h
    d3 = np.abs(np.diff(r, 3, axis=0)) / hf**3 / u           # at the middles of 4 points
    w = d3.max(axis=1) if d3.size else np.zeros(1)
    # running maximum over +-WINDOW points, then onto the points of r
    pad = np.pad(w, WINDOW, mode="edge")
    w = np.max(np.lib.stride_tricks.sliding_window_view(pad, 2 * WINDOW + 1), axis=1)
    tw = hf * (np.arange(w.size) + 1.5)
    tp = hf * np.arange(r.shape[0])
    w = np.interp(tp, tw, w)
    w = np.maximum(w, 1e-300)
    quad = trapezoid_weights(tp)         # the trapezoid rule on the pilot's times
    integral_w = float(quad @ w)
    if e_u <= 0 or integral_w <= 0:
        c = 0.0
    else:
        c = e_u / (hc**2 * integral_w)   # the error model's constant times s
    # the error model of the step profile hs(t), in tolerances: e = (c / s) int hs^2 w dt
    log_s = np.log(s)

    def log_error(steps):
        return np.log(c) + np.log(float(quad @ (steps**2 * w))) - log_s

    saturated = 0.0
    if c > 0:
        reach = log_error(np.full(tp.size, h_min))       # the shortest steps throughout
        if reach > 0:
            raise CaseError(
                f"{_tolerance_text(tol, rtol)} is out of reach: the shortest steps allowed "
                f"({h_min:.3g} s, 1/{SHORTEST} of the coarse pilot's {hc:g} s) reach about "
                f"{_tolerance_text(tol, rtol, reach)} (the pilots' error estimate); give a "
                f"tolerance at least that, or a fixed step time.h")
        # h(t) = K w^(-1/3) with e = 1: K^2 (c / s) int w^(1/3) dt = 1
        k = np.sqrt(s / (c * float(quad @ w ** (1.0 / 3.0))))
        hs = k * w ** (-1.0 / 3.0)
        short = hs < h_min
        if short.any():
            # steps the tolerance asks shorter than allowed: those at the shortest, the
            # others shortened so that the model's error is 1 again (K solved for it)
            saturated = float(quad @ short) / t_end

            def profile(log_k):
                return np.clip(np.exp(log_k) * w ** (-1.0 / 3.0), h_min, h_max)

            # K from all steps at the shortest (error below 1) to all at the longest
            lo = np.log(h_min) + np.log(w.min()) / 3.0 - 1.0
            hi = np.log(h_max) + np.log(w.max()) / 3.0 + 1.0
            if log_error(profile(hi)) <= 0:
                hs = profile(hi)
            else:
                hs = profile(brentq(lambda v: log_error(profile(v)), lo, hi, xtol=1e-6))
    else:
        hs = np.full(tp.size, h_max)
    hs = np.clip(hs, h_min, h_max)
    for i in range(1, hs.size):                  # growth ratio between neighbours
        hs[i] = min(hs[i], GROWTH * hs[i - 1])
    for i in range(hs.size - 2, -1, -1):
        hs[i] = min(hs[i], GROWTH * hs[i + 1])
    # the ladder H 2^(k / LADDER), rounded down
    hs = hc * 2.0 ** (np.floor(LADDER * np.log2(hs / hc) + 1e-9) / LADDER)
    count = float(quad @ (1.0 / hs))
    if count > MAX_STEPS:
        raise ResourceError(
            f"{_tolerance_text(tol, rtol)} needs about {count:.3g} error-controlled steps to "
            f"t_end = {t_end:g} s, more than the core's {MAX_STEPS}: give a larger "
            "tolerance or a shorter t_end", required=40.0 * count, available=None)
    # march: each step the shortest the density asks within it
    times = [0.0]
    while t_end - times[-1] > 1e-12 * t_end:
        t = times[-1]
        i0 = int(np.floor(t / hf))
        step = hs[min(i0, hs.size - 1)]
        i1 = int(np.ceil((t + step) / hf))
        step = min(step, hs[i0:max(i1, i0 + 1) + 1].min())
        rest = t_end - t
        if rest <= 1.5 * step:
            step = rest if rest <= step * (1 + 1e-9) else rest / 2
        times.append(t + step)
    times[-1] = t_end
    grid = np.array(times)
    if info is not None:
        # the error model on the grid itself: (c / s) sum h_n^3 w(t_n + h_n / 2)
        dh = np.diff(grid)
        estimated = 0.0 if c <= 0 else float(np.exp(
            np.log(c) + np.log(float(np.sum(dh**3 * np.interp(grid[:-1] + dh / 2, tp, w))))
            - log_s))
        with np.errstate(over="ignore"):
            coarse = float(np.exp(np.log(e_u) - log_s)) if e_u > 0 else 0.0
        info.update(coarse_error=coarse,
                    predicted_steps=grid.size - 1, estimated_error=estimated,
                    saturated=saturated)
    return grid
