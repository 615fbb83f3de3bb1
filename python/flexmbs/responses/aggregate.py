"""Aggregation of a response history over time, with its design gradient.

A time response r_n (n = 1..nt; a deviation, a stress, a motor torque, ...) enters an
optimization problem either as one constraint per time step (the paper's local constraints) or
aggregated into one smooth number per time window, as the global constraints of eq. (22) of the
paper suggest. `aggregate` offers:

- 'every_step': the history itself (within the window): local constraints r_n <= limit.
- 'max': max_n r_n. Its gradient is the gradient of the largest sample (a subgradient: the
  maximum has a kink wherever two samples tie, so a gradient-based optimizer may zig-zag).
- 'ks': the Kreisselmeier-Steinhauser function (Kreisselmeier & Steinhauser, 1979)
  KS = m + ln(sum_n exp(rho (r_n - m))) / rho, m = max_n r_n (the shift keeps exp finite).
  Smooth; max r <= KS <= max r + ln(N) / rho over N samples.
- 'pnorm': (sum_n |r_n|^P)^(1/P), computed as m (sum (|r_n| / m)^P)^(1/P), m = max |r_n|.
  Smooth where no r_n is zero; max |r| <= PN <= N^(1/P) max |r|. Meant for magnitudes
  (r_n >= 0: stresses, deviations over their limits).
- 'integral': the time integral of the history by the trapezoid rule on its time grid t
  (`integral`): sum_n w_n r_n with w_n = (t_{n+1} - t_{n-1}) / 2 inside, half a step at the
  ends; in r's units times seconds. Linear, so its gradient is the same sum of the gradients.
  With a window, over the time points inside it (the window's ends snapped inwards to the
  grid). One sample per time step; takes no parameter.

A history may carry more than one sample per time step (r of shape (nt, m): the stations of a
beam's elements, say); the aggregate then runs over every sample of every step in the window.

The parameters rho (KS) and P (p-norm) have the defaults of DEFAULT_PARAMETER, rho = 100 and
P = 50, chosen for responses normalized by their limits (r ~ 1): the KS bound ln(N)/rho is then
a relative one. For a response in physical units (Pa, N m), normalize it first (r / limit) or
give rho in units of 1/r.
"""
from __future__ import annotations

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["aggregate", "aggregate_weights", "ks", "pnorm", "integral", "trapezoid_weights",
           "window_mask",
           "aggregate_constraints", "AGGREGATES", "DEFAULT_PARAMETER"]

#: Names accepted by `aggregate(how=...)`.
AGGREGATES = ("every_step", "max", "ks", "pnorm", "integral")
#: Default rho of KS and P of the p-norm (for responses normalized by their limits).
DEFAULT_PARAMETER = {"ks": 100.0, "pnorm": 50.0}


def ks(r, dr=None, rho=DEFAULT_PARAMETER["ks"]):
    """Kreisselmeier-Steinhauser aggregate of the samples r (any shape) and its gradient.

    KS = m + ln(sum exp(rho (r - m))) / rho with m = max r; dKS = sum w dr with the weights
    w = exp(rho (r - m)) / sum exp(rho (r - m)) (they sum to 1). dr: r.shape + (nv,) or None.
    Returns (KS, dKS (nv,) or None).
    """
    val, w = _ks_weights(r, rho, dr is not None)
    if dr is None:
        return val, None
    return val, w @ np.asarray(dr, float).reshape(w.size, -1)


def _ks_weights(r, rho, weights=True):
    """KS of the samples r and its weights dKS/dr (flat; None unless weights)."""
    r = np.asarray(r, float).ravel()
    m = r.max()
    e = np.exp(rho * (r - m))
    val = m + np.log(e.sum()) / rho
    return float(val), (e / e.sum() if weights else None)


def pnorm(r, dr=None, p=DEFAULT_PARAMETER["pnorm"]):
    """p-norm (sum |r|^P)^(1/P) of the samples r (any shape) and its gradient.

    Computed as m (sum (|r| / m)^P)^(1/P), m = max |r|; d = sum (|r| / PN)^(P-1) sign(r) dr.
    All samples zero: 0 with a zero gradient. Returns (PN, dPN (nv,) or None).
    """
    val, w = _pnorm_weights(r, p, dr is not None)
    if dr is None:
        return val, None
    return val, w @ np.asarray(dr, float).reshape(w.size, -1)


