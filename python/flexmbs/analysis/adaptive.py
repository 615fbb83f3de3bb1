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
   K^2 int w^(1/3) dt = 1 / c; bounded by h_max and H / 1024, by a growth ratio of
   `GROWTH` between neighbours, and rounded down to the ladder H 2^(k/4), so that runs of
   equal steps keep modified Newton's held factorizations (generalized_alpha.f90 refactors
   when the step changes).

Within an optimization run the grid is chosen once (at the problem's start design, or at
another by Problem.adapt) and then frozen: the responses are then smooth functions of
the design, and their direct and adjoint derivatives are exact on that grid.
"""
from __future__ import annotations

import numpy as np

from flexmbs.errors import CaseError
from flexmbs.responses.aggregate import trapezoid_weights

__all__ = ["choose_steps", "subdivide", "GROWTH", "LADDER"]

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


def _histories(values, nt):
    """(nt, k) columns of the response histories among `values` (name -> value)."""
    cols = [np.asarray(v, float).reshape(nt, -1) for v in values.values()
            if np.ndim(v) >= 1 and np.shape(v)[0] == nt]
    return np.hstack(cols) if cols else np.zeros((nt, 0))


def _tolerances(r, tol, rtol):
    """Each history's tolerance tol + rtol max|r|."""
    return (tol or 0.0) + (rtol or 0.0) * np.abs(r).max(axis=0)


def choose_steps(problem, x=None, *, tol=None, rtol=None, h_max=None, info=None):
    """A non-uniform step grid (times from 0 to t_end) for design x (default: the start) of
    `problem` (flexmbs.Problem) whose responses' histories are estimated to be within the
    tolerance (tol + rtol max|r| each; default: the case's time.tol, time.rtol, time.h_max).
    The module docstring tells how. `info`, a dict, receives the pilots' cost and estimates:
    pilot_steps, pilot_seconds, coarse_error (e_H, in tolerances), predicted_steps."""
    import time

    ts = problem.description.time
    tol = ts.tol if tol is None else tol
    rtol = ts.rtol if rtol is None else rtol
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
    if h_max < hc / SHORTEST:
        raise CaseError(f"time.h_max = {h_max:g} s is below the shortest step the grid takes, "
                        f"1/{SHORTEST} of the coarse pilot's {hc:g} s ({hc / SHORTEST:g} s): "
                        "give a larger h_max, or a fixed step time.h")
    nc = int(round(t_end / hc))
    t0 = time.perf_counter()
    rc = _histories(problem.values_on(x, np.linspace(0.0, t_end, nc + 1)), n + 1)
    rf = _histories(problem.values_on(x, np.linspace(0.0, t_end, 2 * nc + 1)), n + 1)
    seconds = time.perf_counter() - t0
    if rf.shape[1] == 0:      # nothing to control: the longest steps allowed
        m = max(1, int(np.ceil(t_end / h_max)))
        return np.linspace(0.0, t_end, m + 1)
    tr = _tolerances(rf, tol, rtol)
    tr = np.where(tr > 0, tr, np.inf)
    e_coarse = 4.0 / 3.0 * float(np.max(np.abs(rc - rf) / tr))
    # the finer pilot's histories on the response grid (its step or a multiple of it)
    r, hf = rf, h
    d3 = np.abs(np.diff(r, 3, axis=0)) / hf**3 / tr          # at the middles of 4 points
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
    if e_coarse <= 0 or integral_w <= 0:
        c = 0.0
    else:
        c = e_coarse / (hc**2 * integral_w)
    if c > 0:
        k = np.sqrt(1.0 / (c * float(quad @ w ** (1.0 / 3.0))))
        hs = k * w ** (-1.0 / 3.0)
    else:
        hs = np.full(tp.size, h_max)
    hs = np.clip(hs, hc / SHORTEST, h_max)
    for i in range(1, hs.size):                  # growth ratio between neighbours
        hs[i] = min(hs[i], GROWTH * hs[i - 1])
    for i in range(hs.size - 2, -1, -1):
        hs[i] = min(hs[i], GROWTH * hs[i + 1])
    # the ladder H 2^(k / LADDER), rounded down
    hs = hc * 2.0 ** (np.floor(LADDER * np.log2(hs / hc) + 1e-9) / LADDER)
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
        info.update(pilot_steps=3 * nc, pilot_seconds=seconds, coarse_error=e_coarse,
                    predicted_steps=grid.size - 1)
    return grid
