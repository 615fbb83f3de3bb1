"""The general description (cases/*.toml, flexmbs.problem.Problem) of the paper's four-bar and
robot: published and analytic values (the paper's mass formula, eq. 26's tip path), gradients
by a Taylor test, normalised constraints, and the errors of broken descriptions.
"""
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from flexmbs.analysis.checks import taylor_test
from flexmbs.errors import CaseError
from flexmbs.model.casefile import description_from_dict, read_description
from flexmbs.problem import Problem

CASES = Path(__file__).resolve().parents[1] / "cases"
T3_WEAKLY = [69.85, 87.61, 37.22]           # Table 3, weakly coupled optimum (mm)


def _raw(name):
    return tomllib.loads((CASES / f"{name}.toml").read_text())


@pytest.fixture(scope="module")
def fourbar():
    return Problem(CASES / "fourbar.toml")


@pytest.fixture(scope="module")
def robot():
    return Problem("robot_2dof")          # found by name in cases/


def test_fourbar_mass_is_the_papers_formula(fourbar):
    """The four-bar's mass at the Table 3 weakly design is rho pi/4 sum l_i p_i^2 (paper
    eq. 32, solid circular links) to rounding, and Table 3's 20.703 kg within 0.2 %; its
    gradient is the formula's, 2 rho pi/4 l_i p_i (per mm)."""
    ev = fourbar.evaluate(T3_WEAKLY, gradient=True)
    p = np.array(T3_WEAKLY) * 1e-3
    lengths = np.array([0.3048, 0.9144, 0.762])
    mass = 2757.0 * math.pi / 4 * np.dot(lengths, p ** 2)
    assert ev.values["mass"] == pytest.approx(mass, rel=1e-12)
    assert ev.values["mass"] == pytest.approx(20.703, rel=2e-3)      # Table 3: 20.703 kg
    np.testing.assert_allclose(ev.gradients["mass"], 2757.0 * math.pi / 2 * lengths * p * 1e-3,
                               rtol=1e-12)


def test_rigid_reference_of_the_robot_follows_the_tip_path(robot):
    """The rigid reference's tip follows eq. (26): x = x0 + D(t), y = y0 + D(t),
    D(t) = 0.5 (t/T - sin(2 pi t/T)/(2 pi)), T = 0.5 s; at t = 0.5 s the tip is at
    (0.71962, 0.71962) m (docs/paper-cases.md)."""
    mech = robot.mechanism
    tip = mech.node[("arm2", "tip")]
    ref = mech.reference
    T = 0.5
    D = 0.5 * (ref.t / T - np.sin(2 * np.pi * ref.t / T) / (2 * np.pi))
    x0 = y0 = 0.21961524227066315
    np.testing.assert_allclose(ref.q[:, 3 * tip], x0 + D, atol=1e-10)
    np.testing.assert_allclose(ref.q[:, 3 * tip + 1], y0 + D, atol=1e-10)
    j = int(round(0.5 / mech.h))
    assert ref.q[j, 3 * tip: 3 * tip + 2] == pytest.approx([0.71962, 0.71962], abs=1e-5)


def test_problem_gradients_pass_the_taylor_test():
    """d(deviation^2)/dx at every step and d(mass)/dx of the four-bar over 100 steps (0.05 s):
    remainder of order 2 (> 1.8) along a random direction; a 1e-3 error in one component
    gives order < 1.3. Steps 2^-9 .. 2^-14 mm, measured: order 2.000 (1.01 with the error),
    smallest remainder 23x above the noise floor (tests/test_sensitivity.py: the noise)."""
    raw = _raw("fourbar")
    raw["time"]["t_end"] = 0.05
    prob = Problem(raw)
    x = np.array(T3_WEAKLY)
    d = np.random.default_rng(3).standard_normal(3)
    d /= np.linalg.norm(d)

    def resp(ev):
        v = ev.values["deviation_A"]
        return {"dl2": v ** 2, "dl2 wrong": v ** 2, "mass": np.array([ev.values["mass"]])}

    ev = prob.evaluate(x)
    g = 2 * ev.values["deviation_A"][:, None] * ev.gradients["deviation_A"]
    wrong = g.copy()
    wrong[:, 0] += 1e-3 * np.linalg.norm(g, axis=1)
    jac = {"dl2": g, "dl2 wrong": wrong, "mass": ev.gradients["mass"][None, :]}
    noise = 2 * ev.values["deviation_A"].max() * 2e-15
    checks = taylor_test(lambda q: resp(prob.evaluate(q, gradient=False)), x, jac, d,
                         step=2.0 ** -9, halvings=5, value=resp(ev),
                         noise={"dl2": noise, "dl2 wrong": noise, "mass": 0.0})
    assert checks["dl2"].ok, checks["dl2"].table()
    assert checks["mass"].order > 1.8
    assert not checks["dl2 wrong"].ok and checks["dl2 wrong"].order < 1.3


