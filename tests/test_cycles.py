"""The cycle control of the weakly coupled method (flexmbs.methods.cycles) on synthetic
sequences of designs, ESL changes and constraint values: the diagnoses (converged,
oscillating over up to six cycles as OptiStruct's ESLM, diverging, cap), the best feasible
design kept, the damped update, the move limits and the ESL of the last two cycles. No
simulation runs here except one two-cycle robot run (test_damping_moves_part_of_the_way)."""
import numpy as np
import pytest

from flexmbs.errors import ModelError
from flexmbs.methods.cycles import (CycleControl, check_remedies, damped_update,
                                     move_limited_bounds)
from flexmbs.methods.esl import BodyLoads, EquivalentStaticLoads
from flexmbs.methods.weakly import blend_loads


def _run(designs, changes, violations=None, objectives=None, *, eps=1e-2, confirm=1,
         max_cycles=100, stop=True, design_tol=None):
    """Feed a synthetic sequence to a CycleControl until it stops; (control, stop cycle)."""
    c = CycleControl(eps, confirm, max_cycles, stop, design_tol)
    for k, (x, ch) in enumerate(zip(designs, changes), start=1):
        c.observe(k, x, ch, {}, objective=None if objectives is None else objectives[k - 1],
                  violation=None if violations is None else violations[k - 1])
        if c.stop(k):
            return c, k
    return c, None


def _cycle_of(period, n, radius=10.0):
    """n designs going round a regular polygon of `period` corners (a period-P oscillation)."""
    a = 2 * np.pi * np.arange(n) / period
    return [np.array([50 + radius * np.cos(t), 50 + radius * np.sin(t)]) for t in a]


@pytest.mark.parametrize("period", [2, 3, 5, 6])
def test_oscillation_detected_up_to_six_cycles(period):
    """Designs repeating exactly with period P = 2..6 (OptiStruct's ESLM watches six cycles)
    and a constant ESL change 0.2 >> eps: diagnosis 'oscillating' with that period, found at
    the first cycle where two full repetitions are seen (cycle P + 2)."""
    n = 20
    c, stopped = _run(_cycle_of(period, n), [None] + [0.2] * (n - 1))
    assert c.diagnosis == "oscillating" and c.period == period
    assert stopped == period + 2
    assert not c.converged and "period" in c.reason


def test_period_seven_is_not_an_oscillation():
    """A repetition over 7 cycles lies beyond the six-cycle window: no oscillation is
    reported, the run ends at the cap with diagnosis 'cap'."""
    c, stopped = _run(_cycle_of(7, 30), [None] + [0.2] * 29, max_cycles=30)
    assert c.period is None and c.diagnosis == "cap" and stopped == 30


def test_converging_alternation_is_not_an_oscillation():
    """x_k = 50 + 10 (-0.5)^k alternates about 50 while converging (its ESL change halves
    each cycle): never 'oscillating'; it converges by eq. (25) once the change is below eps in
    two consecutive cycles (cycle k's change 0.2 * 0.5^(k-1) < 1e-2 from cycle 6 on: stops at
    cycle 7)."""
    n = 15
    designs = [np.array([50 + 10 * (-0.5) ** k]) for k in range(n)]
    changes = [None] + [0.2 * 0.5 ** k for k in range(1, n)]
    c, stopped = _run(designs, changes)
    assert c.diagnosis == "converged" and c.converged and c.period is None
    assert stopped == 7


