"""The paper's mechanisms as case files (cases/robot_2dof.toml, robot_2dof_tracking.toml,
fourbar.toml, fourbar_no_masses.toml) against published and analytic values.

Published numbers are read from tests/data/paper_tables.json, a copy of the tables of the paper
(Tromme, Bruls, Duysinx, "Weakly and fully coupled methods for structural optimization of
flexible mechanisms"); calibrated values of an independent code are quoted from
docs/paper-cases.md where used. The robot's rigid reference is checked against the closed-form
inverse kinematics of tests/robot_kinematics.py (the library computes it by position analysis).
"""
import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from flexmbs.errors import CaseError, ModelError
from flexmbs.problem import Problem
from robot_kinematics import planar_2r_inverse, robot_tip_path

DATA = json.loads((Path(__file__).parent / "data" / "paper_tables.json").read_text())
ROBOT = DATA["robot_2dof"]
FOURBAR = DATA["four_bar"]
REPO = Path(__file__).resolve().parents[1]
LIMIT_M = 1.0e-3                   # every paper case's deviation limit (paper 6.2, 7.2)


def _robot_rows():
    """(label, case, t_end override, published row) for every published robot optimum."""
    rows = []
    for method in ("weakly", "fully"):
        rows.append((f"T1-{method}", "robot_2dof", None, ROBOT["table1_formulation28_tend0.65"][method]))
        rows.append((f"T2-{method}", "robot_2dof_tracking", None,
                     ROBOT["table2_formulation30_tend0.65"][method]))
    rows.append(("T5-fully", "robot_2dof", 0.66, ROBOT["table5_formulation28_tend0.66"]["fully"]))
    for method in ("weakly", "fully"):
        for k, row in enumerate(ROBOT["table6_formulation28_tend0.65_initial_points"][method]):
            rows.append((f"T6-{method}-{k}", "robot_2dof", None, row))
        for k, row in enumerate(ROBOT["table7_formulation28_tend0.6687_initial_points"][method]):
            # 0.6687 s is not a multiple of h: the paper's step 1338 is t = 0.6685 s (docs/paper-cases.md)
            rows.append((f"T7-{method}-{k}", "robot_2dof", 0.6685, row))
    return rows


ROBOT_ROWS = _robot_rows()
T1_WEAKLY = ROBOT["table1_formulation28_tend0.65"]["weakly"]["p"]


@functools.lru_cache(maxsize=None)
def problem(name, t_end=None, **over):
    """A shipped case, t_end and other overrides (dotted keys given with '__' for '.')."""
    overrides = {k.replace("__", "."): v for k, v in over.items()}
    if t_end is not None:
        overrides["time.t_end"] = t_end
    return Problem(name, overrides=overrides or None)


def maxdev(prob, x):
    """Largest constrained deviation of design x over the simulation (m)."""
    return float(prob.constrained_deviation(prob.evaluate(x, gradient=False).values).max())


# ----------------------------------------------------------------------------- mass
@pytest.mark.parametrize("label,name,t_end,row", ROBOT_ROWS, ids=[r[0] for r in ROBOT_ROWS])
def test_beam_mass_of_published_robot_optima(label, name, t_end, row):
    """Beam mass of every published robot optimum (Tables 1, 2, 5, 6, 7) within 0.1 %, and
    docs/paper-cases.md's m = 229.02 sum(p_i^2) (p in m) within 1e-4."""
    prob = problem(name)
    assert prob.design_mass(row["p"]) == pytest.approx(row["mass"], rel=1e-3)
    assert prob.design_mass(row["p"]) == pytest.approx(
        229.02 * np.sum((np.array(row["p"]) * 1e-3) ** 2), rel=1e-4)


@pytest.mark.parametrize("method", ["weakly", "fully"])
def test_beam_mass_of_published_fourbar_optima(method):
    """Table 3 masses within 0.1 %; the start design has 268 kg of links (paper 7.2); the
    lumped masses are not part of the objective."""
    fourbar = problem("fourbar")
    row = FOURBAR["table3_with_lumped_masses"][method]
    assert fourbar.design_mass(row["p"]) == pytest.approx(row["mass"], rel=1e-3)
    assert fourbar.design_mass(FOURBAR["start_mm"]) == pytest.approx(FOURBAR["start_mass_kg"],
                                                                    rel=1e-3)
    assert problem("fourbar_no_masses").design_mass(row["p"]) == fourbar.design_mass(row["p"])


