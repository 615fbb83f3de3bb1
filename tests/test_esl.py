"""Equivalent static loads through corotational frames (paper 3.3, eqs. 16-19) and the
static response of problem (23)."""
import copy

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.checks import taylor_test
from flexmbs.analysis.simulate import system_matrices
from flexmbs.errors import ModelError
from flexmbs.methods.esl import (BodyStiffness, ChordFrame, TangentFrame, equivalent_static_loads,
                         esl_change, local_displacements, solve_static,
                         static_response)
from flexmbs.methods.weakly import StaticModel
from flexmbs.problem import Problem
from flexmbs.analysis.settings import SimulationSettings

TABLE1_WEAKLY = [39.29, 28.33, 34.94, 25.19]   # paper Table 1, weakly coupled optimum (mm)
#: the paper's ESL frames of the robot (section 6.3): arm 1 at O, arm 2 at A
ROBOT_FRAMES = (("arm1", "O"), ("arm2", "A"))


@pytest.fixture(scope="module")
def robot():
    """The robot (cases/robot_2dof.toml) simulated at the paper's Table 1 optimum, its
    responses (deviations 28 and 30) and its ESL in tangent frames at O and A."""
    prob = Problem("robot_2dof")
    res = prob.simulate(TABLE1_WEAKLY, store="all")
    values = prob.evaluate(TABLE1_WEAKLY, gradient=False).values
    model = prob.mechanism.set_design(TABLE1_WEAKLY)
    esl = [(name, prob.mechanism.node[(name, pt)]) for name, pt in ROBOT_FRAMES]
    frames = [(name, TangentFrame(node)) for name, node in esl]
    loads = equivalent_static_loads(model, res, frames)
    return prob, res, values, model, loads, esl


def _isolated_stiffness(model, body):
    """K of the body rebuilt on its own, straight along +x from the origin (its body frame)."""
    b = model.body(body)
    q = model.reference_coordinates().reshape(-1, 3)
    length = np.hypot(*(q[b.last, :2] - q[b.first, :2]))
    iso = fx.Model()
    order = len(model._elements[b.elements[0]][0]) - 1
    beam = iso.add_beam("beam", (0.0, 0.0), (length, 0.0), len(b.elements), material=b.material,
                        section=model.element_sections(b)[0], order=order)
    iso.set_element_sections(beam, model.element_sections(b))
    _, S = system_matrices(iso, iso.reference_coordinates())
    return S[:iso.ndof, :iso.ndof]


@pytest.mark.parametrize("frame", ["tangent", "chord"])
def test_esl_applied_to_isolated_body_reproduces_local_displacements(robot, frame):
    """Definition 1 / eq. (19): the ESL applied statically to the isolated body, held as its
    frame prescribes (clamped root for the tangent frame, root and tip transverse for the chord
    frame), gives back u_n^b at every time step. The body is rebuilt independently in its own
    frame, so this checks the extraction of K_t^b from the global matrix and its rotation to
    the body frame; the only error is round-off (cond(K) ~ 1e8, hence rtol 1e-7)."""
    _, res, _, model, _, esl = robot
    for name, node in esl:
        b = model.body(name)
        fr = TangentFrame(node) if frame == "tangent" else ChordFrame(b.first, b.last)
        loads = equivalent_static_loads(model, res, [(name, fr)])[name]
        K = _isolated_stiffness(model, name)
        free = loads.stiffness.free
        u = np.linalg.solve(K[np.ix_(free, free)], loads.g_eq.T).T
        scale = np.abs(loads.u_free).max()
        assert scale > 1e-5                                  # a real deformation
        np.testing.assert_allclose(u, loads.u_free, rtol=0, atol=1e-7 * scale)
        fixed = loads.stiffness.fixed
        np.testing.assert_allclose(loads.u[:, fixed], 0.0, atol=1e-14)


