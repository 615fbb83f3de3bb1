"""Two mechanisms beyond the paper, in the general case format, optimized by both methods: the three-arm robot
(cases/three_arm_robot.toml) and the tube four-bar (cases/fourbar_tubes.toml).
(The press, cases/slider_crank_press.toml: tests/test_problem_optimize.py and
tests/test_problem_weakly.py.)

Fully coupled (flexmbs.methods.fully): converged, the final design re-simulated by a
fresh Problem is feasible, and the first-order (KKT) condition holds at it, checked
independently of the optimizer's own test: a nonnegative least-squares fit of multipliers of
the active rows (g >= -1e-3) and the touched bounds to -grad f, in variables scaled by the
design (x_i d/dx_i), leaves a residual < 1e-2 |grad f| (the optimizer stops at its own KKT
residual < 1e-3: 10x margin; measured 9.4e-5 robot, 0 four-bar).

Weakly coupled (flexmbs.methods.weakly): converged or stopped with a stated reason;
its design compared with the fully coupled optimum. Measured (2 cores, other jobs running):
robot, fully 2.2769 kg (4 iterations, 13 simulations, 2-7 s), weakly 2.2807 kg (+0.17 %,
6 cycles, feasible); four-bar, fully 0.9918 kg from the case's start (17 iterations, 139
simulations, 60 s) and 0.9530 kg from (160, 40, 40, 1.5) (8 iterations, 37 simulations, 7 s:
another local optimum, t at its lower bound), weakly oscillating between 1.40 and 1.46 kg from
cycle 5 to 40 with the stress 1-5 % over its limit (tangent frames; move_limit 0.1 does not stop
it): heavier, as the paper's Table 3 finds for the four-bar.
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import nnls

from flexmbs.methods.esl import equivalent_static_loads
from flexmbs.methods.weakly import StaticModel
from flexmbs.optimize import optimize_fully, optimize_weakly
from flexmbs.problem import Problem


CASES = Path(__file__).resolve().parents[1] / "cases"
ROBOT = CASES / "three_arm_robot.toml"
FOURBAR = CASES / "fourbar_tubes.toml"
#: four-bar fully coupled start: the case's start (100, 100, 100, 5) takes 139 simulations
#: (~60 s on a loaded machine); this one, nearer the optimum, 37 (~7 s)
FOURBAR_X0 = [160.0, 40.0, 40.0, 1.5]


def _kkt_residual(path, design, h=None):
    """Relative residual of the nonnegative least-squares multiplier fit (module docstring),
    from a fresh Problem's evaluation with gradients; also the number of active rows."""
    problem = Problem(path, overrides=None if h is None else {"time.h": h})
    ev = problem.evaluate(design, gradient=True)
    x = np.asarray(design, float)
    df = ev.d_objective * x
    active = ev.constraints >= -1e-3
    cols = [(ev.jacobian[active] * x).T]
    lo, hi = problem.lower, problem.upper
    for i in range(x.size):
        e = np.zeros((x.size, 1))
        e[i, 0] = x[i]
        if x[i] <= lo[i] * (1 + 1e-6):
            cols.append(-e)
        if x[i] >= hi[i] * (1 - 1e-6):
            cols.append(e)
    _, res = nnls(np.hstack(cols), -df)
    return res / np.linalg.norm(df), int(active.sum()), ev


@pytest.fixture(scope="module")
def robot_fully():
    return optimize_fully(Problem(ROBOT))


@pytest.fixture(scope="module")
def fourbar_fully():
    # at the case's step: the comparisons below are of the methods, not of the resolution
    # (the verification and its continuation: tests/test_accuracy.py)
    return optimize_fully(Problem(FOURBAR), FOURBAR_X0, options=dict(verify=False))


@pytest.mark.parametrize("which", ["robot", "fourbar"])
def test_fully_coupled_optimum_is_feasible_and_a_kkt_point(which, request):
    """Fully coupled: converged; the final design re-simulated by a fresh Problem (at the step
    its verification settled on when it was continued there; the robot's is verified feasible
    at the case's step) satisfies every constraint (max g <= 1e-6, torque limits included for
    the robot); at least one constraint is active (the mass alone would run to the lower
    bounds: robot, the tip deviation; four-bar, the stress); the KKT condition holds there
    (module docstring)."""
    res = request.getfixturevalue(f"{which}_fully")
    assert res.converged, res.reason
    if res.verification is not None:
        assert res.verification.verified and res.verification.feasible
    kkt, nactive, ev = _kkt_residual(ROBOT if which == "robot" else FOURBAR, res.design,
                                     res.verification.h if "continued_from" in res.details
                                     else None)
    assert ev.max_violation <= 1e-6
    assert ev.objective == pytest.approx(res.objective, rel=1e-12)
    assert nactive >= 1
    active = set(np.array(ev.constraint_names)[ev.constraints >= -1e-3])
    assert active == ({"tip_deviation"} if which == "robot" else {"link_stress"})
    assert kkt < 1e-2