@pytest.mark.parametrize("name", ["robot_2dof", "fourbar"])
def test_property_derivatives_match_finite_differences(name):
    """d[EA, kGA, EI, rhoA, rhoI]/dp (p in mm) against central differences of the element
    properties. Step 1e-5 p: the truncation error of a central difference of EI ~ p^4 is
    (h/p)^2 = 1e-10 relative and rounding about eps p/h = 2e-11 (measured 1.1e-10), four
    decades under the 1e-6 asserted."""
    mech = Problem(name).mechanism
    p = mech.start * np.linspace(0.7, 1.1, mech.start.size)
    dprops = mech.element_property_derivatives(p)
    nel = len(mech.model._elements)
    assert dprops.shape == (5, nel, p.size)
    for i in range(p.size):
        dp = np.zeros_like(p)
        dp[i] = 1e-5 * p[i]
        props_p = mech.set_design(p + dp).element_properties().copy()
        props_m = mech.set_design(p - dp).element_properties().copy()
        np.testing.assert_allclose(dprops[:, :, i], (props_p - props_m) / (2 * dp[i]),
                                   rtol=1e-6, atol=1e-12 * np.abs(props_p).max())


def test_robot_design_variables_map_to_half_arms():
    """p1, p2: arm 1 root and tip halves; p3, p4: arm 2 (paper 6.1), also with 4 elements per
    arm: element e depends on variable [0, 0, 1, 1, 2, 2, 3, 3][e] alone."""
    mech = Problem("robot_2dof", overrides={"bodies.arm1.elements": 4,
                                            "bodies.arm2.elements": 4}).mechanism
    d = mech.element_property_derivatives(mech.start)[3]          # d(rho A)/dp, (nel, nv)
    assert d.shape == (8, 4)
    np.testing.assert_array_equal(np.argmax(np.abs(d), axis=1), [0, 0, 1, 1, 2, 2, 3, 3])
    assert np.count_nonzero(d) == 8


# ----------------------------------------------------------------------------- kinematics
def _angles(mech, n):
    """theta1 (arm 1 w.r.t. the ground) and theta2 (arm 2 w.r.t. arm 1) of the rigid reference
    at step n, from its node positions."""
    q = mech.reference.q[n]
    O, A, tip = (q[3 * mech.node[k]: 3 * mech.node[k] + 2]
                 for k in (("arm1", "O"), ("arm1", "A"), ("arm2", "tip")))
    th1 = math.atan2(*(A - O)[::-1])
    th2 = math.atan2(*(tip - A)[::-1]) - th1
    return th1, (th2 + math.pi) % (2 * math.pi) - math.pi


