"""The rigid reference stays on its assembly branch and stops only at a singular posture
(flexmbs.model.kinematics.rigid_reference: continuation with a Taylor predictor, subdivided steps).

Every reference value is a closed form independent of the iteration under test:
- the slider-crank's slider position x = r cos(theta) + sqrt(l^2 - (r sin(theta) - e)^2),
  e the slide's offset from the crank pivot (any kinematics textbook, e.g. Norton, Design of
  Machinery, section 4.13);
- the four-bar's follower angle from Freudenstein's equation
  K1 cos(theta4) - K2 cos(theta2) + K3 = cos(theta2 - theta4), K1 = d/a, K2 = d/c,
  K3 = (a^2 - b^2 + c^2 + d^2)/(2 a c), solved by the half-angle substitution (Norton,
  section 4.5), on the branch of the first posture;
- the four-bar's toggle: a follower driven past its extreme angle, where the crank and the
  coupler are collinear, |OB| = b + a or b - a (Norton, section 4.9: limit positions).
"""
import math
import re

import numpy as np
import pytest

from flexmbs import Circle, Material, Model, ModelError, TimeLaw
from flexmbs.model.kinematics import rigid_reference
from flexmbs.problem import Problem

MAT = Material(E=7e10, nu=0.3, rho=2700)
SEC = Circle(0.02)


def ramp_angle(t, speed, ramp):
    """The case format's ramp_to_speed law (docs/case-format.md): speed t^2/(2 ramp) up to
    ramp, then speed (t - ramp/2)."""
    t = np.asarray(t, float)
    return np.where(t <= ramp, speed * t * t / (2 * ramp), speed * (t - ramp / 2))


def slider_x(theta, r, l, e):
    """Slider position along the slide (from the crank pivot), closed form."""
    return r * np.cos(theta) + np.sqrt(l * l - (r * np.sin(theta) - e) ** 2)


def freudenstein(theta2, a, b, c, d, sign):
    """Follower angle theta4 (C -> B) of the four-bar O-A-B-C (O at the origin, C = (d, 0)) at
    crank angles theta2, on the branch `sign` (+1 or -1) of the half-angle quadratic."""
    k1, k2, k3 = d / a, d / c, (a * a - b * b + c * c + d * d) / (2 * a * c)
    cos2, sin2 = np.cos(theta2), np.sin(theta2)
    qa = cos2 - k1 - k2 * cos2 + k3
    qb = -2 * sin2
    qc = k1 - (k2 + 1) * cos2 + k3
    return 2 * np.arctan2(-qb + sign * np.sqrt(qb * qb - 4 * qa * qc), 2 * qa)


def slider_crank(r, rod, law):
    """Crank O-A (r, along x, pinned at O and driven by `law`), rod A-B (rod), B held on the
    x axis. Returns the model, the crank and the rod."""
    m = Model("slider-crank")
    crank = m.add_beam("crank", (0.0, 0.0), (r, 0.0), 2, material=MAT, section=SEC)
    link = m.add_beam("rod", (r, 0.0), (r + rod, 0.0), 2, material=MAT, section=SEC)
    m.pin(crank.first)
    m.hinge(crank.last, link.first)
    m.prescribe_position(link.last, y=0.0)
    m.drive_rotation(crank.first, law)
    return m, crank, link


def fourbar_model(a, b, c, d, theta2, sign, drive_follower=None):
    """Crank O-A, coupler A-B, follower C-B, pinned at O and C, assembled at crank angle
    theta2 on the branch `sign`; driven at the crank at 30 rad/s, or, with drive_follower =
    +1 or -1, at the follower at that angular velocity (rad/s). Returns the model, B's node and
    the follower's initial angle."""
    th4 = float(freudenstein(np.array([theta2]), a, b, c, d, sign)[0])
    A = (a * math.cos(theta2), a * math.sin(theta2))
    B = (d + c * math.cos(th4), c * math.sin(th4))
    m = Model("four-bar")
    crank = m.add_beam("crank", (0.0, 0.0), A, 2, material=MAT, section=SEC)
    coupler = m.add_beam("coupler", A, B, 2, material=MAT, section=SEC)
    follower = m.add_beam("follower", (d, 0.0), B, 2, material=MAT, section=SEC)
    m.pin(crank.first)
    m.pin(follower.first)
    m.hinge(crank.last, coupler.first)
    m.hinge(coupler.last, follower.last)
    if drive_follower is None:
        w, start, node = 30.0, theta2, crank.first
    else:
        w, start, node = float(drive_follower), th4, follower.first
    m.drive_rotation(node, TimeLaw(lambda t: start + w * t, lambda t: w + 0 * t,
                                   lambda t: 0 * t))
    return m, coupler.last, th4


