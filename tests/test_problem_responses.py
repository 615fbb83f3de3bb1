"""Motor torques and joint reactions in the general description (flexmbs.problem), the
gradients of every response type, and the two examples cases/three_arm_robot.toml and
cases/fourbar_tubes.toml.

Sign convention (flexmbs.responses.forces): a torque response is the torque the motor applies
to its drive's body, counter-clockwise positive; a reaction is the force the joint exerts on
its (first) body's node, ground frame.
"""
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from flexmbs.analysis.checks import taylor_test
from flexmbs.errors import CaseError
from flexmbs.problem import Problem

GENERAL = Path(__file__).resolve().parents[1] / "cases"
G = 9.81


def _raw(name):
    return tomllib.loads((GENERAL / f"{name}.toml").read_text())


# ----------------------------------------------------------------------------- analytic values
def test_motor_torque_of_a_stiff_arm_in_the_general_format():
    """Rigid-body dynamics of a uniform arm (1 m, d = 50 mm, steel with E x 100) pinned at O,
    described as a dict, its motor law theta = theta0 + a t^3/6 (a polynomial law, alpha = a t),
    gravity -y, static start: the torque response is I_O alpha + m g (L/2) cos(theta),
    I_O = rhoA L^3/3 + rhoI L (the centrifugal forces pass through O). The arm's flexibility
    changes the torque by ~1e-5 (tests/test_responses.py, the same arm with the Model API);
    measured there after the first 50 steps: 4e-6 of the largest torque; tolerance 1e-4."""
    L, a, th0, dia, E, rho = 1.0, 4.0, 0.3, 0.05, 100 * 210e9, 7850.0
    desc = {
        "points": {"O": [0.0, 0.0], "A": [L * math.cos(th0), L * math.sin(th0)]},
        "materials": {"stiff": {"E": E, "nu": 0.3, "rho": rho}},
        "bodies": [{"name": "arm", "type": "beam", "from": "O", "to": "A", "elements": 4,
                    "material": "stiff", "section": {"shape": "circle", "diameter": dia}}],
        "joints": [{"name": "pin", "type": "pin", "body": "arm", "at": "O"}],
        "drives": [{"name": "motor", "type": "rotation", "body": "arm", "at": "O",
                    "law": {"type": "polynomial", "coefficients": [0.0, 0.0, 0.0, a / 6]}}],
        "gravity": [0.0, -G],
        "responses": [{"name": "torque", "type": "torque", "drive": "motor"}],
        "time": {"t_end": 1.0, "h": 1e-3, "start": "static"}}
    ev = Problem(desc).evaluate()
    rhoA = rho * math.pi * dia ** 2 / 4
    rhoI = rho * math.pi * dia ** 4 / 64
    theta, alpha = th0 + a * ev.t ** 3 / 6, a * ev.t
    expected = (rhoA * L ** 3 / 3 + rhoI * L) * alpha + rhoA * L * G * L / 2 * np.cos(theta)
    after = ev.t >= 0.05
    torque = ev.values["torque"]
    assert np.abs(torque - expected)[after].max() < 1e-4 * np.abs(expected).max()


def _hanging(mass=3.0):
    """A steel rod (1 m, d = 20 mm) hanging from a pin at O, `mass` kg at its lower end, held
    at its angle by a motor at O (so the static problem at t = 0 is determined); a 4 kg block
    on a slide at 45 deg held by a translation drive (constant 0)."""
    s = 1 / math.sqrt(2)
    return {
        "points": {"O": [0.0, 0.0], "P": [0.0, -1.0], "S": [2.0, 0.0]},
        "materials": {"steel": {"E": 210e9, "nu": 0.3, "rho": 7850.0}},
        "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "P", "elements": 2,
                    "material": "steel", "section": {"shape": "circle", "diameter": 0.02}},
                   {"name": "weight", "type": "mass", "at": "P", "on": "rod", "mass": mass},
                   {"name": "block", "type": "mass", "at": "S", "mass": 4.0}],
        "joints": [{"name": "pin", "type": "pin", "body": "rod", "at": "O"},
                   {"name": "slide", "type": "slider", "body": "block", "at": "S",
                    "axis": [s, s]}],
        "drives": [{"name": "motor", "type": "rotation", "body": "rod", "at": "O",
                    "law": {"type": "constant", "value": 0.0}},
                   {"name": "hold", "type": "translation", "body": "block", "at": "S",
                    "axis": [s, s], "law": {"type": "constant", "value": 0.0}}],
        "gravity": [0.0, -G],
        "responses": [{"name": f"pin_{c}", "type": "reaction", "joint": "pin", "component": c}
                      for c in ("x", "y", "magnitude")]
        + [{"name": f"slide_{c}", "type": "reaction", "joint": "slide", "component": c}
           for c in ("x", "y", "magnitude")]
        + [{"name": "hold", "type": "torque", "drive": "hold"},
           {"name": "motor", "type": "torque", "drive": "motor"}],
        "time": {"t_end": 0.01, "h": 1e-3, "start": "static"}}


