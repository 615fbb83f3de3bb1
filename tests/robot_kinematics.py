"""Analytic kinematics of the paper's 2-dof robot (a planar 2R arm whose tip follows the
straight line of eq. (26)), an independent reference for the tests: the library computes the
rigid reference by position analysis of the described mechanism (flexmbs.model.kinematics) and knows
no mechanism by name; the tests compare it with these closed forms.
"""
import numpy as np

from flexmbs.errors import ModelError
from flexmbs.model.laws import TimeLaw


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
