"""The weakly coupled method's corotational frames: the kind each beam gets from its joints
(frame_kind 'auto', `flexmbs.methods.weakly.frame_by_joints`), what a chord and a tangent
frame measure on a simply supported beam (Euler-Bernoulli / Timoshenko closed forms), and the
static-to-simulated ratio of the deviation constraints."""
import math

import numpy as np
import pytest

import flexmbs as fx
import flexmbs  # noqa: F401  (the core is built before the tests)
from flexmbs.errors import CaseError, ModelError
from flexmbs.methods.esl import BodyStiffness, ChordFrame, TangentFrame, local_displacements, solve_static
from flexmbs.methods.weakly import StaticModel, frame_by_joints, optimize_weakly
from flexmbs.problem import Problem

T, C = "tangent", "chord"


@pytest.mark.parametrize("case, kinds", [
    # crank driven at O; coupler hinged at A and B (entered at B); follower pinned at C, hinged at B
    ("fourbar", {"crank": T, "coupler": C, "follower": C}),
    ("fourbar_no_masses", {"crank": T, "coupler": C, "follower": C}),
    ("fourbar_tubes", {"crank": T, "coupler": C, "follower": C}),
    # both arms driven (arm 1 at O, arm 2 at A)
    ("robot_2dof", {"arm1": T, "arm2": T}),
    ("robot_2dof_tracking", {"arm1": T, "arm2": T}),
    ("robot_2dof_tapered", {"arm1": T, "arm2": T}),
    ("robot_2dof_tapered_tubes", {"arm1": T, "arm2": T}),
    # arm 1 driven at O, arms 2 and 3 driven relative to the previous arm at A and B
    ("three_arm_robot", {"arm1": T, "arm2": T, "arm3": T}),
    # the rod hinged to the rigid crank at A and to the ram at B
    ("slider_crank_press", {"rod": C}),
    ("slider_crank_press_tapered", {"rod": C}),
])
def test_auto_frames_of_the_shipped_cases(case, kinds):
    """frame_kind='auto' (the default) on each shipped case gives the kinds read off the case's
    joints by hand: tangent where the beam's entry rotation is driven, chord for a beam with a
    pin or hinge at both ends (cases/*.toml, [[joints]] and [[drives]])."""
    st = StaticModel(Problem(case))
    assert st.kinds == kinds
    assert {n: type(f) for n, f in st.frames} == {
        n: (TangentFrame if k == T else ChordFrame) for n, k in kinds.items()}


def _description(joints, drives=()):
    """A two-beam description: beam 'a' from P to Q, beam 'b' from Q to R."""
    raw = {
        "case": {"name": "frames"},
        "points": {"P": [0.0, 0.0], "Q": [1.0, 0.0], "R": [2.0, 0.0]},
        "materials": {"steel": {"E": 210e9, "nu": 0.3, "rho": 7850.0}},
        "bodies": [
            {"name": "a", "type": "beam", "from": "P", "to": "Q", "material": "steel",
             "section": {"shape": "circle", "diameter": 0.02}},
            {"name": "b", "type": "beam", "from": "Q", "to": "R", "material": "steel",
             "section": {"shape": "circle", "diameter": 0.02}}],
        "joints": list(joints), "drives": list(drives),
        "responses": [{"name": "m", "type": "mass"}],
        "objective": {"response": "m"},
        "time": {"t_end": 0.01, "h": 1e-3},
    }
    return Problem(raw).description