def test_robot_kinematics_published_checks():
    """Paper 6.1 and 8.2: tip from (0.21962, 0.21962) to (0.71962, 0.71962) m at t = 0.5 s;
    theta1 = 120 deg, theta2 = -150 deg at the start; theta1 = 60 deg, theta2 = -30 deg at the
    end of the motion of Table 7 (t ~ 0.6687 s, where the tip has moved 0.6 m along its path);
    the rigid reference (position analysis) equals the closed-form inverse kinematics of the
    2R arm along eq. (26) (tests/robot_kinematics.py) at every step to 1e-9 rad."""
    mech = problem("robot_2dof", 0.6685).mechanism
    tipn = mech.node[("arm2", "tip")]
    q = mech.reference.q
    np.testing.assert_allclose(q[0, 3 * tipn: 3 * tipn + 2], [0.21962, 0.21962], atol=5e-6)
    j = int(round(0.5 / 5e-4))
    np.testing.assert_allclose(q[j, 3 * tipn: 3 * tipn + 2], [0.71962, 0.71962], atol=5e-6)
    np.testing.assert_allclose(np.degrees(_angles(mech, 0)), [120, -150], atol=1e-9)
    th1, th2 = np.degrees(_angles(mech, int(round(0.668 / 5e-4))))          # t = 0.668 s
    assert th1 == pytest.approx(60.0, abs=0.1) and th2 == pytest.approx(-30.0, abs=0.2)
    # the posture (60, -30) deg puts the tip 0.6 m further along the path: at t in (0.6675, 0.669)
    x0 = q[0, 3 * tipn]
    t = np.linspace(0.66, 0.675, 15001)
    k = np.argmin(np.abs(robot_tip_path(t, x0, x0)[0] - (x0 + 0.6)))
    assert 0.6675 < t[k] < 0.6690
    # closed form along eq. (26) at every step of the rigid reference
    x, y, xd, yd, xdd, ydd = robot_tip_path(mech.t, x0, x0)
    th1, th2 = planar_2r_inverse(x, y, xd, yd, xdd, ydd, 0.6, 0.6)[:2]
    ref = np.array([_angles(mech, n) for n in range(mech.t.size)])
    np.testing.assert_allclose(ref[:, 0], np.unwrap(th1), atol=1e-9)
    np.testing.assert_allclose(ref[:, 1], th2, atol=1e-9)


def test_fourbar_reference_closes_the_loop():
    """The four-bar's rigid reference (position analysis): crank at theta0 = 90 deg puts A at
    (0, 0.3048) m, C at (0.9144, 0); at every step the link lengths 0.3048, 0.9144, 0.762 m
    (paper 7.1) are kept to 1e-9 m and B stays on the upper branch (y_B > 0.5 m)."""
    mech = problem("fourbar").mechanism
    q = mech.reference.q

    def pos(body, point):
        n = mech.node[(body, point)]
        return q[:, 3 * n: 3 * n + 2]

    O, A, B, C = pos("crank", "O"), pos("crank", "A"), pos("coupler", "B"), pos("follower", "C")
    np.testing.assert_allclose(A[0], [0.0, 0.3048], atol=1e-12)
    np.testing.assert_allclose(C, np.broadcast_to([0.9144, 0.0], C.shape), atol=1e-12)
    np.testing.assert_allclose(O, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.hypot(*(A - O).T), 0.3048, atol=1e-9)
    np.testing.assert_allclose(np.hypot(*(B - A).T), 0.9144, atol=1e-9)
    np.testing.assert_allclose(np.hypot(*(B - C).T), 0.762, atol=1e-9)
    np.testing.assert_allclose(pos("follower", "B"), B, atol=1e-12)
    assert np.all(B[:, 1] > 0.5)
    # the crank turns: more than a full revolution over the 0.5 s
    ang = np.unwrap(np.arctan2(A[:, 1], A[:, 0]))
    assert abs(ang[-1] - ang[0]) > 2 * np.pi


@pytest.mark.parametrize("name", ["robot_2dof", "robot_2dof_tracking", "fourbar"])
def test_rigid_limit_follows_the_reference(name):
    """With very stiff links (E = 1e20 Pa) every node follows the rigid reference mechanism and
    the deviation vanishes (< 1e-9 m): the model, its drives and the reference agree."""
    prob = problem(name, materials__aluminium__E=1e20)
    x = prob.start
    assert maxdev(prob, x) < 1e-9
    r = prob.simulate(x, store="all")
    mech = prob.mechanism
    for body in mech.beams:
        for n in mech.model.body(body).nodes:
            ref = mech.reference.q[:, 3 * n: 3 * n + 2]
            assert np.abs(r.position(n) - ref).max() < 1e-9


