"""Assembly and rigid reference by position analysis (flexmbs.model.kinematics, flexmbs.model.constraints).

Every reference value is independent of the Newton iteration under test: the four-bar's closed
form (tests/fourbar_kinematics.py, loop closure solved by circle intersection), the robot's
eq. (26) of the paper and its inverse kinematics (tests/robot_kinematics.py), and the
slider-crank's textbook formula x_B = r cos(theta) + sqrt(l^2 - r^2 sin^2(theta)).
"""
import math

import numpy as np
import pytest

from flexmbs import Circle, Material, Model, ModelError, TimeLaw
from flexmbs.model.constraints import (acceleration_rhs, constraint_jacobian, constraint_rate,
                                 constraint_values, law_tables)
from flexmbs.model.kinematics import (assemble, drive_velocities, free_degrees_of_freedom,
                                rigid_groups, rigid_reference)
from flexmbs.problem import Problem
from fourbar_kinematics import fourbar_positions
from robot_kinematics import planar_2r_inverse, robot_tip_path

MAT = Material(E=7e10, nu=0.3, rho=2700)
SEC = Circle(0.02)
R_CRANK, L_ROD = 0.1, 0.3
TH0, W0, ALPHA = 0.3, 12.0, 40.0      # crank law theta0 + w0 t + alpha t^2 / 2 + 0.2 sin(5 t)


def crank_law():
    return TimeLaw(lambda t: TH0 + W0 * t + 0.5 * ALPHA * t * t + 0.2 * np.sin(5 * t),
                   lambda t: W0 + ALPHA * t + np.cos(5 * t),
                   lambda t: ALPHA - 5 * np.sin(5 * t) + 0 * t, name="crank")


def slider_crank(driven=True, elements=2):
    """Crank O-A (pinned at O, driven), rod A-B hinged at A, B held on the x axis (y_B = 0)."""
    m = Model("slider-crank")
    A = (R_CRANK * math.cos(TH0), R_CRANK * math.sin(TH0))
    B = (A[0] + math.sqrt(L_ROD ** 2 - A[1] ** 2), 0.0)
    crank = m.add_beam("crank", (0.0, 0.0), A, elements, material=MAT, section=SEC)
    rod = m.add_beam("rod", A, B, elements, material=MAT, section=SEC)
    m.pin(crank.first)
    m.hinge(crank.last, rod.first)
    m.prescribe_position(rod.last, y=0.0)
    if driven:
        m.drive_rotation(crank.first, crank_law())
    return m, crank, rod


def slider_exact(t):
    """x_B, its rate and acceleration from the closed form, and the crank angle and rate."""
    th, w, a = crank_law().evaluate(t)
    r, l = R_CRANK, L_ROD
    s, c = np.sin(th), np.cos(th)
    S = np.sqrt(l * l - r * r * s * s)
    x = r * c + S
    dx = -r * s - r * r * s * c / S
    ddx = -r * c - r * r * (c * c - s * s) / S - r ** 4 * s * s * c * c / S ** 3
    return x, dx * w, ddx * w * w + dx * a, th, w


# --------------------------------------------------------------------------- four-bar
class FourBar:
    """The paper's four-bar (cases/fourbar.toml): its model, time grid, nodes of A and B,
    and the closed form's parameters (link lengths from the case's points, upper branch)."""

    def __init__(self):
        prob = Problem("fourbar")
        mech = prob.mechanism
        pts = {k: np.array(v) for k, v in prob.description.points.items()}
        self.model, self.t, self.beams = mech.model, mech.t, mech.beams
        self.points = {"A": mech.node[("crank", "A")], "B": mech.node[("coupler", "B")]}
        self.lengths = (np.linalg.norm(pts["A"] - pts["O"]), np.linalg.norm(pts["B"] - pts["A"]),
                        np.linalg.norm(pts["B"] - pts["C"]))
        self.ground = float(pts["C"][0])
        assert pts["O"].tolist() == [0.0, 0.0] and pts["C"][1] == 0.0
        self.branch = "upper"

    def closed_form(self, th, rate=None, accel=None):
        return fourbar_positions(th, self.lengths, self.ground, self.branch, rate, accel)


@pytest.fixture(scope="module")
def fourbar():
    case = FourBar()
    return case, case.model, rigid_reference(case.model, case.t)


