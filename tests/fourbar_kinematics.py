"""The four-bar's rigid kinematics in closed form (loop closure by circle intersection): an
analytic reference FOR TESTS ONLY (the library computes every rigid reference by position
analysis, flexmbs.model.kinematics; this is the independent check of it)."""
import numpy as np


def fourbar_positions(theta, lengths, ground, branch="upper", rate=None, accel=None):
    """Rigid four-bar kinematics from the loop-closure equations, in closed form (vectorized).

    O = (0, 0), A = l1 (cos theta, sin theta), C = (ground, 0); B is the intersection of the
    circles of radius l2 about A and l3 about C, to the left of the directed line A -> C for
    branch="upper" (to the right for "lower").

    lengths = (l1, l2, l3): crank, coupler, follower (m); ground: l4 (m); rate, accel: crank
    angular velocity and acceleration (optional). Returns a dict with A, B (n, 2), phi_coupler
    (angle of A -> B), phi_follower (angle of C -> B), and with rate (and accel) their rates
    (and accelerations) from the differentiated loop closure
    l1 e(theta) + l2 e(phi2) - l3 e(phi3) = (l4, 0).
    """
    l1, l2, l3 = (float(v) for v in lengths)
    th = np.asarray(theta, float)
    A = np.stack([l1 * np.cos(th), l1 * np.sin(th)], axis=-1)
    AC = np.array([float(ground), 0.0]) - A
    d = np.hypot(AC[..., 0], AC[..., 1])
    a = (l2 * l2 - l3 * l3 + d * d) / (2 * d)
    h2 = l2 * l2 - a * a
    if np.any(h2 <= 0):
        raise ValueError("four-bar: the loop does not close at some crank angle")
    hh = np.sqrt(h2) * (1.0 if branch == "upper" else -1.0)
    u = AC / d[..., None]
    n = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    B = A + a[..., None] * u + hh[..., None] * n
    out = dict(A=A, B=B, phi_coupler=np.arctan2(B[..., 1] - A[..., 1], B[..., 0] - A[..., 0]),
               phi_follower=np.arctan2(B[..., 1], B[..., 0] - float(ground)))
    if rate is None:
        return out
    p2, p3 = out["phi_coupler"], out["phi_follower"]

    def e(p):
        return np.stack([np.cos(p), np.sin(p)], axis=-1)

    def eperp(p):
        return np.stack([-np.sin(p), np.cos(p)], axis=-1)

    # [l2 e_perp(phi2), -l3 e_perp(phi3)] [phi2', phi3'] = rhs
    m11, m21 = l2 * eperp(p2)[..., 0], l2 * eperp(p2)[..., 1]
    m12, m22 = -l3 * eperp(p3)[..., 0], -l3 * eperp(p3)[..., 1]
    det = m11 * m22 - m12 * m21

    def solve(rhs):
        return ((m22 * rhs[..., 0] - m12 * rhs[..., 1]) / det,
                (-m21 * rhs[..., 0] + m11 * rhs[..., 1]) / det)

    w = np.asarray(rate, float)
    w2, w3 = solve(-l1 * w[..., None] * eperp(th))
    out["phi_coupler_rate"], out["phi_follower_rate"] = w2, w3
    if accel is not None:
        al = np.asarray(accel, float)
        rhs = (-l1 * (al[..., None] * eperp(th) - (w * w)[..., None] * e(th))
               + l2 * (w2 * w2)[..., None] * e(p2) - l3 * (w3 * w3)[..., None] * e(p3))
        out["phi_coupler_accel"], out["phi_follower_accel"] = solve(rhs)
    return out
