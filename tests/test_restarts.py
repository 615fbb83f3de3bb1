"""Adaptive step grids (time.h = "auto", flexmbs.analysis.adaptive) between restarts of an
optimization: a multistart's start runs on the grid chosen at its own start design, frozen for
the whole run (its responses smooth in the design: a Taylor test), every local optimum is
re-checked on a grid chosen at itself, and a verified continuation runs on the frozen grid
with every step divided (docs/accuracy.md, "Continuation grids")."""
import numpy as np

from flexmbs.analysis.adaptive import choose_steps, subdivide
from flexmbs.analysis.checks import taylor_test
from flexmbs.methods import verified
from flexmbs.methods.multistart import multistart, start_problem
from flexmbs.problem import Problem

OVER = {"time.t_end": 0.05, "time.h": "auto", "time.rtol": 1e-2, "time.newton": "full",
        "constraints.0.over": "ks"}


def _robot():
    return Problem("robot_2dof", OVER)


def test_each_start_runs_on_the_grid_chosen_at_its_start():
    """Two starts of an adaptive multistart (robot, 0.05 s, rtol 1e-2, 2 MMA iterations): each
    start's record states the grid choose_steps gives at its own start design (number of
    steps, shortest and longest step, rtol, the tolerance reached), the two grids differ, and each local optimum's
    re-check states the grid choose_steps gives at that optimum."""
    p = _robot()
    res = multistart(p, 2, options=dict(optimizer="mma", verify=False),
                     fully=dict(max_iterations=2), workers=1)
    grids = []
    for o in res.optima:
        g = choose_steps(Problem(p.description), o["start"])
        dh = np.diff(g)
        keys = ("steps", "tol", "rtol", "h_min", "h_max")
        assert {k: o["grid"][k] for k in keys} == dict(steps=dh.size, tol=None, rtol=1e-2,
                                                      h_min=dh.min(), h_max=dh.max())
        assert o["grid"]["tolerance_reached"] and o["grid"]["estimated_error"] <= 1
        grids.append(g)
        r = choose_steps(Problem(p.description), o["design"])
        assert o["recheck_grid"]["steps"] == r.size - 1
    assert not np.array_equal(*grids)
    # the caller's problem keeps the grid chosen at its start design
    assert np.array_equal(p.steps(), choose_steps(Problem(p.description), None))
    assert "steps (grid chosen at the start, rtol 0.01)" in res.summary()


def test_a_start_keeps_its_grid_and_its_responses_are_smooth():
    """Within one start the grid chosen at the start design x0 (robot, 0.05 s, rtol 1e-2,
    x0 = 0.7 x the case's start: 22 steps) stays the same object through evaluations, also at
    a design whose own grid differs (24 steps at [54, 57, 34.5, 34.6] mm), and the KS
    deviation constraint is a smooth function of the design on it: the Taylor test of its
    direct gradient along a direction has order in [1.8, 2.2] (2 for a right derivative of
    a smooth response, Taylor remainder; measured 1.997)."""
    p0 = _robot()
    x0 = 0.7 * np.asarray(p0.start, float)
    p, grid = start_problem(p0.description, x0)
    g = p.steps()
    assert grid["steps"] == g.size - 1
    assert np.array_equal(g, choose_steps(Problem(p0.description), x0))
    x1 = np.array([54.0, 57.0, 34.5, 34.6])
    assert choose_steps(Problem(p0.description), x1).size != g.size
    p.evaluate(x1, gradient=False)
    ev = p.evaluate(x0)
    d = np.array([0.6, -0.3, 0.8, 0.5]) * x0
    check = taylor_test(lambda x: p.evaluate(x, gradient=False).constraints[0], x0,
                        ev.jacobian[0], d, step=0.02, halvings=4,
                        value=ev.constraints[0])
    assert check.ok and check.order < 2.2, check.table()
    assert p.steps() is g


def test_a_resumed_multistart_takes_its_stored_starts(tmp_path):
    """A multistart of an adaptive case run again with the same store takes every stored
    start (their fingerprints match: the grid is a function of the description and the start)
    and gives the same optima and grids."""
    p = _robot()
    kw = dict(options=dict(optimizer="mma", verify=False), fully=dict(max_iterations=1),
              workers=1, store=tmp_path)
    first = multistart(p, 2, **kw)
    stamps = {f: f.stat().st_mtime_ns for f in tmp_path.glob("*.json")}
    again = multistart(p, 2, resume=True, **kw)
    assert {f: f.stat().st_mtime_ns for f in tmp_path.glob("*.json")} == stamps
    assert [o["grid"] for o in again.optima] == [o["grid"] for o in first.optima]
    assert [o["design"] for o in again.optima] == [o["design"] for o in first.optima]


def test_a_continuation_runs_on_the_frozen_grid_subdivided(monkeypatch):
    """A verified continuation of an adaptive case (a verification that finds the design
    infeasible at level 1, then feasible) optimizes on the frozen grid with every step halved
    (Problem.refined(2), the grid the verification integrated) and its record states that
    grid: steps, and subdivided = 2."""
    p = _robot()
    p.adapt(0.8 * np.asarray(p.start, float))
    g = p.steps()

    class V:                                           # a verification's outcome
        def __init__(self, feasible):
            self.verified, self.feasible, self.level = True, feasible, 1
            self.h, self.max_violation, self.rtol, self.constraints = 2.5e-4, 0.1, 1e-3, {}

        def to_json(self):
            return {}

    outcomes = iter([V(False), V(True)])
    monkeypatch.setattr(verified, "verify_design", lambda *a, **k: next(outcomes))

    class R:                                           # an optimization's result
        def __init__(self, design):
            self.design, self.objective, self.iterations, self.simulations = design, 1.0, 1, 1
            self.wall_time_s, self.history, self.details, self.reason = 0.0, [], {}, "done"

    seen = []

    def rerun(fine, x):
        seen.append(fine)
        return R(x)
    res = verified.finish(p, R(np.asarray(p.start, float)), rerun, True)
    assert np.array_equal(seen[0].steps(), subdivide(g, 2))
    grid = res.details["continuations"][0]["grid"]
    assert grid["steps"] == 2 * (g.size - 1) and grid["subdivided"] == 2