def test_reactions_of_a_pin_and_a_slide_at_rest():
    """Statics (static start, so at rest from t = 0): the pin holding a rod of weight w with
    3 kg at its end pushes up with (0, 3 g + w) and the motor holding the rod needs no torque
    (the weights act along the rod); the 45 deg slide holding a 4 kg block pushes
    along its normal with m g cos 45 (components (-m g/2, m g/2)) and the drive along the
    slide with m g sin 45 (its force response), the two summing to (0, m g). Tolerance 1e-8
    relative (the Newton tolerance of the static solve; measured 6e-10)."""
    ev = Problem(_hanging()).evaluate(gradient=False)
    v = ev.values
    w = 7850.0 * math.pi * 0.02 ** 2 / 4 * 1.0 * G
    W = 3.0 * G + w
    assert np.abs(v["pin_y"] / W - 1).max() < 1e-8
    assert np.abs(v["pin_magnitude"] / W - 1).max() < 1e-8
    assert np.abs(v["pin_x"]).max() < 1e-8 * W
    assert np.abs(v["motor"]).max() < 1e-8 * W * 1.0
    mg = 4.0 * G
    assert np.abs(v["slide_x"] / (-mg / 2) - 1).max() < 1e-8
    assert np.abs(v["slide_y"] / (mg / 2) - 1).max() < 1e-8
    assert np.abs(v["slide_magnitude"] / (mg / math.sqrt(2)) - 1).max() < 1e-8
    assert np.abs(v["hold"] / (mg / math.sqrt(2)) - 1).max() < 1e-8


# ----------------------------------------------------------------------------- Taylor tests
def _robot():
    r = _raw("three_arm_robot")
    r["time"]["t_end"] = 0.1                                         # 200 steps
    r["responses"] += [
        {"name": "elbow_rx", "type": "reaction", "joint": "elbow_hinge", "component": "x"},
        {"name": "arm1_stress", "type": "stress", "bodies": ["arm1"]}]
    return r


def _fourbar_tubes():
    r = _raw("fourbar_tubes")
    r["time"]["t_end"] = 0.05                                        # 100 steps
    r["responses"] += [{"name": "pin_C_y", "type": "reaction", "joint": "pin_C",
                        "component": "y"}]
    return r


def _press():
    r = _raw("slider_crank_press")
    r["time"]["t_end"] = 0.1                                         # 200 steps
    r["joints"][3]["name"] = "slide"
    r["responses"] += [{"name": "torque", "type": "torque", "drive": "motor"},
                       {"name": "slide_y", "type": "reaction", "joint": "slide",
                        "component": "y"}]
    return r


#: noise of each response type, 5x to 10x the measured departure from linearity at steps of
#: 1e-9 .. 1e-7 mm (the Newton tolerance): torques 3e-9 N m, reactions 6e-8 N, stresses
#: 3e-4 Pa (absolute); squared deviations 5e-11 of their maximum (relative, here x max)
NOISE = {"torque": 3e-8, "reaction": 3e-7, "stress": 3e-3, "deviation": 5e-10, "mass": 0.0}


@pytest.mark.parametrize("build,step", [(_robot, 2.0 ** -1), (_fourbar_tubes, 2.0 ** -1),
                                        (_press, 2.0 ** -5)],
                         ids=["three_arm_robot", "fourbar_tubes", "slider_crank_press"])