def test_diverging():
    """ESL changes 0.1, 0.15, 0.25, 0.4, 0.8 (grown in each of the last 4 cycles, to 8x) with
    the largest constraint value growing too: diagnosis 'diverging' at the fifth change
    (cycle 6). The same ESL changes with constraint values going up and down (a bounded
    oscillation, as the four-bar's cycles 9-13) or a slow growth (0.10 .. 0.14, under 2x) are
    not divergence."""
    designs = [np.array([50.0 + 3 * k, 40.0 - k]) for k in range(8)]
    growing = [None, 0.1, 0.15, 0.25, 0.4, 0.8, 1.6, 3.2]
    c, stopped = _run(designs, growing, violations=[-0.5, -0.3, -0.1, 0.1, 0.3, 0.5, 1, 2])
    assert c.diagnosis == "diverging" and stopped == 6
    c, stopped = _run(designs, growing, violations=[-0.5, -0.02, -0.05, 0.03, -0.05, 0.08,
                                                    -0.1, 0.1], max_cycles=8)
    assert c.diagnosis == "cap" and stopped == 8
    c, stopped = _run(designs, [None, 0.10, 0.11, 0.12, 0.13, 0.14, 0.145, 0.15], max_cycles=8)
    assert c.diagnosis == "cap" and stopped == 8


def test_best_feasible_design_is_kept():
    """Objectives 10, 5, 7, 6, 8 with constraint values -0.1, +0.2, 0.0, +0.01, -0.3: the
    feasible ones (g <= 1e-6) are cycles 1, 3 and 5; the best of them is cycle 3 (7), not the
    lighter infeasible cycles 2 and 4 nor the last one."""
    designs = [np.array([float(k)]) for k in range(1, 6)]
    c, _ = _run(designs, [None, 0.5, 0.5, 0.5, 0.5], violations=[-0.1, 0.2, 0.0, 0.01, -0.3],
                objectives=[10.0, 5.0, 7.0, 6.0, 8.0], max_cycles=5)
    assert c.best.cycle == 3 and c.best.objective == 7.0
    np.testing.assert_array_equal(c.best.design, [3.0])
    c, _ = _run(designs[:2], [None, 0.5], violations=[0.1, 0.2], objectives=[1.0, 2.0],
                max_cycles=2)
    assert c.best is None                                # nothing feasible seen


def test_design_change_criterion():
    """design_tol = 1e-3 (OptiStruct's ESLM: design change and constraint violation between
    cycles): designs changing by 0.05 % while feasible converge after 1 + 1 confirming cycles
    (cycle 3), although the ESL change 0.5 never meets eq. (25); the same designs infeasible
    (g = 0.01) do not converge, nor do they when the static optimization proposed steps of
    5 % that a damped update shrank (`step`)."""
    designs = [np.array([100.0 * (1 + 5e-4) ** k, 50.0]) for k in range(6)]
    c, stopped = _run(designs, [None] + [0.5] * 5, violations=[-0.1] * 6, design_tol=1e-3,
                      max_cycles=6)
    assert c.converged and c.diagnosis == "converged" and stopped == 3
    assert "design change" in c.reason
    c, stopped = _run(designs, [None] + [0.5] * 5, violations=[0.01] * 6, design_tol=1e-3,
                      max_cycles=6)
    assert not c.converged and c.diagnosis == "cap"
    c = CycleControl(1e-2, 1, 6, True, 1e-3)
    for k, x in enumerate(designs, start=1):
        c.observe(k, x, None if k == 1 else 0.5, {}, objective=1.0, violation=-0.1,
                  step=None if k == 1 else 0.05)
        assert not c.stop(k) or k == 6
    assert not c.converged and c.design_changes[-1] == 0.05


def test_damped_update_and_move_limits():
    """damped_update: x + w (x* - x), w = 0.25: from [100, 20] towards [20, 100] -> [80, 40];
    w = 1 gives x*. move_limited_bounds with 0.1: [90, 18]..[110, 22], clipped to the bounds
    [95, 15]..[500, 21]."""
    x, xs = np.array([100.0, 20.0]), np.array([20.0, 100.0])
    np.testing.assert_allclose(damped_update(x, xs, 0.25), [80.0, 40.0], rtol=1e-14)
    np.testing.assert_array_equal(damped_update(x, xs, 1.0), xs)
    lo, hi = move_limited_bounds(x, np.array([95.0, 15.0]), np.array([500.0, 21.0]), 0.1)
    np.testing.assert_allclose(lo, [95.0, 18.0], rtol=1e-14)
    np.testing.assert_allclose(hi, [110.0, 21.0], rtol=1e-14)