# ----------------------------------------------------------------------------- deviation
def test_deviation_formulas_from_node_positions():
    """The deviation responses equal eqs. (28), (30), (33) written out with the simulated
    positions of A, the tip and their rigid references (the robot's from the closed-form
    inverse kinematics of eq. 26, tests/robot_kinematics.py)."""
    prob = problem("robot_2dof")
    values = prob.evaluate(T1_WEAKLY, gradient=False).values
    r = prob.simulate(T1_WEAKLY, store="all")
    mech = prob.mechanism
    A, tip = r.position(mech.node[("arm1", "A")]), r.position(mech.node[("arm2", "tip")])
    x0 = 0.21961524227066315
    x, y, xd, yd, xdd, ydd = robot_tip_path(mech.t, x0, x0)
    th1 = planar_2r_inverse(x, y, xd, yd, xdd, ydd, 0.6, 0.6)[0]
    yA_ref = 0.6 * np.sin(th1)
    a = A[:, 1] - yA_ref
    np.testing.assert_allclose(values["deviation_28"],
                               np.sqrt(a ** 2 + ((tip[:, 1] - y) - a) ** 2), rtol=0, atol=1e-12)
    np.testing.assert_allclose(values["deviation_30"], np.hypot(tip[:, 0] - x, tip[:, 1] - y),
                               rtol=0, atol=1e-12)
    fourbar = problem("fourbar", 0.05)
    values = fourbar.evaluate(FOURBAR["start_mm"], gradient=False).values
    rf = fourbar.simulate(FOURBAR["start_mm"], store="all")
    n = fourbar.mechanism.node[("crank", "A")]
    ref = fourbar.mechanism.reference.q[:, 3 * n: 3 * n + 2]
    A = rf.position(n)
    np.testing.assert_allclose(values["deviation_A"], np.hypot(*(A - ref).T), rtol=0, atol=1e-12)


@pytest.mark.parametrize("label,name,t_end,row", ROBOT_ROWS, ids=[r[0] for r in ROBOT_ROWS])
def test_published_robot_optima_sit_on_their_constraint(label, name, t_end, row):
    """At an optimum the deviation limit is active: the maximum deviation of every published
    robot optimum is 1.000 mm within 3 % (Tables 1, 2, 5, 6 at their t_end; Table 7 at the
    paper's step 1338, 0.6685 s). Measured: all within 1 %."""
    assert maxdev(problem(name, t_end), row["p"]) == pytest.approx(LIMIT_M, rel=0.03)


def test_robot_start_design_is_well_inside():
    """The start design p = 50 mm is far from the limit (paper 6.2: the optimum is 2.4 times
    lighter); Table 7's infeasible start [45, 45, 45, 45] is infeasible at 0.6685 s."""
    assert maxdev(problem("robot_2dof"), [50] * 4) < 0.5e-3
    assert maxdev(problem("robot_2dof", 0.6685), [45] * 4) > 1.0e-3


def test_fourbar_start_design():
    """Paper 7.2: at p = 250 mm the maximum deviation of A is about 50 um (53-58 um on the
    independent code of docs/paper-cases.md), over 0.5 s (1001 time points)."""
    prob = problem("fourbar")
    assert 40e-6 < maxdev(prob, FOURBAR["start_mm"]) < 65e-6
    assert prob.mechanism.t.size == 1001


@pytest.mark.parametrize("method", ["weakly", "fully"])
def test_fourbar_table3_optima_near_their_constraint(method):
    """Both Table 3 optima sit near the 1 mm limit with theta0 = 90 deg (docs/paper-cases.md: 0.96-1.03 mm
    depending on the element). Tolerance 5 %: the fully coupled optimum's maximum is a sharp
    vibration peak that moves by 6 % when h is halved (measured; fourbar.toml)."""
    row = FOURBAR["table3_with_lumped_masses"][method]
    assert maxdev(problem("fourbar"), row["p"]) == pytest.approx(LIMIT_M, rel=0.05)


def test_calibrated_alternatives_of_cases_md():
    """docs/paper-cases.md, at the Table 1 weakly optimum on an independent code: undeformed start
    (start = "rest") 1.16 mm; 2 linear elements per arm 0.90 mm, 8 linear 0.989 mm."""
    assert maxdev(problem("robot_2dof", time__start="rest"), T1_WEAKLY) == pytest.approx(
        1.16e-3, rel=0.03)
    lin = dict(bodies__arm1__order=1, bodies__arm2__order=1)
    assert maxdev(problem("robot_2dof", **lin), T1_WEAKLY) == pytest.approx(0.90e-3, rel=0.02)
    assert maxdev(problem("robot_2dof", bodies__arm1__elements=8, bodies__arm2__elements=8,
                          **lin), T1_WEAKLY) == pytest.approx(0.989e-3, rel=0.01)


