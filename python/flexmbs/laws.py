"""Time laws with analytic first and second derivatives (motors, loads)."""
from __future__ import annotations

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.sections import real_number

__all__ = ["TimeLaw", "as_law"]


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
        return cls(lambda t: np.full(np.shape(t), c), lambda t: np.zeros(np.shape(t)),
                   lambda t: np.zeros(np.shape(t)), name=name)

    @classmethod
    def samples(cls, t, values, name="samples", interpolation="cubic"):
        """A law through sampled values.

        interpolation: 'cubic' (cubic spline, not-a-knot: smooth, continuous acceleration, but
        it overshoots between samples of a step-like profile) or 'pchip' (monotone piecewise
        cubic Hermite, scipy's PchipInterpolator: no overshoot, continuous rate, acceleration
        piecewise)."""
        from scipy.interpolate import CubicSpline, PchipInterpolator
        if interpolation not in ("cubic", "pchip"):
            raise ModelError(f"TimeLaw.samples {name!r}: interpolation must be 'cubic' or "
                             f"'pchip', got {interpolation!r}")
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
        spline = (CubicSpline if interpolation == "cubic" else PchipInterpolator)(arrays[0],
                                                                                 arrays[1])
        return cls(spline, spline.derivative(1), spline.derivative(2), name=name)

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