def test_fourbar_matches_closed_form(fourbar):
    """Rigid reference of the paper's four-bar (docs/paper-cases.md section 7, 1001 steps): positions,
    velocities and accelerations of A and B equal the closed-form loop closure
    (tests/fourbar_kinematics.py) to 1e-10 relative to their largest magnitude."""
    case, model, ref = fourbar
    l1, l2, l3 = case.lengths
    law = model.laws()[0]
    th, w, al = law.evaluate(case.t)
    k = case.closed_form(th, w, al)
    A, B = case.points["A"], case.points["B"]

    def e(p):
        return np.stack([np.cos(p), np.sin(p)], -1)

    def ep(p):
        return np.stack([-np.sin(p), np.cos(p)], -1)

    p3, w3, a3 = k["phi_follower"], k["phi_follower_rate"], k["phi_follower_accel"]
    exact = {
        ("A", 0): k["A"], ("B", 0): k["B"],
        ("A", 1): l1 * w[:, None] * ep(th),
        ("B", 1): l3 * w3[:, None] * ep(p3),
        ("A", 2): l1 * (al[:, None] * ep(th) - (w * w)[:, None] * e(th)),
        ("B", 2): l3 * (a3[:, None] * ep(p3) - (w3 * w3)[:, None] * e(p3)),
    }
    for (pt, order), want in exact.items():
        node = A if pt == "A" else B
        got = (ref.q, ref.qd, ref.qdd)[order][:, 3 * node:3 * node + 2]
        scale = np.abs(want).max()
        assert np.abs(got - want).max() <= 1e-10 * scale, (pt, order)
    # the coupler's rotation is the closed form's coupler angle (node rotation, unwrapped)
    coupler = model.body("coupler")
    d = ref.q[:, 3 * coupler.first + 2] - k["phi_coupler"]
    assert np.abs((d + np.pi) % (2 * np.pi) - np.pi).max() <= 1e-10
    assert np.abs(ref.qd[:, 3 * coupler.first + 2] - k["phi_coupler_rate"]).max() <= 1e-10 * np.abs(
        k["phi_coupler_rate"]).max()


def test_fourbar_constraints_hold_on_every_level(fourbar):
    """Phi = 0, Phi_q qd + Phi_t = 0 and Phi_q qdd = gamma at every step (1e-12 absolute on
    positions, relative on the rate levels): the analysis satisfies what it solves."""
    case, model, ref = fourbar
    cm = model.compile()
    val, rate, acc = law_tables(model, case.t)
    assert np.abs(constraint_values(cm, ref.q, val)).max() <= 1e-12
    for k in (0, 300, 600, 1000):
        jac = constraint_jacobian(cm, ref.q[k])
        v = jac @ ref.qd[k] + constraint_rate(cm, rate[:, k])
        a = jac @ ref.qdd[k] - acceleration_rhs(cm, ref.q[k], ref.qd[k], acc[:, k])
        assert np.abs(v).max() <= 1e-12 * max(1.0, np.abs(ref.qd[k]).max())
        assert np.abs(a).max() <= 1e-12 * max(1.0, np.abs(ref.qdd[k]).max())


def test_groups_are_bodies(fourbar):
    """Each beam is one rigid group (the four-bar: crank, coupler, follower, 13 nodes each)."""
    case, model, _ = fourbar
    groups = rigid_groups(model)
    assert sorted(map(tuple, groups)) == sorted(tuple(model.body(b).nodes) for b in case.beams)