def test_constraints_are_normalised_and_aggregated(fourbar):
    """Every-step constraints are g_n = dl_n / 1 mm - 1 (one per step); the Table 3 weakly
    design has its maximum at 0.978 mm (cases/fourbar.toml), so it is feasible with
    max g = dl_max / 1 mm - 1."""
    ev = fourbar.evaluate(T3_WEAKLY, gradient=False)
    dl = ev.values["deviation_A"]
    assert ev.constraints.shape == dl.shape
    np.testing.assert_allclose(ev.constraints, dl / 1e-3 - 1.0, rtol=0, atol=1e-14)
    assert ev.feasible and ev.max_violation == pytest.approx(dl.max() / 1e-3 - 1)
    assert ev.objective == ev.values["mass"]


# ----------------------------------------------------------------------------- errors
def _broken(name, edit):
    raw = _raw(name)
    edit(raw)
    return raw


@pytest.mark.parametrize("edit,message", [
    (lambda r: r["joints"][1].update(bodies=["crank", "couplr"]),
     r"joint 2 \(hinge\): unknown body 'couplr' \(bodies: crank, coupler, follower"),
    (lambda r: r["bodies"][0].update(elements=0),
     r"key 'bodies\[0\]\.elements' .*greater than or equal to 1, got 0"),
    (lambda r: r["bodies"][1]["section"].update(diameter="p7"),
     r"body 'coupler': section diameter = 'p7' is not a design variable"),
    (lambda r: r["bodies"][0].update(colour="red"),
     r"key 'bodies\[0\]\.colour' is not a known key"),
    (lambda r: r["drives"][0]["law"].pop("ramp_s"),
     r"law type 'ramp_to_speed' needs ramp_s"),
    (lambda r: r["design"][0].update(start=600.0),
     r"design variable 'p1': start = 600.0 must lie within \[15.0, 500.0\]"),
    (lambda r: r["constraints"][0].update(response="dev"),
     r"constraint: unknown response 'dev'"),
    (lambda r: r["points"].update(A="north"), r"key 'points\.A' .*got 'north'"),
    (lambda r: r["time"].pop("t_end"), r"key 'time\.t_end' is missing"),
])
def test_bad_descriptions_name_the_key(edit, message):
    """A broken description is a CaseError naming the key (or the body/joint) and the value."""
    with pytest.raises(CaseError, match=message):
        description_from_dict(_broken("fourbar", edit), "fourbar.toml")


def test_case_file_errors_name_the_file(tmp_path):
    """Syntax errors and unknown case names are CaseErrors naming the file or the name."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[[bodies]\nname = 1\n")
    with pytest.raises(CaseError, match=r"bad\.toml: not valid TOML"):
        read_description(bad)
    with pytest.raises(CaseError, match=r"case 'no_such_case' not found.*fourbar"):
        Problem("no_such_case")


def test_t_end_not_a_multiple_of_h_is_rounded_with_a_warning():
    """t_end = 0.0503 s with h = 5e-4: 101 steps (0.0505 s), and a warning says so."""
    raw = _raw("fourbar")
    raw["time"]["t_end"] = 0.0503
    with pytest.warns(UserWarning, match=r"not a whole number of steps.*0\.0505 s \(101 steps\)"):
        prob = Problem(raw)
    assert prob.mechanism.nsteps == 101