def _loads(g, angle):
    t = np.arange(g.shape[0], dtype=float)
    return EquivalentStaticLoads([BodyLoads(name="arm", stiffness=None, props=np.zeros((5, 1)),
                                            t=t, origin=np.zeros((t.size, 2)),
                                            angle=np.full(t.size, angle),
                                            u=np.zeros_like(g), g_eq=g)])


def test_blend_loads():
    """ESL of the last two cycles: weight 0.25 gives 0.75 g_k + 0.25 g_(k-1) (g_k = 4,
    g_(k-1) = 8 -> 5) with the current frame angle; weight 0 or no previous loads: the current
    loads; different time grids: ModelError naming the body."""
    cur, prev = _loads(np.full((3, 2), 4.0), 0.3), _loads(np.full((3, 2), 8.0), 0.1)
    b = blend_loads(cur, prev, 0.25)["arm"]
    np.testing.assert_allclose(b.g_eq, 5.0, rtol=1e-14)
    assert np.all(b.angle == 0.3)
    assert blend_loads(cur, prev, 0.0) is cur and blend_loads(cur, None, 0.5) is cur
    with pytest.raises(ModelError, match="body 'arm': ESL of different shapes"):
        blend_loads(cur, _loads(np.ones((4, 2)), 0.1), 0.5)


@pytest.mark.parametrize("kw, msg", [
    (dict(damping=1.5), r"damping must lie in \(0, 1\].*got 1.5"),
    (dict(damping=0.0), r"damping must be a positive finite number, got 0.0"),
    (dict(esl_blend=1.0), r"esl_blend must lie in \[0, 1\).*got 1.0"),
    (dict(design_tol=-1e-3), r"design_tol \(or None\) must be a positive finite number"),
])
def test_remedy_options_checked(kw, msg):
    """Out-of-range anti-oscillation options are ModelErrors naming the option, the value and
    the allowed range."""
    opts = dict(damping=1.0, esl_blend=0.0, design_tol=None)
    opts.update(kw)
    with pytest.raises(ModelError, match=msg):
        check_remedies(**opts)


def test_damping_moves_part_of_the_way():
    """On the robot (two cycles), damping 0.5 makes the second cycle's design the midpoint of
    the start and the undamped second design: both solve the same first static problem (the
    ESL of the start), so x2 = x1 + 0.5 (x* - x1) exactly, up to SLSQP's rounding."""
    from flexmbs.optimize import optimize_weakly
    from flexmbs.problem import Problem
    r1 = optimize_weakly(Problem("robot_2dof"), options=dict(max_cycles=2))
    r2 = optimize_weakly(Problem("robot_2dof"), options=dict(max_cycles=2, damping=0.5))
    x1 = np.asarray(r1.history[0]["design"])
    xs = np.asarray(r1.history[1]["design"])
    assert np.max(np.abs(xs - x1) / x1) > 0.1                  # the step is not negligible
    np.testing.assert_allclose(r2.history[1]["design"], x1 + 0.5 * (xs - x1), rtol=1e-6)
    assert r2.details["damping"] == 0.5


def test_cli_remedy_option_checked(capsys):
    """``flexmbs optimize robot_2dof --method weakly --damping 1.5``: exit status 2 and one
    line naming the option, the value and the allowed range (before any simulation)."""
    from flexmbs.cli.main import main
    assert main(["optimize", "robot_2dof", "--method", "weakly", "--damping", "1.5"]) == 2
    err = capsys.readouterr().err
    assert "option damping = 1.5: Input should be less than or equal to 1" in err