def test_component_forms_equal_inertial_deviations(robot):
    """With the absolute motors of the calibrated robot (docs/paper-cases.md) the frames' angles are the
    rigid ones, so eq. (29) from the local displacements equals deviation (28) of the full
    simulation, and eq. (31) equals (30), to round-off (paper 6.2-6.3)."""
    _, _, values, model, loads, _ = robot
    a1, a2 = model.body("arm1"), model.body("arm2")
    dA = loads["arm1"].node_displacement(a1.last)
    dT = loads["arm2"].node_displacement(a2.last)
    np.testing.assert_allclose(np.hypot(dA[:, 1], dT[:, 1]), values["deviation_28"],
                               rtol=0, atol=1e-12)
    w = dA + dT
    np.testing.assert_allclose(np.hypot(w[:, 0], w[:, 1]), values["deviation_30"],
                               rtol=0, atol=1e-12)


def _stiff_arm(scale):
    """A single tube arm (4 quadratic elements) swung by a smooth motor at its root under
    gravity, with a 0.5 kg tip mass; Young's modulus 72 GPa times `scale`."""
    mat = fx.Material(E=72e9 * scale, nu=0.3, rho=2700)
    m = fx.Model()
    end = (0.8 * np.cos(0.3), 0.8 * np.sin(0.3))
    b = m.add_beam("arm", (0, 0), end, 4, material=mat, section=fx.Tube.with_wall_ratio(0.03, 0.1))
    m.pin(b.first)
    w = np.pi / 0.5
    m.drive_rotation(b.first, fx.TimeLaw(lambda t: 0.3 + 0.5 * (1 - np.cos(w * t)),
                                         lambda t: 0.5 * w * np.sin(w * t),
                                         lambda t: 0.5 * w * w * np.cos(w * t)))
    m.add_point_mass(b.last, 0.5)
    m.set_gravity(0, -9.81)
    return m, b


def _esl_vs_dynamic_loads(scale):
    m, b = _stiff_arm(scale)
    r = fx.simulate(m, 0.5, 1e-3, settings=SimulationSettings(start="static", tol=1e-12))
    loads = equivalent_static_loads(m, r, [("arm", TangentFrame(b.first))])["arm"]
    inertia_only = m.element_properties().copy()
    inertia_only[:3] = 0.0                     # f_int = 0: r = M qdd - f_ext
    err = ref = 0.0
    for n in range(0, r.t.size, 10):
        res, _ = system_matrices(m, r.q[n], r.qdd[n], t=max(r.t[n], 1e-3), cm=1.0,
                                 props=inertia_only)
        g = -res[:m.ndof][b.dofs]             # g - M qdd (inertial components)
        c, s = np.cos(loads.angle[n]), np.sin(loads.angle[n])
        T = np.kron(np.eye(len(b.nodes)), np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]))
        g_local = (T.T @ g)[loads.stiffness.free]
        err = max(err, np.abs(g_local - loads.g_eq[n]).max())
        ref = max(ref, np.abs(g_local).max())
    return err / ref, np.abs(loads.u).max()


def test_esl_approaches_dynamic_loads_for_small_deformations():
    """Eq. (10): for a linear structure g_eq = g - M qdd. For the nonlinear beam the ESL
    K_t^b u_n (eq. 19) differ from g - M qdd (in the body frame, on the free coordinates, where
    the motor's reactions do not act) by the terms K_t drops: the axial shortening from
    bending (~ v^2/L) times EA and the rotation of the internal forces, both first order in
    the deformation. So the relative difference must fall in proportion to the deformation:
    about 10x per 10x stiffer arm, and below 1 % when the tip deflection is ~4 um."""
    rel_100, u_100 = _esl_vs_dynamic_loads(100.0)
    rel_1000, u_1000 = _esl_vs_dynamic_loads(1000.0)
    assert rel_1000 < 1e-2
    assert 5.0 < rel_100 / rel_1000 < 20.0
    assert 5.0 < u_100 / u_1000 < 20.0


