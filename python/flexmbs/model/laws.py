"""Time laws with analytic first and second derivatives (motors, loads)."""
from __future__ import annotations

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.model.sections import real_number

__all__ = ["TimeLaw", "as_law", "EXTRAPOLATIONS"]

#: what a sampled law may be beyond its samples (TimeLaw.samples); None: an error
EXTRAPOLATIONS = (None, "hold", "linear")


class _Ends:
    """A sampled law's interpolant inside its samples' span [lo, hi] and its extrapolation
    outside (TimeLaw.samples): None refuses a time outside (ModelError), 'hold' keeps the end
    value, 'linear' goes on along the end tangent."""

    def __init__(self, t, spline, how):
        self.lo, self.hi, self.spline, self.how = float(t[0]), float(t[-1]), spline, how
        self.tol = 1e-9 * max(1.0, abs(self.lo), abs(self.hi))   # a grid's rounding
        d1 = spline.derivative(1)
        self.d1, self.d2 = d1, spline.derivative(2)
        self.y = (float(spline(self.lo)), float(spline(self.hi)))
        self.s = (0.0, 0.0) if how != "linear" else (float(d1(self.lo)), float(d1(self.hi)))

    def _split(self, t):
        t = np.asarray(t, float)
        below, above = t < self.lo - self.tol, t > self.hi + self.tol
        if self.how is None and (below.any() or above.any()):
            bad = t[below | above].ravel()[0]
            raise ModelError(
                f"t = {bad:.6g} s is outside its samples' times ({self.lo:.6g} to {self.hi:.6g} s); "
                "a sampled law is not extended beyond its table unless asked: give samples up "
                "to the end of the run, or extrapolate = 'hold' (the end value) or 'linear' "
                "(on along the end tangent)")
        return t, below, above, np.clip(t, self.lo, self.hi)

    def value(self, t):
        t, below, above, tc = self._split(t)
        out = self.spline(tc)
        return np.where(below, self.y[0] + self.s[0] * (t - self.lo),
                        np.where(above, self.y[1] + self.s[1] * (t - self.hi), out))

    def rate(self, t):
        t, below, above, tc = self._split(t)
        return np.where(below, self.s[0], np.where(above, self.s[1], self.d1(tc)))

    def accel(self, t):
        t, below, above, tc = self._split(t)
        return np.where(below | above, 0.0, self.d2(tc))


class _Constant:
    """t -> c of t's shape (picklable, as the callables below: a law, and a Problem holding
    it, can be sent to another process)."""

    def __init__(self, c):
        self.c = c

    def __call__(self, t):
        return np.full(np.shape(t), self.c) if self.c else np.zeros(np.shape(t))


class _Pieces:
    """Value (which = 0), rate (1) or acceleration (2) of the law of t's interval
    (TimeLaw.piecewise)."""

    def __init__(self, breaks, laws, which):
        self.breaks, self.laws, self.which = breaks, laws, which

    def __call__(self, t):
        t = np.asarray(t, float)
        k = np.searchsorted(self.breaks, t, side="right")
        out = np.zeros(t.shape)
        for i, law in enumerate(self.laws):
            m = k == i
            if np.any(m):
                out[m] = law.evaluate(t[m])[self.which]
        return out


class _Terms:
    """Value (which = 0), rate (1) or acceleration (2) of a sum of laws (TimeLaw.sum)."""

    def __init__(self, laws, which):
        self.laws, self.which = laws, which

    def __call__(self, t):
        return sum(law.evaluate(np.asarray(t, float))[self.which] for law in self.laws)