def test_oscillating_run_returns_best_feasible_design():
    """The paper's oscillating case (robot, 0.66 s, Table 5) in the paper's cycles (shrink 0):
    the run stops 'oscillating', not converged, and returns the lightest design among the cycles whose simulation was feasible
    (g <= 1e-6); a fresh simulation of the returned design confirms it is feasible."""
    from flexmbs.optimize import optimize_weakly
    from flexmbs.problem import Problem
    r = optimize_weakly(Problem("robot_2dof", overrides={"time.t_end": 0.66}),
                        options=dict(max_cycles=15, shrink=0))
    assert not r.converged and r.details["diagnosis"] == "oscillating"
    feasible = [h for h in r.history if h["max_violation"] <= 1e-6]
    best = min(feasible, key=lambda h: h["mass_kg"])
    assert r.details["best_feasible_cycle"] == best["iteration"]
    np.testing.assert_array_equal(r.design, best["design"])
    ev = Problem("robot_2dof", overrides={"time.t_end": 0.66}).evaluate(r.design, gradient=False)
    assert ev.constraints.max() <= 1e-6


def _bang_bang_cycles(shrink, max_cycles=60, x0=60.0, centre=50.0):
    """Cycles on a one-variable static problem whose optimum jumps to the other side of its
    fixed point: x* (x) = centre - 10 tanh(x - centre) (an unstable fixed point at `centre`,
    slope -11; from x0 = 60 the plain cycles alternate 60 <-> 40.0000, a period-2
    oscillation). The static optimum is clipped to the move limits as the weakly coupled
    cycles do. Returns (control, designs)."""
    from flexmbs.methods.cycles import ShrinkingMoveLimit
    c = CycleControl(1e-2, 1, max_cycles, True, None)
    mover = ShrinkingMoveLimit(shrink) if shrink > 0 else None
    lower, upper = np.array([1.0]), np.array([100.0])
    x, step, designs = np.array([x0]), None, []
    for k in range(1, max_cycles + 1):
        designs.append(x)
        c.observe(k, x, 0.5, {}, objective=float(x[0]), violation=-1.0, step=step)
        if mover is not None and c.period is not None:
            mover.oscillation(k, c.designs, c.period)
            c.period = None
            c.design_tol = c.design_tol or 1e-3
        if c.stop(k):
            break
        lo, hi = (lower, upper) if mover is None else mover.bounds(x, lower, upper)
        x_star = np.clip(centre - 10.0 * np.tanh(x - centre), lo, hi)
        step = float(np.max(np.abs(x_star - x) / np.abs(x)))
        x_new = x_star
        if mover is not None and len(c.designs) >= 2:
            mover.step(c.designs[-2], x, x_new)
        x = x_new
    return c, designs


def test_shrinking_move_limit_settles_an_oscillation_on_the_fixed_point():
    """The period-2 oscillation of `_bang_bang_cycles` (60 <-> 40 about the fixed point 50):
    with shrink 0.5 the move limit starts at half the oscillation's amplitude and halves at
    every reversal, so the designs converge; the run ends 'converged' by the design-change
    criterion (SHRINK_DESIGN_TOL = 1e-3) within the cycle cap. The last two designs straddle
    the fixed point (the map sends each to its other side) and differ by less than 1e-3 of
    the design, so the design lies within 1e-3 * 50 = 0.05 of 50."""
    from flexmbs.methods.cycles import SHRINK_DESIGN_TOL
    c, designs = _bang_bang_cycles(0.5)
    assert c.converged and c.diagnosis == "converged", c.reason
    assert "design change" in c.reason
    assert abs(designs[-1][0] - 50.0) < SHRINK_DESIGN_TOL * 50.0


def test_without_shrinking_the_same_cycles_stop_oscillating():
    """The same cycles with shrink 0 (the paper's cycles): the designs repeat 60, 40, 60, ...
    and the run stops at cycle 4 with diagnosis 'oscillating', period 2."""
    c, designs = _bang_bang_cycles(0.0)
    assert c.diagnosis == "oscillating" and c.period == 2 and len(designs) == 4