# --------------------------------------------------------------------------- press
@pytest.mark.parametrize("rpm", [600.0, 2000.0, 3000.0])
@pytest.mark.parametrize("h", [5e-4, 1e-3])
def test_press_slider_on_branch(rpm, h):
    """cases/slider_crank_press.toml with its motor at 600, 2000, 3000 rpm and steps of 0.5 and
    1 ms: the rigid reference's ram position equals the closed-form slider position (crank
    radius, rod length and slide offset from the case's points, crank angle from its
    ramp_to_speed law) at every time, to 1e-9 m. (The branch's neighbour lies 2 sqrt(l^2 -
    r^2 sin^2) >= 0.77 m away; at 2000 rpm and 0.5 ms the residual floor of a rod angle that
    had wandered many turns once stopped the analysis.)"""
    prob = Problem("slider_crank_press", overrides={"drives.motor.law.speed_rpm": rpm,
                                                    "time.h": h})
    pts = {k: np.array(v, float) for k, v in prob.description.points.items()}
    law = next(d.law for d in prob.description.drives if d.name == "motor")
    r = float(np.linalg.norm(pts["A"] - pts["O"]))
    rod = float(np.linalg.norm(pts["B"] - pts["A"]))
    e = float(pts["B"][1] - pts["O"][1])
    mech = prob.mechanism
    ref = mech.reference
    theta = math.atan2(*(pts["A"] - pts["O"])[::-1]) + ramp_angle(ref.t, rpm * math.pi / 30,
                                                                  law.ramp_s)
    x = ref.coordinates(3 * mech.node[("ram", "B")]) - pts["O"][0]
    assert ref.t.size == round(prob.description.time.t_end / h) + 1
    assert np.abs(x - slider_x(theta, r, rod, e)).max() <= 1e-9


def test_slider_crank_fast_ramp_on_branch():
    """A slider-crank (crank 0.1 m, rod 0.3 m, no offset) whose crank ramps to 150 rad/s in
    0.02 s, 201 times over 0.5 s (0.375 rad of crank per step): the slider's position equals
    the closed form at every time to 1e-9 m, and its rate the closed form's derivative to
    1e-8 m/s."""
    r, rod, w, ramp = 0.1, 0.3, 150.0, 0.02
    m, _, link = slider_crank(r, rod, TimeLaw(
        lambda t: ramp_angle(t, w, ramp), lambda t: np.where(t <= ramp, w * t / ramp, w),
        lambda t: np.where(t <= ramp, w / ramp, 0.0)))
    t = np.linspace(0.0, 0.5, 201)
    ref = rigid_reference(m, t)
    th = ramp_angle(t, w, ramp)
    thd = np.where(t <= ramp, w * t / ramp, w)
    s = np.sqrt(rod * rod - (r * np.sin(th)) ** 2)
    xd = (-r * np.sin(th) - r * r * np.sin(th) * np.cos(th) / s) * thd
    assert np.abs(ref.coordinates(3 * link.last) - slider_x(th, r, rod, 0.0)).max() <= 1e-9
    assert np.abs(ref.coordinates(3 * link.last, 1) - xd).max() <= 1e-8


def test_links_after_many_turns_converge_at_rounding_level():
    """A slider-crank whose crank and rod start after 10^5 turns (angles of 6.3e5 rad: a unit
    in their last place, 1.2e-10 rad, moves the rod's ends by ~1e-11 m, above the 1e-12
    tolerance), the crank driven at 40 rad/s: the analysis converges at that rounding level
    and the slider follows the closed form to 1e-9 m."""
    r, rod, th0 = 0.1, 0.3, 2 * math.pi * 1e5
    m, crank, link = slider_crank(r, rod, TimeLaw(lambda t: th0 + 40.0 * t,
                                                  lambda t: 40.0 + 0 * t, lambda t: 0 * t))
    q0 = m.reference_coordinates()
    q0[3 * np.array(crank.nodes + link.nodes) + 2] += th0
    t = np.linspace(0.0, 0.3, 301)
    ref = rigid_reference(m, t, q0)
    assert np.abs(ref.coordinates(3 * link.last) - slider_x(40.0 * t, r, rod, 0.0)).max() <= 1e-9


# --------------------------------------------------------------------------- four-bar
@pytest.mark.parametrize("sign", [1, -1])
@pytest.mark.parametrize("links", [(1.0, 3.0, 2.2, 3.0), (0.3048, 0.9144, 0.762, 0.9144)])
def test_fourbar_full_turn_freudenstein(links, sign):
    """Grashof crank-rockers (crank, coupler, follower, ground: 1, 3, 2.2, 3 m, and the
    paper's four-bar of cases/fourbar.toml: 1, 3, 2.5, 3 ft) on either
    assembly branch, the crank driven through a full turn in 12 steps of 30 deg: B follows
    Freudenstein's closed form on the branch it started on at every time, to 1e-9 m (steps
    this long are subdivided: substeps were used)."""
    a, b, c, d = links
    m, node_b, _ = fourbar_model(a, b, c, d, 0.3, sign)
    t = np.linspace(0.0, 2 * math.pi / 30.0, 13)
    ref = rigid_reference(m, t)
    th4 = freudenstein(0.3 + 30.0 * t, a, b, c, d, sign)
    got = ref.q[:, 3 * node_b:3 * node_b + 2]
    want = np.stack([d + c * np.cos(th4), c * np.sin(th4)], axis=1)
    assert np.abs(got - want).max() <= 1e-9
    assert ref.substeps.sum() > 0