class TimeLaw:
    """A scalar function of time with its first and second derivatives.

    Parameters
    ----------
    value, rate, accel : callables of time
        theta(t), theta'(t), theta''(t). All are evaluated once on the simulation's time
        grid before the Fortran loop starts: on the whole array of times at once, or, for a
        function of a single time (a Python `if`, math functions), time by time. If `rate` or
        `accel` is missing it is obtained by central differences (step 1e-6 s);
        give them analytically where you can.
    name : str
        Shown in error messages.
    """

    def __init__(self, value, rate=None, accel=None, name="law"):
        if not isinstance(name, str):
            raise ModelError(f"TimeLaw name must be a string, got {name!r}")
        if not callable(value):
            raise ModelError(f"time law {name!r}: value must be a callable of t, got {value!r}")
        for what, f in (("rate", rate), ("accel", accel)):
            if f is not None and not callable(f):
                raise ModelError(f"time law {name!r}: {what} must be a callable of t or None, "
                                 f"got {f!r}")
        self.value = value
        self.rate = rate
        self.accel = accel
        self.name = name

    @classmethod
    def constant(cls, c, name="constant"):
        """theta(t) = c."""
        c = real_number(f"TimeLaw.constant {name!r}: c", c)
        return cls(_Constant(c), _Constant(0.0), _Constant(0.0), name=name)

    @classmethod
    def samples(cls, t, values, name="samples", interpolation="cubic", extrapolate=None):
        """A law through sampled values.

        interpolation: 'cubic' (cubic spline, not-a-knot: smooth, continuous acceleration, but
        it overshoots between samples of a step-like profile) or 'pchip' (monotone piecewise
        cubic Hermite, scipy's PchipInterpolator: no overshoot, continuous rate, acceleration
        piecewise).
        extrapolate: what the law is outside [t[0], t[-1]]: None (default: evaluating it
        there is a ModelError naming the time and the samples' span), 'hold' (the end sample's
        value, zero rate and acceleration) or 'linear' (on along the end's tangent: the
        interpolant's rate at the end sample, zero acceleration)."""
        from scipy.interpolate import CubicSpline, PchipInterpolator
        if interpolation not in ("cubic", "pchip"):
            raise ModelError(f"TimeLaw.samples {name!r}: interpolation must be 'cubic' or "
                             f"'pchip', got {interpolation!r}")
        if extrapolate not in EXTRAPOLATIONS:
            raise ModelError(f"TimeLaw.samples {name!r}: extrapolate must be None, 'hold' or "
                             f"'linear', got {extrapolate!r}")
        arrays = []
        for what, v in (("t", t), ("values", values)):
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                a = None
            if a is None or a.ndim != 1 or a.size < 2 or np.asarray(v).dtype.kind not in "iuf" \
                    or not np.all(np.isfinite(a)):
                raise ModelError(f"TimeLaw.samples {name!r}: {what} must be a 1-D array of at least "
                                 f"2 finite numbers, got {v!r}")
            arrays.append(a)
        if arrays[0].size != arrays[1].size:
            raise ModelError(f"TimeLaw.samples {name!r}: t and values must have the same length, "
                             f"got {arrays[0].size} and {arrays[1].size}")
        if np.any(np.diff(arrays[0]) <= 0):
            raise ModelError(f"TimeLaw.samples {name!r}: t must be strictly increasing")
        with np.errstate(all="ignore"):
            dt, dv = np.diff(arrays[0]), np.diff(arrays[1])
            slopes = dv / dt
            curvature = slopes / dt
        if not (np.all(np.isfinite(dt)) and np.all(np.isfinite(dv)) and np.all(dt > 0)
                and np.all(np.isfinite(slopes)) and np.all(np.isfinite(curvature))):
            raise ModelError(f"TimeLaw.samples {name!r}: the differences of t and values and "
                             f"the slopes between samples overflow or underflow double "
                             f"precision (t from {arrays[0].min():.3g} to "
                             f"{arrays[0].max():.3g} s, values from {arrays[1].min():.3g} to "
                             f"{arrays[1].max():.3g}); give samples whose rate and acceleration "
                             f"are finite numbers")
        try:
            with np.errstate(all="ignore"):
                spline = (CubicSpline if interpolation == "cubic" else PchipInterpolator)(
                    arrays[0], arrays[1])
        except ValueError as exc:
            raise ModelError(f"TimeLaw.samples {name!r}: no interpolant through the samples "
                             f"({exc})") from None
        ends = _Ends(arrays[0], spline, extrapolate)
        return cls(ends.value, ends.rate, ends.accel, name=name)

    @classmethod
    def piecewise(cls, breaks, laws, name="piecewise"):
        """laws[k] on [breaks[k-1], breaks[k]) (laws[0] before breaks[0], the last law from
        breaks[-1] on), each evaluated at the absolute time t: value, rate and acceleration
        are those of the law of t's interval (at a break, the later law's). Nothing makes the
        pieces meet: give laws whose values (and rates, for a drive) agree at the breaks."""
        laws = [as_law(law, f"{name} segment {k + 1}") for k, law in enumerate(laws)]
        try:
            b = np.asarray(breaks, dtype=float).ravel()
        except (TypeError, ValueError):
            b = None
        if b is None or b.size != len(laws) - 1 or not np.all(np.isfinite(b)) \
                or np.any(np.diff(b) <= 0) or not laws:
            raise ModelError(f"TimeLaw.piecewise {name!r}: breaks must be {max(len(laws) - 1, 0)} "
                             f"finite increasing times (one fewer than the {len(laws)} laws), "
                             f"got {breaks!r}")
        return cls(*(_Pieces(b, laws, which) for which in range(3)), name=name)

    @classmethod
    def sum(cls, laws, name="sum"):
        """The sum of laws (values, rates and accelerations added)."""
        laws = [as_law(law, f"{name} term {k + 1}") for k, law in enumerate(laws)]
        if not laws:
            raise ModelError(f"TimeLaw.sum {name!r}: needs at least one law")
        return cls(*(_Terms(laws, which) for which in range(3)), name=name)

    def _eval(self, f, t, what):
        ta = np.asarray(t, float)
        try:
            out = np.asarray(f(ta), dtype=float)
            if out.shape not in ((), ta.shape):
                raise ValueError("shape")
        except ModelError as exc:
            raise ModelError(f"time law {self.name!r}: {exc}") from None
        except (TypeError, ValueError, IndexError, ArithmeticError):
            # a function of one time (a Python `if`, math.sin): evaluate it time by time
            try:
                out = np.array([float(f(float(tk))) for tk in ta.ravel()]).reshape(ta.shape)
            except ModelError as exc:
                raise ModelError(f"time law {self.name!r}: {exc}") from None
            except (TypeError, ValueError, ArithmeticError) as exc:
                raise ModelError(f"time law {self.name!r}: its {what} cannot be evaluated at "
                                 f"the times of the grid ({type(exc).__name__}: {exc})") from None
        out = np.broadcast_to(out, np.shape(t)).astype(float)
        if not np.all(np.isfinite(out)):
            bad = np.asarray(t)[~np.isfinite(out)].ravel()
            raise ModelError(f"time law {self.name!r}: {what} is not finite at t = {bad[0]:.6g} s")
        return out

    def _value_rate(self, t):
        v = self._eval(self.value, t, "value")
        if self.rate is not None:
            return v, self._eval(self.rate, t, "rate")
        e = 1e-6
        return v, (self._eval(self.value, t + e, "value")
                   - self._eval(self.value, t - e, "value")) / (2 * e)

    def _accel(self, t, v):
        if self.accel is not None:
            return self._eval(self.accel, t, "acceleration")
        e = 1e-4
        return (self._eval(self.value, t + e, "value") - 2 * v
                + self._eval(self.value, t - e, "value")) / e ** 2

    def evaluate(self, t):
        """(theta, theta', theta'') on the grid t, each an array of t's shape.

        Missing derivatives come from central differences of the value (steps 1e-6 s for the
        rate, 1e-4 s for the acceleration), as in `tabulate`.
        """
        t = np.asarray(t, float)
        v, d = self._value_rate(t)
        return v, d, self._accel(t, v)

    def tabulate(self, t):
        """(theta, theta') on the grid t and theta''(t[0])."""
        t = np.asarray(t, float)
        v, d = self._value_rate(t)
        return v, d, self._accel(t[:1], v[:1])[0]


def as_law(obj, name="law"):
    """A TimeLaw from a TimeLaw, a number (constant) or a callable."""
    if isinstance(obj, TimeLaw):
        return obj
    if obj is None:
        return None
    if callable(obj):
        return TimeLaw(obj, name=name)
    if isinstance(obj, (bool, np.bool_, str, bytes)) or not np.isscalar(obj):
        raise ModelError(f"{name}: law must be a TimeLaw, a finite number or a callable of t, "
                         f"got {obj!r} ({type(obj).__name__})")
    real_number(f"{name}: law", obj)
    return TimeLaw.constant(obj, name=name)