def test_frame_by_joints_rule():
    """The rule on hand-made joints: a clamp, a weld, a slider, a rotation drive of the beam
    or a drive of another body relative to it hold the rotation (tangent); a pin or hinge at
    the frame point with the other end joined gives a chord; a free other end keeps the
    tangent frame (a chord through a free end would hide its transverse displacement)."""
    pin_P = {"type": "pin", "body": "a", "at": "P"}
    hinge_Q = {"type": "hinge", "bodies": ["a", "b"], "at": "Q"}
    pin_R = {"type": "pin", "body": "b", "at": "R"}
    d = _description([pin_P, hinge_Q, pin_R])
    assert [frame_by_joints(d, "a", "P"), frame_by_joints(d, "b", "Q"),
            frame_by_joints(d, "b", "R")] == [C, C, C]
    d = _description([pin_P, hinge_Q])                       # b's end R is free
    assert frame_by_joints(d, "a", "P") == C and frame_by_joints(d, "b", "Q") == T
    d = _description([{"type": "clamp", "body": "a", "at": "P"}, hinge_Q, pin_R])
    assert frame_by_joints(d, "a", "P") == T and frame_by_joints(d, "b", "Q") == C
    d = _description([pin_P, {"type": "weld", "bodies": ["a", "b"], "at": "Q"}, pin_R])
    assert frame_by_joints(d, "b", "Q") == T and frame_by_joints(d, "a", "Q") == T
    d = _description([pin_P, hinge_Q, pin_R],
                     [{"type": "rotation", "body": "a", "at": "P",
                       "law": {"type": "constant", "value": 0.0}},
                      {"type": "rotation", "body": "b", "at": "Q", "relative_to": "a",
                       "law": {"type": "constant", "value": 0.0}}])
    assert [frame_by_joints(d, "a", "P"), frame_by_joints(d, "b", "Q"),
            frame_by_joints(d, "a", "Q")] == [T, T, T]
    with pytest.raises(CaseError, match="beam 'a' has no end point 'R'"):
        frame_by_joints(d, "a", "R")
    with pytest.raises(CaseError, match="'ground' is not a beam"):
        frame_by_joints(d, "ground", "P")


def test_bad_frame_kind_names_the_kinds():
    """An unknown kind, for all beams or one, is a ModelError listing auto, tangent, chord."""
    pb = Problem("fourbar")
    with pytest.raises(ModelError, match="frame_kind must be 'auto', 'tangent', 'chord', "
                                         "got 'arc'"):
        StaticModel(pb, frame_kind="arc")
    with pytest.raises(ModelError, match="frame_kind of beam 'follower' must be 'auto', "
                                         "'tangent', 'chord', got 'arc'"):
        StaticModel(pb, frame_kind={"follower": "arc"})


# ---------------------------------------------------------------------------- simply supported
L, E, D, NU = 1.2, 210e9, 0.03, 0.3
ALPHA = math.radians(30.0)          # the beam's direction (its reference frame is rotated)


def _beam(elements):
    model = fx.Model()
    mat = fx.Material(E=E, nu=NU, rho=7850.0)
    sec = fx.Circle(D)
    body = model.add_beam("beam", (0.2, -0.1), (0.2 + L * math.cos(ALPHA),
                                                -0.1 + L * math.sin(ALPHA)),
                          elements, material=mat, section=sec)
    ea, kga, ei, _, _ = sec.properties(mat)
    return model, body, kga, ei


def test_chord_frame_measures_the_simply_supported_deflection():
    """A beam between two free hinges, deflected under a uniform load w as Euler-Bernoulli's
    closed form v(s) = w s (L^3 - 2 L s^2 + s^3) / (24 EI), slope v'(s), and moved rigidly
    (turned by 0.4 rad, shifted): in the chord frame its mid-span displacement is the
    deflection 5 w L^4 / (384 EI) and its far end's transverse displacement 0; in the tangent
    frame at its end it is v(L/2) - (L/2) v'(0) = -3 w L^4 / (384 EI) (0.6 times, of the other
    sign) and the far end's -L v'(0) = -w L^4 / (24 EI) (where the deflection is 0). The nodes are placed exactly, so only the frames' small
    angle (|v'(0)| = 3.2e-3, its sine and cosine) separates the tangent frame's values from the
    closed forms: rtol 1e-4 (measured 5e-6); the chord frame's to round-off (rtol 1e-10,
    measured 8e-14)."""
    model, body, _, ei = _beam(4)
    w = -1e-3 * L * 384 * ei / (5 * L ** 4)      # mid-span deflection 1e-3 L: small angles
    s = np.linspace(0.0, L, len(body.nodes))
    v = w * s * (L ** 3 - 2 * L * s ** 2 + s ** 3) / (24 * ei)
    dv = w * (L ** 3 - 6 * L * s ** 2 + 4 * s ** 3) / (24 * ei)
    qref = model.reference_coordinates()[body.dofs]
    turn, shift = 0.4, np.array([0.3, -0.7])
    a = ALPHA + turn
    ca, sa = math.cos(a), math.sin(a)
    x0 = np.array([0.2, -0.1]) + shift
    q = np.empty_like(qref)
    q[0::3] = x0[0] + ca * s - sa * v
    q[1::3] = x0[1] + sa * s + ca * v
    q[2::3] = a + np.arctan(dv)
    mid, tip = len(s) // 2, len(s) - 1
    vm = 5 * w * L ** 4 / (384 * ei)
    u, _, _, _ = local_displacements(q[None], qref, body.nodes, ChordFrame(body.first, body.last))
    assert u[0, 3 * mid + 1] == pytest.approx(vm, rel=1e-10)
    assert abs(u[0, 3 * tip + 1]) < 1e-12
    u, _, _, _ = local_displacements(q[None], qref, body.nodes, TangentFrame(body.first))
    assert u[0, 3 * mid + 1] == pytest.approx(-3 * w * L ** 4 / (384 * ei), rel=1e-4)
    assert u[0, 3 * tip + 1] == pytest.approx(-w * L ** 4 / (24 * ei), rel=1e-4)