def test_every_response_gradient_passes_the_taylor_test(build, step):
    """d r/dx of every response at every step (deviations squared, their norm has a kink at
    zero; mass, stress, torque, reaction), at the start design along a random unit direction
    (mm): remainder of order 2 (> 1.8), 6 steps halving from 2^-1 mm (2^-5 mm for the press:
    its stress, a maximum over stations, is smooth only below 2^-4 mm, where the largest
    station changes at no step). The four-bar's wall thickness is one variable shared by three
    links. Measured: orders 2.00 +- 0.02, smallest remainders 22 (robot elbow reaction) to
    1e5 times the noise. A torque gradient with an error of 1e-3 of its norm in one component
    fails at 64 times smaller steps (order < 1.3)."""
    prob = Problem(build())
    x = prob.start
    d = np.random.default_rng(3).standard_normal(x.size)
    d /= np.linalg.norm(d)
    kinds = {name: r.type for name, r in prob._resp.items()}

    def resp(ev):
        return {k: np.atleast_1d(v ** 2 if kinds[k] == "deviation" else v)
                for k, v in ev.values.items()}

    ev = prob.evaluate(x)
    value = resp(ev)
    jac = {}
    for k, v in ev.values.items():
        g = ev.gradients[k]
        jac[k] = np.atleast_2d(2 * v[:, None] * g if kinds[k] == "deviation" else g)
    assert set(kinds.values()) >= {"deviation", "mass", "stress", "torque", "reaction"}
    noise = {k: NOISE[kinds[k]] * (value[k].max() if kinds[k] == "deviation" else 1.0)
             for k in value}
    checks = taylor_test(lambda q: resp(prob.evaluate(q, gradient=False)), x, jac, d,
                         step=step, halvings=5, value=value, noise=noise)
    for k, c in checks.items():
        assert c.ok, f"{k}:\n{c.table()}"
    # a deliberately wrong torque gradient (1e-3 of its norm added to one component) fails at
    # smaller steps, where the error's first-order term dominates the remainder
    force = next(k for k in value if kinds[k] == "torque")
    wrong = jac[force].copy()
    wrong[:, 0] += 1e-3 * np.linalg.norm(jac[force], axis=1)
    bad = taylor_test(lambda q: prob.evaluate(q, gradient=False).values[force], x, wrong, d,
                      step=step * 2.0 ** -6, halvings=5, value=value[force],
                      noise=NOISE["torque"])
    assert not bad.ok and bad.order < 1.3, bad.table()


# ----------------------------------------------------------------------------- rigid limit
@pytest.mark.parametrize("name,response", [("three_arm_robot", "tip_deviation"),
                                           ("fourbar_tubes", "deviation_A")])
def test_rigid_limit_of_the_examples(name, response):
    """The deviation from the rigid reference is of order 1 in the compliance 1/E: each decade
    of E (x 100, x 1000, x 10000) divides the largest deviation by 10, the higher orders in 1/E
    fading as E grows. Asserted: the order over the last decade within 0.01 of 1 and over the
    one before within 0.05. Half the horizon of each example (the moves' fastest part).
    Measured: robot 1.0030 and 1.0000023, four-bar 0.99999 and 0.9999987 (from E to 10 E the
    higher orders still show: 1.029 and 1.040)."""
    dev = []
    for factor in (100.0, 1000.0, 10000.0):
        raw = _raw(name)
        raw["time"]["t_end"] = raw["time"]["t_end"] / 2
        for m in raw["materials"].values():
            m["E"] *= factor
        dev.append(Problem(raw).evaluate(gradient=False).values[response].max())
    first = math.log10(dev[0] / dev[1])
    last = math.log10(dev[1] / dev[2])
    assert abs(first - 1) < 0.05 and abs(last - 1) < 0.01, (dev, first, last)


# ----------------------------------------------------------------------------- bad input
def test_torque_of_an_unknown_drive_is_a_case_error():
    """A torque response naming a drive that does not exist: CaseError naming the response,
    the drive given and the named drives; the same for a reaction of an unknown joint."""
    raw = _raw("three_arm_robot")
    raw["responses"].append({"name": "knee", "type": "torque", "drive": "knee"})
    with pytest.raises(CaseError, match=r"response 'knee': unknown drive 'knee' \(named drives: "
                                        r"elbow, shoulder, wrist\)"):
        Problem(raw)
    raw = _raw("three_arm_robot")
    raw["responses"].append({"name": "r", "type": "reaction", "joint": "hip"})
    with pytest.raises(CaseError, match=r"response 'r': unknown joint 'hip' \(named joints: "
                                        r"elbow_hinge, shoulder_pin, wrist_hinge\)"):
        Problem(raw)


def test_every_response_type_has_a_kind():
    """Every response type a case may declare (flexmbs.model.description.Response) has its
    kind in flexmbs.responses.kinds.KINDS (how a Problem evaluates it, the nodes it reads,
    its unit, its adjoint partials), registered by its schema class and overriding `value`:
    a new type without one would fail only when a case uses it."""
    import typing
    from flexmbs.model.description import Response
    from flexmbs.responses.kinds import KINDS, ResponseKind
    union = typing.get_args(Response)[0]
    assert set(typing.get_args(union)) == set(KINDS)
    for schema, kind in KINDS.items():
        assert kind.schema is schema
        assert type(kind).value is not ResponseKind.value, schema.__name__