def test_local_displacements_of_rigid_motion_vanish():
    """Eqs. (16)-(17): a rigid rotation and translation of the undeformed body gives u = 0 in
    the tangent and in the chord frame, whatever the angle (also beyond pi)."""
    m, b = _stiff_arm(1.0)
    q0 = m.reference_coordinates()[b.dofs].reshape(-1, 3)
    qs = []
    for ang in (0.0, 1.0, 3.5, -2.5, 7.0):
        c, s = np.cos(ang), np.sin(ang)
        xy = q0[:, :2] @ np.array([[c, s], [-s, c]]) + np.array([0.3, -0.2])
        qs.append(np.column_stack([xy, q0[:, 2] + ang]).ravel())
    qs = np.array(qs)
    for fr in (TangentFrame(b.first), TangentFrame(b.last), ChordFrame(b.first, b.last)):
        u, _, angle, aref = local_displacements(qs, q0.ravel(), b.nodes, fr)
        np.testing.assert_allclose(u, 0.0, atol=1e-13)
        np.testing.assert_allclose(angle - aref, [0.0, 1.0, 3.5, -2.5, 7.0], atol=1e-13)


def test_esl_change_is_relative_load_change(robot):
    """Eq. (25): loads scaled by (1 + s) change by exactly |s| relative to the old ones."""
    loads = robot[4]
    scaled = copy.deepcopy(loads)
    for b in scaled:
        b.g_eq = 1.03 * b.g_eq
    ch = esl_change(scaled, loads)
    assert ch == pytest.approx({"arm1": 0.03, "arm2": 0.03}, rel=1e-12)
    assert esl_change(loads, loads) == {"arm1": 0.0, "arm2": 0.0}


def _perturbed(J, i):
    """J with a 1e-3 relative error in component i (1e-3 of the gradient's norm)."""
    Jw = J.copy()
    Jw[..., i] += 1e-3 * np.linalg.norm(J, axis=-1)
    return Jw


def test_static_displacement_gradient_passes_the_taylor_test(robot):
    """du/dp = -K^-1 (dK/dp) u of the static problem (23), Taylor test (flexmbs.analysis.checks) along
    p1, p2 and a random direction: the remainder |u(p + s d) - u(p) - s du.d| is second order
    (> 1.8) for steps 2^-9 .. 2^-14 mm, and order < 1.3 with a 1e-3 error in one component.
    Measured: order 2.00; remainders 1e-10 .. 5e-14 m, 50x above the rounding floor
    (1e3 eps max|u| = 1.2e-15 m; the remainder levels off at 3e-16 m, cond(K) ~ 1e8); the
    1e-3 error dominates the remainder below s ~ 2e-3 mm."""
    loads = robot[4]
    mech = Problem("robot_2dof").mechanism        # its own model: the fixture's keeps its design
    p = np.array([41.0, 30.0, 36.0, 27.0])
    body = loads["arm1"]
    props = mech.set_design(p).element_properties().copy()
    sol = solve_static(body.stiffness, body.g_eq, props, mech.element_property_derivatives(p))
    J = np.transpose(sol.du, (1, 2, 0))                        # (nt, nf, nv)

    def u_of(q):
        u = solve_static(body.stiffness, body.g_eq, mech.set_design(q).element_properties()).u
        return {"u": u, "u perturbed": u}

    rng = np.random.default_rng(5)
    for d in (np.eye(4)[0], np.eye(4)[1], rng.normal(size=4)):   # arm 1 depends on p1, p2
        d = d / np.linalg.norm(d)
        jac = {"u": J, "u perturbed": _perturbed(J, int(np.argmax(np.abs(d))))}
        chk = taylor_test(u_of, p, jac, d, step=2.0 ** -9, halvings=5,
                          value={"u": sol.u, "u perturbed": sol.u})
        assert chk["u"].ok, chk["u"].table()
        assert not chk["u perturbed"].ok and chk["u perturbed"].order < 1.3, \
            chk["u perturbed"].table()
    assert np.all(sol.du[2:] == 0.0)            # arm 1 does not depend on p3, p4
    # the adjoint form used by the optimizer gives the same selected coordinates
    cols = [body.stiffness.nfree - 3, body.stiffness.nfree - 2]
    u, du = static_response(body.stiffness, body.g_eq, props, cols,
                            mech.element_property_derivatives(p))
    np.testing.assert_allclose(u, sol.u[:, cols], rtol=0, atol=1e-9 * np.abs(sol.u).max())
    np.testing.assert_allclose(du, sol.du[:, :, cols], rtol=0, atol=1e-9 * np.abs(sol.du).max())