def test_chord_frame_static_load_case_is_simply_supported():
    """The static load case of a chord frame is the simply supported beam: a transverse force P
    at mid span gives the mid-span deflection P L^3 / (48 EI) + P L / (4 kGA) (Timoshenko's
    closed form; the shear term is 0.14 % here) through `solve_static`; the tangent frame's
    load case is a cantilever clamped at the root: P (L/2)^3 / (3 EI) + P L / (2 kGA) at the
    load's point, twice the simply supported deflection. The quadratic elements are exact at
    the nodes under point loads: rtol 1e-8 (measured 5e-13 and 4e-12 with 4 elements)."""
    model, body, kga, ei = _beam(4)
    props = model.element_properties()
    P = 1.0e3
    mid = len(body.nodes) // 2
    for frame, expected in ((ChordFrame(body.first, body.last),
                             P * L ** 3 / (48 * ei) + P * L / (4 * kga)),
                            (TangentFrame(body.first),
                             P * (L / 2) ** 3 / (3 * ei) + P * L / (2 * kga))):
        ks = BodyStiffness(model, body, frame)
        col = int(np.flatnonzero(ks.free == 3 * mid + 1)[0])
        g = np.zeros((1, ks.nfree))
        g[0, col] = P
        u = solve_static(ks, g, props).u
        assert u[0, col] == pytest.approx(expected, rel=1e-8)


# ---------------------------------------------------------------------------- static / simulated
def test_static_to_simulated_is_one_for_the_robot():
    """At the design of its ESL the static form is the chain sum of the frames' displacements
    (K^-1 g_eq = u, eq. 19); with the robot's arms in tangent frames at their driven joints the
    frame angles are the motors' prescribed angles, so the sum is the simulated deviation (28)
    itself (tests/test_problem_weakly.py): the ratio is 1 to 1e-6."""
    from flexmbs.methods.esl import equivalent_static_loads
    prob = Problem("robot_2dof")
    x = prob.mechanism.design_values([40.0, 30.0, 35.0, 25.0])
    st = StaticModel(prob)
    res = prob.simulate(x, store="all")
    model = prob.mechanism.set_design(x)
    loads = equivalent_static_loads(model, res, st.frames, stiffness=st.stiffness)
    values = prob.evaluate(x, gradient=False).values
    ratios = st.static_to_simulated(x, loads, values)
    assert list(ratios) == ["deviation_28"]
    assert ratios["deviation_28"] == pytest.approx(1.0, abs=1e-6)


def test_press_result_reports_the_ratio():
    """The press (cases/slider_crank_press.toml), weakly coupled with the default frames: its rod
    gets a chord frame, and the ram error's static form is the rod's axial deflection projected
    on x, the simulated error up to cos(beta) >= cos(14.5 deg) = 0.97 of the rod's angle: the
    reported ratio lies within 0.06 of 1 (twice that bound), in the details, in the last cycle's
    history record and in the summary."""
    r = optimize_weakly("slider_crank_press")
    assert r.details["frame_kinds"] == {"rod": "chord"}
    ratio = r.details["static_to_simulated"]["ram_error"]
    assert abs(ratio - 1.0) < 0.06
    assert r.history[-1]["static_to_simulated"]["ram_error"] == ratio
    assert "static form / simulation at this design: ram_error" in r.summary()