def test_fourbar_case_fast_crank_freudenstein():
    """cases/fourbar.toml with its crank ramped to 3000 rpm in 0.01 s and 2 ms steps (up to
    0.63 rad per step, 16 times): its point B follows Freudenstein's closed form (link lengths
    from the case's points, branch of its first posture) at every time, to 1e-9 m."""
    prob = Problem("fourbar", overrides={"drives.motor.law.speed_rpm": 3000.0,
                                         "drives.motor.law.ramp_s": 0.01,
                                         "time.t_end": 0.03, "time.h": 2e-3})
    pts = {k: np.array(v, float) for k, v in prob.description.points.items()}
    a = float(np.linalg.norm(pts["A"] - pts["O"]))
    b = float(np.linalg.norm(pts["B"] - pts["A"]))
    c = float(np.linalg.norm(pts["B"] - pts["C"]))
    d = float(pts["C"][0])
    assert pts["O"].tolist() == [0.0, 0.0] and pts["C"][1] == 0.0
    mech = prob.mechanism
    ref = mech.reference
    th2 = math.atan2(pts["A"][1], pts["A"][0]) + ramp_angle(ref.t, 100 * math.pi, 0.01)
    th40 = math.atan2(pts["B"][1], pts["B"][0] - d)
    sign = min((1, -1), key=lambda s: abs(math.remainder(
        float(freudenstein(th2[:1], a, b, c, d, s)[0]) - th40, 2 * math.pi)))
    th4 = freudenstein(th2, a, b, c, d, sign)
    node_b = mech.node[("coupler", "B")]
    got = np.stack([ref.coordinates(3 * node_b), ref.coordinates(3 * node_b + 1)], axis=1)
    want = np.stack([d + c * np.cos(th4), c * np.sin(th4)], axis=1)
    assert ref.t.size == 16
    assert np.abs(got - want).max() <= 1e-9


# --------------------------------------------------------------------------- singularity
@pytest.mark.parametrize("sign,w", [(1, 1.0), (1, -1.0), (-1, 1.0)])
def test_follower_driven_past_toggle_is_singular(sign, w):
    """A crank-rocker (1, 3, 2.2, 3 m) driven at its follower at +-1 rad/s, 101 times up to
    twice the time t* at which the follower reaches an extreme angle theta4* (crank and
    coupler collinear: |OB|^2 = d^2 + c^2 + 2 d c cos(theta4*) = (b +- a)^2): the analysis
    raises ModelError naming a singular posture, the Jacobian's rank deficiency and the time
    t* to 1e-5 s, not a Newton iteration count."""
    a, b, c, d = 1.0, 3.0, 2.2, 3.0
    m, _, th40 = fourbar_model(a, b, c, d, 0.0, sign, drive_follower=w)
    ext = [math.acos(((b + k * a) ** 2 - d * d - c * c) / (2 * d * c)) for k in (1, -1)]
    period = 2 * math.pi / abs(w)
    tstar = min(((e - th40) / w) % period for e in ext + [-x for x in ext])
    with pytest.raises(ModelError, match="singular posture") as err:
        rigid_reference(m, np.linspace(0.0, 2 * tstar, 101))
    msg = str(err.value)
    assert "rank-deficient" in msg and "iteration" not in msg
    when = float(re.search(r"t = ([0-9.e+-]+) s", msg).group(1))
    assert abs(when - tstar) <= 1e-5


def test_jumping_drive_is_not_singular():
    """A slider-crank (crank 0.1 m, rod 0.3 m: no singular posture, l > r) whose crank law
    jumps by 1 rad at t = 0.0503 s: the analysis raises ModelError saying the mechanism
    cannot follow its drives past that time (to 1e-6 s) although the Jacobian has full rank,
    not a singular posture."""
    r, rod = 0.1, 0.3
    m, _, _ = slider_crank(r, rod, TimeLaw(lambda t: np.where(t < 0.0503, t, t + 1.0),
                                           lambda t: 1.0 + 0 * t, lambda t: 0 * t))
    with pytest.raises(ModelError, match="cannot follow its drives") as err:
        rigid_reference(m, np.linspace(0.0, 0.1, 101))
    msg = str(err.value)
    assert "full rank" in msg and "singular posture" not in msg
    assert abs(float(re.search(r"past t = ([0-9.e+-]+) s", msg).group(1)) - 0.0503) <= 1e-6