# --------------------------------------------------------------------------- robot
def test_robot_tip_follows_eq26():
    """Robot (docs/paper-cases.md section 6, cases/robot_2dof.toml, 1301 steps): the rigid reference that
    flexmbs computes by position analysis from the case's [[paths]] (Mechanism.reference):
    tip path, velocity and acceleration equal eq. (26) within 1e-10 (relative to the largest
    value), arm 2's angle equals planar_2r_inverse (tests/robot_kinematics.py), and at
    t = 0.5 s the tip is at the published (0.71962, 0.71962) m. The rigid reference of the
    flexible model driven by the motor laws it gives (law "reference") follows the same
    path."""
    mech = Problem("robot_2dof").mechanism
    model = mech.model
    t = mech.t
    # docs/paper-cases.md: arms of 0.6 m at 120 deg and -30 deg (absolute) at t = 0; T = 0.5 s, D = 0.5 m
    l1 = l2 = 0.6
    t10, t20 = math.radians(120.0), math.radians(-150.0)
    x0 = l1 * math.cos(t10) + l2 * math.cos(t10 + t20)
    y0 = l1 * math.sin(t10) + l2 * math.sin(t10 + t20)
    path = robot_tip_path(t, x0, y0, 0.5, 0.5)
    tip = mech.node[("arm2", "tip")]
    ref = mech.reference
    for order, arr in enumerate((ref.q, ref.qd, ref.qdd)):
        for c in (0, 1):
            want = path[2 * order + c]
            assert np.abs(arr[:, 3 * tip + c] - want).max() <= 1e-10 * max(1.0, np.abs(want).max())
    ref = rigid_reference(model, t)
    for order, arr in enumerate((ref.q, ref.qd, ref.qdd)):
        for c in (0, 1):
            want = path[2 * order + c]
            assert np.abs(arr[:, 3 * tip + c] - want).max() <= 1e-10 * max(1.0, np.abs(want).max())
    th1, th2, d1, d2, dd1, dd2 = planar_2r_inverse(*path, l1, l2, -1.0)
    arm2 = model.body("arm2")
    assert np.abs(ref.q[:, 3 * arm2.first + 2] - (th1 + th2)).max() <= 1e-10
    assert np.abs(ref.qdd[:, 3 * arm2.first + 2] - (dd1 + dd2)).max() <= 1e-10 * np.abs(dd1 + dd2).max()
    k = int(np.argmin(np.abs(t - 0.5)))
    assert abs(t[k] - 0.5) < 1e-12
    assert np.allclose(ref.q[k, 3 * tip:3 * tip + 2], 0.71962, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------- slider-crank
def test_slider_crank_piston_motion():
    """Slider-crank built with the Model API: x_B(theta) = r cos(theta) + sqrt(l^2 - r^2
    sin^2(theta)) and its first and second time derivatives, to 1e-10 relative."""
    m, crank, rod = slider_crank()
    t = np.linspace(0.0, 0.6, 601)
    ref = rigid_reference(m, t)
    x, v, a = slider_exact(t)[:3]
    B = rod.last
    for got, want in ((ref.q, x), (ref.qd, v), (ref.qdd, a)):
        assert np.abs(got[:, 3 * B] - want).max() <= 1e-10 * np.abs(want).max()
        assert np.abs(got[:, 3 * B + 1]).max() <= 1e-10 * np.abs(want).max()


def test_drive_velocities_rod_field():
    """drive_velocities on the slider-crank at an assembled state (t = 0.25 s): every node of
    the rod moves with the analytic rigid field v_A + beta' e_perp(beta) s, sin(beta) =
    -r sin(theta) / l, beta' = -r cos(theta) theta' / (l cos(beta)), to 1e-10 relative."""
    m, crank, rod = slider_crank(elements=3)
    t = 0.25
    _, _, _, th, w = slider_exact(np.array([t]))
    th, w = float(th[0]), float(w[0])
    asm = assemble(m, t)
    qd = drive_velocities(m, asm.q, t)
    beta = math.asin(-R_CRANK * math.sin(th) / L_ROD)
    bd = -R_CRANK * math.cos(th) * w / (L_ROD * math.cos(beta))
    vA = R_CRANK * w * np.array([-math.sin(th), math.cos(th)])
    n = len(rod.nodes)
    for i, node in enumerate(rod.nodes):
        s = L_ROD * i / (n - 1)
        want = vA + bd * s * np.array([-math.sin(beta), math.cos(beta)])
        assert np.abs(qd[3 * node:3 * node + 2] - want).max() <= 1e-10 * np.abs(vA).max()
        assert abs(qd[3 * node + 2] - bd) <= 1e-10 * abs(w)
    for node in crank.nodes:      # crank: rotation about O
        p = asm.q[3 * node:3 * node + 2]
        assert np.abs(qd[3 * node:3 * node + 2] - w * np.array([-p[1], p[0]])).max() <= 1e-10 * abs(w)


# --------------------------------------------------------------------------- assembly
def test_assemble_is_identity_on_assembled_state(fourbar):
    """Assembling the already assembled four-bar (its reference at t = 0) moves no node."""
    case, model, _ = fourbar
    asm = assemble(model, 0.0, model.reference_coordinates())
    assert asm.correction.max() <= 1e-12
    assert asm.iterations == 0


def test_assemble_from_perturbed_positions(fourbar):
    """Node positions of the four-bar perturbed by up to 3 mm: assembly at t = 0.17 s gives the
    closed-form configuration of that crank angle (the only one on the branch) to 1e-10, the
    constraints hold to 1e-12, and no node moves by more than the perturbation plus the
    motion of the crank between t = 0 and 0.17 s."""
    case, model, ref = fourbar
    rng = np.random.default_rng(3)
    q = model.reference_coordinates().copy()
    pert = rng.uniform(-3e-3, 3e-3, size=(model.nnodes, 2))
    q.reshape(-1, 3)[:, :2] += pert
    t = 0.17
    asm = assemble(model, t, q)
    val, _, _ = law_tables(model, [t])
    assert np.abs(constraint_values(model.compile(), asm.q, val[:, 0])).max() <= 1e-12
    th = model.laws()[0].evaluate(np.array([t]))[0]
    k = case.closed_form(th)
    A, B = case.points["A"], case.points["B"]
    assert np.abs(asm.q[3 * A:3 * A + 2] - k["A"][0]).max() <= 1e-10
    assert np.abs(asm.q[3 * B:3 * B + 2] - k["B"][0]).max() <= 1e-10


def test_assemble_correction_is_nearest():
    """Undriven slider-crank (one free degree of freedom): from positions perturbed by up to
    2 mm, assembly returns the nearest configuration: the correction is orthogonal (to 1e-3 of
    its size) to the mechanism's free motion there (the analytic velocity field of theta' = 1),
    and its norm does not exceed the perturbation's."""
    m, crank, rod = slider_crank(driven=False, elements=3)
    q_exact = m.reference_coordinates()
    rng = np.random.default_rng(7)
    q = q_exact.copy()
    pert = rng.uniform(-2e-3, 2e-3, size=(m.nnodes, 2))
    q.reshape(-1, 3)[:, :2] += pert
    asm = assemble(m, 0.0, q)
    val = law_tables(m, [0.0])[0][:, 0]
    assert np.abs(constraint_values(m.compile(), asm.q, val)).max() <= 1e-12
    corr = (asm.q - q).reshape(-1, 3)[:, :2]
    assert np.linalg.norm(corr) <= np.linalg.norm(pert)
    # free motion at the assembled state: crank angle from A, rod field from the closed form
    A = asm.q[3 * crank.last:3 * crank.last + 2]
    th = math.atan2(A[1], A[0])
    beta = math.asin(-R_CRANK * math.sin(th) / L_ROD)
    bd = -R_CRANK * math.cos(th) / (L_ROD * math.cos(beta))
    tang = np.zeros((m.nnodes, 2))
    for node in crank.nodes:
        p = asm.q[3 * node:3 * node + 2]
        tang[node] = (-p[1], p[0])
    for i, node in enumerate(rod.nodes):
        s = L_ROD * i / (len(rod.nodes) - 1)
        tang[node] = R_CRANK * np.array([-math.sin(th), math.cos(th)]) + \
            bd * s * np.array([-math.sin(beta), math.cos(beta)])
    cos = abs(np.sum(corr * tang)) / (np.linalg.norm(corr) * np.linalg.norm(tang))
    assert cos <= 1e-3


def test_redundant_pin_is_harmless():
    """A four-bar loop with its B hinge given twice (consistent redundant rows): the rigid
    reference still matches the closed form (A and B to 1e-10)."""
    case = FourBar()
    model = case.model
    model.hinge(model.body("coupler").last, model.body("follower").last)
    t = case.t[:201]
    ref = rigid_reference(model, t)
    th = model.laws()[0].evaluate(t)[0]
    k = case.closed_form(th)
    B = case.points["B"]
    assert np.abs(ref.q[:, 3 * B:3 * B + 2] - k["B"]).max() <= 1e-10


# --------------------------------------------------------------------------- errors
def test_undriven_mechanism_names_free_dof():
    """A slider-crank without its motor has one free degree of freedom: rigid_reference raises
    ModelError saying so; free_degrees_of_freedom counts it."""
    m, _, _ = slider_crank(driven=False)
    assert free_degrees_of_freedom(m)[0] == 1
    with pytest.raises(ModelError, match="1 free degree"):
        rigid_reference(m, np.linspace(0, 0.1, 11))


def test_inconsistent_constraints_name_rows():
    """A node pinned at x = 0 and prescribed at x = 1 cannot be assembled: ModelError naming
    both rows and the time."""
    m = Model()
    n = m.add_node(0.0, 0.0)
    m.pin(n)
    m.prescribe_position(n, x=1.0)
    with pytest.raises(ModelError, match=r"t = 0\.5 s") as err:
        assemble(m, 0.5)
    assert f"pin node {n} x" in str(err.value) and f"position node {n} x" in str(err.value)


def test_out_of_reach_names_time():
    """A slider-crank without motor whose piston is prescribed at x_B = x_B(0) + 0.1 t: the
    rod and crank align (x_B = r + l) at t = 0.0593 s; the rigid reference stops there with a
    ModelError naming a time between 0.05 and 0.07 s."""
    m, crank, rod = slider_crank(driven=False)
    x0 = R_CRANK * math.cos(TH0) + math.sqrt(L_ROD ** 2 - (R_CRANK * math.sin(TH0)) ** 2)
    m.prescribe_position(rod.last, x=TimeLaw(lambda t: x0 + 0.1 * t, lambda t: 0.1 + 0 * t,
                                             lambda t: 0 * t))
    with pytest.raises(ModelError, match=r"t = 0\.0[56]\d* s"):
        rigid_reference(m, np.linspace(0, 0.1, 101))


# --------------------------------------------------------------------------- constraint rows
def test_constraint_jacobian_and_gamma_taylor():
    """flexmbs.model.constraints on every row kind (linear, rigid link x and y of a rigid body, a
    driven row): Phi_q passes a Taylor test (remainder order 2); and gamma is the second
    derivative of Phi along a path q(s) = q0 + s v + s^2 a / 2: the Taylor test of
    s -> Phi_q(q(s)) q'(s) with derivative Phi_q a - gamma(q0, v) (Phi_t = 0 at fixed laws)."""
    from flexmbs.analysis.checks import taylor_test
    m = Model()
    beam = m.add_beam("b", (0.0, 0.0), (0.5, 0.2), 1, material=MAT, section=SEC)
    n = m.add_node(0.9, 0.4)
    body = m.add_rigid_body("r", [beam.last, n], mass=1.0, inertia=0.1)
    m.pin(beam.first)
    m.drive_rotation(beam.first, TimeLaw.constant(0.4))
    m.prescribe_position(n, y=0.5)
    cm = m.compile()
    assert set(cm.c_kind[:cm.nc]) == {1, 2, 3}
    rng = np.random.default_rng(1)
    q0 = m.reference_coordinates() + rng.normal(size=cm.ndof) * 0.1
    val = law_tables(m, [0.0])[0][:, 0]
    chk = taylor_test(lambda q: constraint_values(cm, q, val), q0, constraint_jacobian(cm, q0),
                      rng.normal(size=cm.ndof), step=1e-2)
    assert chk.ok, chk
    v, a = rng.normal(size=cm.ndof), rng.normal(size=cm.ndof)
    acc0 = np.zeros(len(m.laws()))

    def rate(s):
        s = float(s[0])
        return constraint_jacobian(cm, q0 + s * v + 0.5 * s * s * a) @ (v + s * a)

    deriv = constraint_jacobian(cm, q0) @ a - acceleration_rhs(cm, q0, v, acc0)
    chk = taylor_test(rate, np.zeros(1), deriv[:, None], np.ones(1), step=1e-2)
    assert chk.ok, chk
    assert body.nodes[0] in rigid_groups(m)[0]     # beam and rigid body share a node: one group


def test_reference_law_interpolant_is_exact_for_cubics():
    """The interpolant of a 'reference' drive's law (mechanism._CubicHermite: values and rates
    at the knots) reproduces any cubic exactly (Hermite interpolation is exact to degree 3):
    value and rate of p(t) = 1 - 2 t + 3 t^2 - 4 t^3 between uneven knots and beyond the ends
    (extrapolation by the end pieces) to 1e-12, and it equals scipy's CubicHermiteSpline on a
    non-polynomial (sin) to 1e-14 (same formula)."""
    from scipy.interpolate import CubicHermiteSpline
    from flexmbs.model.mechanism import _CubicHermite
    t = np.array([0.0, 0.1, 0.25, 0.3, 0.7, 1.0])
    p = np.polynomial.Polynomial([1.0, -2.0, 3.0, -4.0])
    law = _CubicHermite(t, p(t), p.deriv()(t))
    s = np.linspace(-0.2, 1.2, 57)
    np.testing.assert_allclose(law(s), p(s), rtol=0, atol=1e-12)
    np.testing.assert_allclose(law.rate(s), p.deriv()(s), rtol=0, atol=1e-12)
    assert np.array_equal(law(t[:-1]), p(t[:-1]))            # knots: the values given
    ref = CubicHermiteSpline(t, np.sin(3 * t), 3 * np.cos(3 * t))
    mine = _CubicHermite(t, np.sin(3 * t), 3 * np.cos(3 * t))
    np.testing.assert_allclose(mine(s), ref(s), rtol=0, atol=1e-14)
    np.testing.assert_allclose(mine.rate(s), ref.derivative()(s), rtol=0, atol=1e-14)