# ----------------------------------------------------------------------------- convergence
def _t1(**over):
    return maxdev(problem("robot_2dof", **over), T1_WEAKLY)


def test_convergence_in_time_step():
    """Generalized-alpha is second order: halving h divides the change of the maximum deviation
    (Table 1 optimum) by about 4; at the paper's h = 5e-4 s it is within 0.1 % of the
    Richardson-extrapolated value."""
    m = np.array([_t1(time__h=h) for h in (5e-4, 2.5e-4, 1.25e-4, 6.25e-5)])
    d = np.abs(np.diff(m))
    ratios = d[:-1] / d[1:]
    assert np.all((ratios > 3.0) & (ratios < 5.5)), ratios
    extrapolated = m[-1] + (m[-1] - m[-2]) / 3
    assert abs(m[0] / extrapolated - 1) < 1e-3


def test_numerical_damping_only_changes_the_time_error():
    """rho_inf changes the maximum deviation by < 0.05 % at h = 5e-4 s, and by far less at
    h / 4: it only acts through the O(h^2) error."""
    spread = [np.ptp([_t1(time__h=h, time__rho_inf=r) for r in (0.3, 0.5, 0.8)])
              for h in (5e-4, 1.25e-4)]
    assert spread[0] < 5e-4 * 1e-3
    assert spread[1] < spread[0] / 4


def test_convergence_in_elements_per_arm():
    """Quadratic elements: 2 per arm are converged within 0.05 % (changes shrink more than 4
    times per doubling); linear elements converge at second order to the same value."""
    def arms(n, order=2):
        return _t1(bodies__arm1__elements=n, bodies__arm2__elements=n,
                   bodies__arm1__order=order, bodies__arm2__order=order)

    quad = np.array([arms(n) for n in (2, 4, 8)])
    assert abs(quad[1] / quad[0] - 1) < 5e-4
    assert abs(quad[2] - quad[1]) < abs(quad[1] - quad[0]) / 4
    lin = np.array([arms(n, 1) for n in (4, 8, 16, 32)])
    d = np.abs(np.diff(lin))
    assert np.all((d[:-1] / d[1:] > 3.0) & (d[:-1] / d[1:] < 5.0))
    assert lin[-1] == pytest.approx(quad[-1], rel=1e-3)


# ----------------------------------------------------------------------------- case settings
def test_time_grids_of_the_paper_problems():
    """t_end = 0.65 s is Table 1's problem (1301 time points), 0.66 s Table 5's (1321),
    0.6685 s Tables 7-8's (1338, the paper's step 1338, docs/paper-cases.md); the four-bar 0.5 s (1001)."""
    assert problem("robot_2dof").mechanism.t.size == 1301
    mech = problem("robot_2dof", 0.66).mechanism
    assert mech.t.size == 1321 and mech.t[-1] == pytest.approx(0.66)
    assert problem("robot_2dof", 0.6685).mechanism.t.size == 1338
    assert problem("fourbar").mechanism.t.size == 1001


def test_unknown_overrides_and_bad_designs_are_named():
    """An override of an unknown key and a design of the wrong length are errors naming the
    key / the expected count."""
    with pytest.raises(CaseError, match="t_edn"):
        Problem("robot_2dof", overrides={"time.t_edn": 0.66})
    with pytest.raises(ModelError, match=r"design must be 4 finite numbers \(p1, p2, p3, p4\)"):
        problem("robot_2dof").evaluate([50, 50], gradient=False)


def test_shipped_cases_are_listed_for_installation():
    """Every case file of cases/ is listed in meson.build for installation with the package."""
    build = (REPO / "python" / "flexmbs" / "meson.build").read_text()
    names = sorted(f.stem for f in (REPO / "cases").glob("*.toml"))
    assert {"robot_2dof", "robot_2dof_tracking", "fourbar", "fourbar_no_masses"} <= set(names)
    for name in names:
        assert f"'../../cases/{name}.toml'" in build