def test_shrinking_move_limit_shrinks_only_reversing_variables():
    """`ShrinkingMoveLimit`: an oscillation over designs [50, 10], [60, 10], [50, 10] sets
    every limit to shrink * amplitude = 0.5 * (60 - 50) / 60; a cycle where variable 1
    reverses (50 -> 55 -> 52) and variable 2 keeps its direction (10 -> 11 -> 12) halves the
    first limit only; the bounds are x (1 -/+ limit) within the variables' bounds."""
    from flexmbs.methods.cycles import ShrinkingMoveLimit
    m = ShrinkingMoveLimit(0.5)
    lo0, hi0 = np.array([1.0, 1.0]), np.array([100.0, 100.0])
    assert not m.active
    assert np.array_equal(m.bounds(np.array([50.0, 10.0]), lo0, hi0)[0], lo0)
    m.oscillation(3, [np.array([50.0, 10.0]), np.array([60.0, 10.0]),
                      np.array([50.0, 10.0])], 2)
    a = 0.5 * 10.0 / 60.0
    assert m.active and np.allclose(m.limits, [a, a])
    m.step(np.array([50.0, 10.0]), np.array([55.0, 11.0]), np.array([52.0, 12.0]))
    assert np.allclose(m.limits, [a / 2, a])
    lo, hi = m.bounds(np.array([52.0, 12.0]), lo0, hi0)
    assert np.allclose(lo, [52 * (1 - a / 2), 12 * (1 - a)])
    assert np.allclose(hi, [52 * (1 + a / 2), 12 * (1 + a)])


def test_shrink_option_is_checked():
    """WeaklyOptions.shrink must lie in [0, 1): 1 is refused with a message naming the
    option."""
    from flexmbs.model.options import WeaklyOptions, build
    with pytest.raises(Exception, match="shrink"):
        build(WeaklyOptions, dict(shrink=1.0))


def test_shrinking_move_limit_converges_the_papers_oscillating_case():
    """The paper's oscillating case (robot, 0.66 s, Table 5; paper 8.1: the weakly coupled
    cycles oscillate to the maximum number of cycles) with the default options (shrink 0.5):
    the oscillation is detected, the cycles go on with shrinking move limits and end
    'converged' within 30 cycles, at a design whose mass lies within 1 % of the paper's fully
    coupled optimum of the same problem, 1.099 kg (Table 5), and which is feasible at h/4 (the
    step the verification of this design reaches) within the verification's accuracy 1e-3
    (VERIFY_RTOL)."""
    from flexmbs.analysis.accuracy import VERIFY_RTOL
    from flexmbs.optimize import optimize_weakly
    from flexmbs.problem import Problem
    r = optimize_weakly(Problem("robot_2dof", overrides={"time.t_end": 0.66}),
                        options=dict(verify=False))
    assert r.converged and r.details["diagnosis"] == "converged", r.reason
    assert r.details["shrink_cycle"] is not None and r.details["oscillation_period"] is not None
    assert r.iterations <= 30
    assert abs(r.mass_kg - 1.099) < 0.01 * 1.099
    fine = Problem("robot_2dof", overrides={"time.t_end": 0.66, "time.h": 5e-4 / 4})
    assert fine.evaluate(r.design, gradient=False).constraints.max() <= VERIFY_RTOL


@pytest.mark.parametrize("diagnosis, shrink, damping, expected, absent", [
    ("oscillating", 0.0, 1.0, ["--shrink 0.5", "--damping 0.5", "--method fully"], ["--max-cycles"]),
    ("cap", 0.5, 1.0, ["--max-cycles 60", "--shrink 0.3", "--damping 0.5"], ["--shrink 0.5"]),
    ("diverging", 0.5, 0.5, ["--design-tol", "--method fully"], ["--damping", "--shrink"]),
])
def test_what_to_try_names_the_remedies_the_run_did_not_use(diagnosis, shrink, damping,
                                                            expected, absent):
    """`what_to_try` after a run that did not converge (30 cycles at most): the remedies of
    docs/optimizers.md the run did not already use, as command-line options (an oscillation
    in the paper's cycles: a shrinking move limit; the cap: twice the cycles, a faster shrink;
    a damped update unless damping <= 0.5); nothing after 'converged'."""
    from flexmbs.methods.cycles import what_to_try
    text = what_to_try(diagnosis, shrink, damping, 30)
    assert all(e in text for e in expected), text
    assert not any(a in text for a in absent), text
    assert what_to_try("converged", 0.5, 1.0, 30) == ""
