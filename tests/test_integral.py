"""The 'integral' aggregate (flexmbs.responses.aggregate.integral, over = "integral" in a case's
objective and constraints): the time integral of a history by the trapezoid rule on the output
grid, its gradient by direct differentiation and by the discrete adjoint (like any
response that is a function of the whole history)."""
import math

import numpy as np
import pytest

from flexmbs.errors import CaseError, ModelError
from flexmbs.problem import Problem
from flexmbs.responses.aggregate import aggregate, trapezoid_weights

G = 9.81
REL = 1e-8


def _rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_trapezoid_of_a_parabola_is_exact():
    """The trapezoid rule on a uniform grid of step h integrates t^2 over [0, T] to
    T^3/3 + h^2 T/6 exactly (its error term h^2/12 (f'(T) - f'(0)) is exact for a parabola),
    and over a window [a, b] of grid points to (b^3 - a^3)/3 + h^2 (b - a)/6; the gradient
    of the integral with respect to the samples is the trapezoid weights, which sum to the
    span. Tolerance 1e-13 relative (rounding)."""
    h, T = 0.01, 0.6
    t = h * np.arange(61)
    r = t ** 2
    val, grad = aggregate(r, np.eye(t.size), "integral", t=t)
    assert val == pytest.approx(T ** 3 / 3 + h ** 2 * T / 6, rel=1e-13)
    assert np.allclose(grad, trapezoid_weights(t), rtol=0, atol=1e-16)
    assert grad.sum() == pytest.approx(T, rel=1e-13)
    a, b = 0.2, 0.45
    val, _ = aggregate(r, None, "integral", t=t, window=(a, b))
    assert val == pytest.approx((b ** 3 - a ** 3) / 3 + h ** 2 * (b - a) / 6, rel=1e-13)


def _hanging():
    """A steel rod (1 m, diameter d mm a design variable, start 20 mm) hanging from a pin at
    O with 3 kg at its lower end, held at its angle by a motor (tests/test_problem_responses.py
    _hanging, without the slide): from static equilibrium it stays at rest, so the pin's
    reaction is the weight W(d) = (3 + rho pi d^2/4 L) g at every step."""
    return {
        "points": {"O": [0.0, 0.0], "P": [0.0, -1.0]},
        "materials": {"steel": {"E": 210e9, "nu": 0.3, "rho": 7850.0}},
        "design": [{"name": "d", "unit": "mm", "lower": 10.0, "upper": 40.0, "start": 20.0}],
        "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "P", "elements": 2,
                    "material": "steel", "section": {"shape": "circle", "diameter": "d"}},
                   {"name": "weight", "type": "mass", "at": "P", "on": "rod", "mass": 3.0}],
        "joints": [{"name": "pin", "type": "pin", "body": "rod", "at": "O"}],
        "drives": [{"name": "motor", "type": "rotation", "body": "rod", "at": "O",
                    "law": {"type": "constant", "value": 0.0}}],
        "gravity": [0.0, -G],
        "responses": [{"name": "pin", "type": "reaction", "joint": "pin",
                       "component": "magnitude"}],
        "objective": {"response": "pin", "over": "integral"},
        "constraints": [{"response": "pin", "upper": 10.0, "over": "integral",
                         "window": [0.004, 0.016]}],
        "time": {"t_end": 0.02, "h": 1e-3, "start": "static", "newton": "full"}}


@pytest.mark.parametrize("method", ["direct", "adjoint"])
def test_integral_of_a_constant_reaction(method):
    """The rod at rest (static start): the integral of the pin's reaction over [0, 0.02] s is
    W t_end and over the window [0.004, 0.016] W 0.012 (trapezoid exact on a constant),
    W = (3 + rho pi d^2/4 L) g; their gradients dW/dd times the spans, dW/dd = rho pi d/2 L g
    (per mm: x 1e-3), by direct differentiation and by the adjoint. Tolerance 1e-8
    relative (the Newton tolerance of the static solve; tests/test_problem_responses.py
    measured 6e-10 on the reaction itself)."""
    p = Problem(_hanging())
    ev = p.evaluate(method=method)
    assert ev.gradient_method == method
    d = 0.02
    W = (3.0 + 7850.0 * math.pi * d ** 2 / 4) * G
    dW = 7850.0 * math.pi * d / 2 * G * 1e-3
    assert ev.objective == pytest.approx(W * 0.02, rel=REL)
    assert ev.constraints[0] == pytest.approx((W * 0.012 - 10.0) / 10.0, rel=REL)
    assert ev.d_objective[0] == pytest.approx(dW * 0.02, rel=REL)
    assert ev.jacobian[0, 0] == pytest.approx(dW * 0.012 / 10.0, rel=REL)