def _pnorm_weights(r, p, weights=True):
    """p-norm of the samples r and its weights dPN/dr (flat; None unless weights)."""
    r = np.asarray(r, float).ravel()
    a = np.abs(r)
    m = a.max()
    if m <= 0.0:
        return 0.0, (np.zeros(r.size) if weights else None)
    sc = a / m
    norm = np.sum(sc ** p) ** (1.0 / p)
    if not weights:
        return float(m * norm), None
    return float(m * norm), (sc / norm) ** (p - 1.0) * np.sign(r)


def trapezoid_weights(t):
    """Weights w (nt,) of the trapezoid rule on the times t (increasing): integral of r over
    [t_0, t_end] ~ w . r, w_n = (t_{n+1} - t_{n-1}) / 2 inside, (t_1 - t_0) / 2 and
    (t_end - t_{end-1}) / 2 at the ends; zero for a single time point."""
    t = np.asarray(t, float)
    w = np.zeros(t.shape)
    if t.size >= 2:
        dt = np.diff(t)
        w[:-1] += dt / 2
        w[1:] += dt / 2
    return w


def integral(r, dr=None, t=None):
    """Time integral of a history r (nt,) on its times t (nt,) by the trapezoid rule
    (`trapezoid_weights`), and its gradient from dr (nt, nv). Returns (value, (nv,) or None)."""
    r = np.asarray(r, float)
    if t is None:
        raise ModelError("aggregation 'integral' needs the times t of the history")
    t = np.asarray(t, float)
    if r.ndim != 1:
        raise ModelError(f"aggregation 'integral' takes one sample per time step (a history of "
                         f"shape (nt,)), got shape {r.shape}")
    if t.shape != r.shape or (t.size > 1 and not np.all(np.diff(t) > 0)):
        raise ModelError(f"t must be increasing times of shape {r.shape} for 'integral', got "
                         f"shape {t.shape}")
    w = trapezoid_weights(t)
    val = float(w @ r)
    if dr is None:
        return val, None
    return val, w @ np.asarray(dr, float).reshape(r.size, -1)


def window_mask(t, window):
    """Boolean mask of the times t (nt,) inside window = (t0, t1), both ends included (to
    1e-9 of the time span, so that grid points on the ends count); None: every time."""
    t = np.asarray(t, float)
    if window is None:
        return np.ones(t.shape, bool)
    try:
        t0, t1 = (float(v) for v in window)
    except (TypeError, ValueError):
        raise ModelError(f"window must be a pair (t0, t1) of times in s, got {window!r}") from None
    if not (np.isfinite(t0) and np.isfinite(t1) and t0 <= t1):
        raise ModelError(f"window must be finite with t0 <= t1, got {window!r}")
    tol = 1e-9 * max(1.0, float(np.abs(t).max()) if t.size else 1.0)
    mask = (t >= t0 - tol) & (t <= t1 + tol)
    if not mask.any():
        span = f"[{t[0]:.6g}, {t[-1]:.6g}] s" if t.size else "empty"
        raise ModelError(f"window {window!r} holds no time step of the history ({span})")
    return mask