@pytest.mark.parametrize("name,response,t_end,step", [
    ("robot_2dof", "deviation_28", 0.65, 2.0 ** -6),
    ("robot_2dof_tracking", "deviation_30", 0.65, 2.0 ** -6),
    ("fourbar", "deviation_A", 0.1, 2.0 ** -4)])
def test_static_deviation_gradients_pass_the_taylor_test(name, response, t_end, step):
    """Gradients of the static component deviations (29), (31), (34)-(35) of problem (23)
    (flexmbs.methods.weakly.StaticModel, ESL of one simulation at 0.85 x the start), Taylor
    test along each design variable and a random direction: the remainder (max over chain
    variants and time steps) is second order (> 1.8) over 5 halvings from `step` mm, and
    order < 1.3 with a 1e-3 error in one component. At the design of the loads the static
    model returns the simulated deviation (eq. 19): (29) = (28), (31) = (30), and one of the
    four-bar's two chains, (34) through the crank (its frame angle is the motor's, its origin
    the fixed pivot O), = (33), to 1e-12 m."""
    prob = Problem(name, overrides={"time.t_end": t_end})
    p0 = prob.start * 0.85
    res = prob.simulate(p0, store="all")
    dyn = prob.evaluate(p0, gradient=False).values[response]
    static = StaticModel(prob)
    model = prob.mechanism.set_design(p0)
    static.set_loads(equivalent_static_loads(model, res, static.frames,
                                             stiffness=static.stiffness))
    p = p0 * np.linspace(0.9, 1.1, p0.size)
    values, grads = static.responses_at(p, gradient=True)
    val, grad = values[response], grads[response]                # (nvar, nt), (nvar, nt, nv)

    def fun(q):
        v = static.responses_at(q, gradient=False)[0][response]
        return {"dl": v, "dl perturbed": v}

    rng = np.random.default_rng(3)
    dirs = list(np.eye(p.size)) + [rng.normal(size=p.size)]
    for d in dirs:
        d = d / np.linalg.norm(d)
        jac = {"dl": grad, "dl perturbed": _perturbed(grad, int(np.argmax(np.abs(d))))}
        chk = taylor_test(fun, p, jac, d, step=step, halvings=5,
                          value={"dl": val, "dl perturbed": val})
        assert chk["dl"].ok, chk["dl"].table()
        assert not chk["dl perturbed"].ok and chk["dl perturbed"].order < 1.3, \
            chk["dl perturbed"].table()
    val0 = static.responses_at(p0, gradient=False)[0][response]
    assert min(np.abs(v - dyn).max() for v in val0) < 1e-12


def test_bad_input_errors(robot):
    """Clear errors for a frame node outside the body and for a rigid/unknown body."""
    model, res = robot[3], robot[1]
    with pytest.raises(ModelError, match="not a node of the body"):
        BodyStiffness(model, "arm1", TangentFrame(model.body("arm2").last))
    with pytest.raises(ModelError, match="unknown body"):
        equivalent_static_loads(model, res, [("arm3", "tangent")])
    store = fx.simulate(model, 0.01,
                        settings=SimulationSettings(start="static", store=[model.body("arm1")]))
    with pytest.raises(ModelError, match="arm2"):
        equivalent_static_loads(model, store, [("arm2", "tangent")])