def _robot(**more):
    ov = {"time.t_end": 0.05, "time.newton": "full", "constraints.0.over": "integral",
          "constraints.0.upper": 1e-5, "objective": {"response": "deviation_28",
                                                     "over": "integral"}}
    ov.update(more)
    return Problem("robot_2dof", ov)


@pytest.mark.parametrize("start,more", [("rest", {}), ("static", {}),
                                        ("static", {"constraints.0.window": [0.01, 0.035]})])
def test_integral_adjoint_equals_direct(start, more):
    """Robot (cases/robot_2dof.toml, 0.05 s): the integral of the deviation (28) as the
    objective and as a constraint (over the whole run, and over a window): the adjoint's
    gradients equal direct differentiation's to 1e-8 relative (both differentiate the same
    discrete solution; docs/adjoint.md: 1e-13 to 1e-9 measured for the other aggregates)."""
    p = _robot(**{"time.start": start, **more})
    direct = p.evaluate(p.start, method="direct")
    adj = p.evaluate(p.start, method="adjoint")
    assert adj.objective == pytest.approx(direct.objective, rel=1e-12)
    assert _rel(adj.jacobian, direct.jacobian) < REL
    assert _rel(adj.d_objective, direct.d_objective) < REL
    # the objective is the trapezoid rule on the deviation history
    t, dev = direct.t, direct.values["deviation_28"]
    assert direct.objective == pytest.approx(float(np.trapezoid(dev, t)), rel=1e-13)


def test_taylor_integral_robot():
    """Taylor test (robot from rest, 0.05 s, integral of the deviation): the central
    difference remainder |(G(x + h d) - G(x - h d)) / 2h - dG . d| of the adjoint gradient
    falls as h^2: observed order within [1.8, 2.2] over h = 0.02 .. 1.25e-3 (relative to the
    design; the same steps as tests/test_adjoint.py's KS Taylor test)."""
    p = _robot(**{"time.start": "rest"})
    x = np.asarray(p.start, float)
    ev = p.evaluate(x, method="adjoint")
    d = np.array([0.6, -0.3, 0.8, 0.5]) * x
    slope = float(ev.d_objective @ d)
    rem = []
    for h in [0.02 / 2 ** k for k in range(5)]:
        fp = p.evaluate(x + h * d, gradient=False).objective
        fm = p.evaluate(x - h * d, gradient=False).objective
        rem.append(abs((fp - fm) / (2 * h) - slope))
    orders = np.log2(np.array(rem[:-1]) / np.array(rem[1:]))
    assert np.all((orders > 1.8) & (orders < 2.2)), (rem, orders)


def test_integral_bad_input():
    """A parameter given with over = 'integral' is a CaseError naming the key and the value;
    aggregate(how='integral') refuses a parameter, missing times and several samples per
    step (ModelError naming them)."""
    with pytest.raises(CaseError, match=r"constraints\[0\]\.parameter.*over = 'integral'.*30"):
        Problem("robot_2dof", {"constraints.0.over": "integral", "constraints.0.parameter": 30.0})
    with pytest.raises(CaseError, match=r"objective\.over"):
        Problem("robot_2dof", {"objective": {"response": "deviation_28", "over": "area"}})
    t = np.linspace(0, 1, 5)
    with pytest.raises(ModelError, match="parameter of 'integral'"):
        aggregate(t, None, "integral", t=t, parameter=2.0)
    with pytest.raises(ModelError, match="needs the times t"):
        aggregate(t, None, "integral")
    with pytest.raises(ModelError, match=r"one sample per time step.*\(5, 2\)"):
        aggregate(np.ones((5, 2)), None, "integral", t=t)