def test_robot_static_model_includes_the_turn_of_the_relative_joints():
    """The robot's elbow and wrist motors drive their arm relative to the previous one, so a
    deflection slope at A turns arms 2 and 3 rigidly. At the ESL design the static tip
    deviation must equal the simulated one (eq. 19, K^-1 g_eq = u, plus the linearised turn):
    measured 2.5e-4 relative at the start (2.8 mm); asserted < 5e-3. Without the turn the
    static model predicted a converged weakly design feasible whose simulated deviation was
    2.7 times the limit."""
    prob = Problem(ROBOT)
    x = prob.start
    static = StaticModel(prob)
    res = prob.simulate(x, store="all")
    model = prob.mechanism.set_design(x)
    static.set_loads(equivalent_static_loads(model, res, static.frames,
                                             stiffness=static.stiffness))
    values, _ = static.responses_at(x, gradient=False)
    dyn = prob.evaluate(x, gradient=False).values["tip_deviation"]
    assert np.abs(values["tip_deviation"][0] - dyn).max() < 5e-3 * dyn.max()


def test_robot_static_deviation_gradient_taylor():
    """The static tip deviation's design gradient, turn of the relative joints included, by a
    Taylor test at (45, 37, 26) mm with the ESL of the start: the remainder |r(x + h d) - r(x)
    - h r'(x) d| falls by 100 per decade of h (second order; measured 99.6 for h = 0.1, 0.01,
    0.001 mm); asserted > 50, a first-order (wrong gradient) remainder falls by 10."""
    prob = Problem(ROBOT)
    static = StaticModel(prob)
    res = prob.simulate(prob.start, store="all")
    model = prob.mechanism.set_design(prob.start)
    static.set_loads(equivalent_static_loads(model, res, static.frames,
                                             stiffness=static.stiffness))
    y = np.array([45.0, 37.0, 26.0])
    v, g = static.responses_at(y, gradient=True)
    d = np.random.default_rng(0).standard_normal(3)
    rem = [np.abs(static.responses_at(y + h * d, gradient=False)[0]["tip_deviation"][0]
                  - v["tip_deviation"][0] - h * g["tip_deviation"][0] @ d).max()
           for h in (1e-1, 1e-2, 1e-3)]
    assert rem[0] / rem[1] > 50 and rem[1] / rem[2] > 50


def test_robot_weakly_matches_fully_and_rechecks_the_torques(robot_fully):
    """Weakly coupled on the serial robot (no loop): converged by eq. (25); the torque
    limits have no static form, so the result names them as checked by simulation only; its
    final design, re-simulated by a fresh Problem, is feasible (all constraints, max g
    measured -2.2e-4) and its mass within 2 % of the fully coupled optimum (measured +0.17 %)."""
    res = optimize_weakly(Problem(ROBOT))
    assert res.converged, res.reason
    assert res.details["constraints_checked_by_simulation"] == [
        "shoulder_torque", "elbow_torque", "wrist_torque"]
    assert "checked by simulation only" in res.reason
    ev = Problem(ROBOT).evaluate(res.design, gradient=False)
    assert ev.max_violation <= 1e-6
    assert res.details["feasible"]
    assert res.mass_kg == pytest.approx(robot_fully.objective, rel=0.02)


def test_fourbar_weakly_is_heavier_than_fully(fourbar_fully):
    """Weakly coupled on the tube four-bar (a loop), the default frames (crank tangent, coupler
    and follower chord): it does not converge in 8 cycles (the masses fall from 4.78 to
    4.38 kg, cycles 5-8 infeasible); stopped with the reason stated, it returns the best
    feasible design seen. Its design is heavier than the fully coupled optimum (the paper's
    Table 3 finding on the four-bar): measured 4.477 kg (cycle 4), 4.7 times 0.953 kg, asserted
    > +4.8 %. The feasibility it reports is the fresh simulation's."""
    res = optimize_weakly(Problem(FOURBAR), options=dict(max_cycles=8, verify=False))
    assert res.reason
    assert res.mass_kg > 1.048 * fourbar_fully.objective
    ev = Problem(FOURBAR).evaluate(res.design, gradient=False)
    assert res.details["feasible"] == (ev.max_violation <= 1e-6)
    assert res.max_violation == pytest.approx(max(0.0, ev.max_violation), rel=1e-9, abs=1e-12)
