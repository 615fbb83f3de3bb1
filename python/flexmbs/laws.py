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
        except (TypeError, ValueError, IndexError):
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


def planar_2r_inverse(x, y, xd, yd, xdd, ydd, l1, l2, elbow=-1.0):
    """Inverse kinematics of a planar 2R arm with first and second derivatives.

    Returns (theta1, theta2, dtheta1, dtheta2, ddtheta1, ddtheta2) arrays; theta1 is
    the first link's angle w.r.t. the ground, theta2 the second's w.r.t. the first;
    elbow = -1 takes the branch theta2 < 0. Rates from J dtheta = dp and
    accelerations from J ddtheta = ddp - dJ dtheta (J of eq. 36).
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    c2 = (x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2)
    out = np.abs(c2) > 1 + 1e-12
    if np.any(out):
        k = int(np.flatnonzero(np.ravel(out))[0])
        err = ModelError(f"2R inverse kinematics: target out of reach (sample {k})")
        err.index = k
        raise err
    th2 = elbow * np.arccos(np.clip(c2, -1.0, 1.0))
    th1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(th2), l1 + l2 * np.cos(th2))
    s1, c1 = np.sin(th1), np.cos(th1)
    s12, c12 = np.sin(th1 + th2), np.cos(th1 + th2)
    j11, j12 = -l1 * s1 - l2 * s12, -l2 * s12
    j21, j22 = l1 * c1 + l2 * c12, l2 * c12
    det = j11 * j22 - j12 * j21
    d1 = (j22 * xd - j12 * yd) / det
    d2 = (-j21 * xd + j11 * yd) / det
    # dJ dtheta
    w1, w12 = d1, d1 + d2
    bx = -l1 * c1 * w1 * w1 - l2 * c12 * w12 * w12
    by = -l1 * s1 * w1 * w1 - l2 * s12 * w12 * w12
    rx, ry = xdd - bx, ydd - by
    dd1 = (j22 * rx - j12 * ry) / det
    dd2 = (-j21 * rx + j11 * ry) / det
    return th1, th2, d1, d2, dd1, dd2


def robot_tip_path(t, x0, y0, period=0.5, stroke=0.5):
    """The paper's eq. (26): x = x0 + D(t), y = y0 + D(t),
    D(t) = (stroke/T)(t - T/(2 pi) sin(2 pi t/T)); returns (x, y, xd, yd, xdd, ydd)."""
    t = np.asarray(t, float)
    w = 2 * np.pi / period
    d = stroke / period * (t - np.sin(w * t) / w)
    dd = stroke / period * (1 - np.cos(w * t))
    ddd = stroke / period * w * np.sin(w * t)
    return x0 + d, y0 + d, dd, dd, ddd, ddd


def robot_joint_laws(l1=0.6, l2=0.6, theta1_0=np.radians(120.0), theta2_0=np.radians(-150.0),
                     period=0.5, stroke=0.5):
    """TimeLaws theta1(t) (arm 1 w.r.t. ground), theta2(t) (arm 2 w.r.t. arm 1) and
    theta1 + theta2 (arm 2 w.r.t. ground) that move the 2R robot's tip along eq. (26)."""
    x0 = l1 * np.cos(theta1_0) + l2 * np.cos(theta1_0 + theta2_0)
    y0 = l1 * np.sin(theta1_0) + l2 * np.sin(theta1_0 + theta2_0)
    elbow = -1.0 if np.sin(theta2_0) < 0 else 1.0

    def joints(t):
        try:
            return planar_2r_inverse(*robot_tip_path(t, x0, y0, period, stroke), l1, l2, elbow)
        except ModelError as exc:
            tk = np.ravel(t)[getattr(exc, "index", 0)]
            raise ModelError(f"the tip path of eq. (26) is out of reach of the arms at "
                             f"t = {tk:.4f} s (past the singular posture)") from None

    def pick(i, j=None):
        if j is None:
            return lambda t: joints(t)[i]
        return lambda t: joints(t)[i] + joints(t)[j]

    th1 = TimeLaw(pick(0), pick(2), pick(4), name="theta1")
    th2 = TimeLaw(pick(1), pick(3), pick(5), name="theta2")
    th12 = TimeLaw(pick(0, 1), pick(2, 3), pick(4, 5), name="theta1+theta2")
    return th1, th2, th12