def aggregate(r, dr=None, how="max", *, parameter=None, t=None, window=None):
    """Aggregate a response history over time (and over its samples per step).

    Parameters
    ----------
    r : (nt,) or (nt, ...) array
        The history: one or more samples per time step.
    dr : r.shape + (nv,) array, optional
        Its derivatives with respect to nv design variables.
    how : {'every_step', 'max', 'ks', 'pnorm', 'integral'}, default 'max'
        See the module docstring.
    parameter : float, optional
        rho of 'ks' (> 0, default 100) or P of 'pnorm' (> 1, default 50); ignored by 'max'
        and 'every_step'; 'integral' takes none (ModelError).
    t : (nt,) array, optional
        Times of the history; required with `window` and by 'integral'.
    window : (t0, t1), optional
        Only the steps with t0 <= t <= t1 count (default: all).

    Returns
    -------
    value, gradient
        'every_step': r and dr restricted to the window (arrays); otherwise a float and an
        (nv,) array. The gradient is None when dr is None.
    """
    if how not in AGGREGATES:
        raise ModelError(f"aggregation how={how!r} is unknown; allowed: {', '.join(AGGREGATES)}")
    r = np.asarray(r, float)
    if r.ndim == 0 or r.shape[0] == 0:
        raise ModelError(f"r must be a history of shape (nt, ...) with nt >= 1, got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ModelError("r holds non-finite values")
    if dr is not None:
        dr = np.asarray(dr, float)
        if dr.ndim != r.ndim + 1 or dr.shape[:-1] != r.shape:
            raise ModelError(f"dr must have shape {r.shape} + (nv,), got {dr.shape}")
    if how == "integral":
        if parameter is not None:
            raise ModelError(f"parameter of 'integral' must not be given (the trapezoid rule "
                             f"takes none), got {parameter!r}")
        if t is None:
            raise ModelError("aggregation 'integral' needs the times t of the history")
    if t is not None and (window is not None or how == "integral"):
        t = np.asarray(t, float)
        if t.shape != (r.shape[0],):
            raise ModelError(f"t must have shape ({r.shape[0]},) like r's first axis, got {t.shape}")
    if window is not None:
        if t is None:
            raise ModelError("window needs the times t of the history")
        mask = window_mask(t, window)
        r = r[mask]
        dr = None if dr is None else dr[mask]
        t = t[mask]
    if how == "integral":
        return integral(r, dr, t)
    if how == "every_step":
        return r, dr
    if how == "max":
        k = int(np.argmax(r.ravel()))
        return float(r.ravel()[k]), (None if dr is None else dr.reshape(r.size, -1)[k].copy())
    par = DEFAULT_PARAMETER[how] if parameter is None else parameter
    least = 1.0 if how == "pnorm" else 0.0
    if not (isinstance(par, (int, float, np.floating, np.integer)) and not isinstance(par, bool)
            and np.isfinite(par) and par > least):
        raise ModelError(f"parameter of {how!r} must be a finite number > {least:g}, got {parameter!r}")
    return (ks if how == "ks" else pnorm)(r, dr, float(par))


def aggregate_weights(r, how="max", *, parameter=None, t=None, window=None):
    """`aggregate` of a history r with the weights of its gradient instead of the gradient:
    (value, W) with W (k, r.size) such that aggregate(r, dr, ...)'s gradient is
    W @ dr.reshape(r.size, nv) (k rows: the window's samples for 'every_step', else 1).
    What the adjoint needs (the weight of every sample), without identity derivatives.
    Arguments, values and errors as `aggregate`."""
    r = np.asarray(r, float)
    value, _ = aggregate(r, None, how, parameter=parameter, t=t, window=window)
    idx = np.arange(r.size).reshape(r.shape)
    if window is not None:
        idx = idx[window_mask(np.asarray(t, float), window)]
        rw = r[window_mask(np.asarray(t, float), window)]
    else:
        rw = r
    idx = idx.ravel()
    if how == "every_step":
        W = np.zeros((idx.size, r.size))
        W[np.arange(idx.size), idx] = 1.0
        return value, W
    W = np.zeros((1, r.size))
    if how == "max":
        W[0, idx[int(np.argmax(rw.ravel()))]] = 1.0
        return value, W
    if how == "integral":       # the trapezoid rule on the window's times
        tw = np.asarray(t, float)
        if window is not None:
            tw = tw[window_mask(tw, window)]
        W[0, idx] = trapezoid_weights(tw)
        return value, W
    par = float(DEFAULT_PARAMETER[how] if parameter is None else parameter)
    W[0, idx] = (_ks_weights if how == "ks" else _pnorm_weights)(rw, par)[1]
    return value, W


def aggregate_constraints(ratio, d_ratio, kind, parameter, windows):
    """Aggregate relative responses r_n >= 0 (constraint r_n - 1 <= 0) over index windows.

    Used by the fully coupled method (flexmbs.methods.fully).

    Parameters
    ----------
    ratio : (nt,) r_n (a response over its limit, or its square).
    d_ratio : (nt, nv) or None, derivatives of r_n.
    kind : {'ks', 'pnorm'}
        'ks': G = KS(r) - 1 (`ks`): max g <= G <= max g + ln(N) / rho with g_n = r_n - 1.
        'pnorm': G = PN(r) - 1 (`pnorm`): max r <= G + 1 <= N^(1/P) max r.
    parameter : float
        rho (ks) or P (pnorm).
    windows : list of index arrays (the time steps of each window).

    Returns
    -------
    G : (nw,) aggregated constraints; dG : (nw, nv) or None, their derivatives.
    """
    if kind not in ("ks", "pnorm"):
        raise ModelError(f"aggregation kind must be 'ks' or 'pnorm', got {kind!r}")
    r = np.asarray(ratio, float)
    nw = len(windows)
    G = np.empty(nw)
    dG = None if d_ratio is None else np.empty((nw, d_ratio.shape[1]))
    fun = ks if kind == "ks" else pnorm
    for k, idx in enumerate(windows):
        val, grad = fun(r[idx], None if d_ratio is None else d_ratio[idx], parameter)
        G[k] = val - 1.0
        if dG is not None:
            dG[k] = grad
    return G, dG
