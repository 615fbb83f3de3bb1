"""Tolerances of error-controlled steps (time.h = "auto", flexmbs.analysis.adaptive) at their
limits, and long runs announced on the command line (flexmbs.cli.common.announce_run).

A tolerance is a positive finite number from the case file, --set and Python alike (a
CaseError naming the key otherwise); one that the shortest steps allowed (1/1024 of the
coarse pilot's) do not reach is refused with the tolerance they reach; one that asks for
shorter steps over part of the run runs at the shortest there and says so; one that any
grid reaches runs on the longest steps and says so. docs/accuracy.md, "Error-controlled
steps"."""
import json
import re

import numpy as np
import pytest

import flexmbs.cli.common as common
from flexmbs.analysis.adaptive import SHORTEST, choose_steps
from flexmbs.cli.main import main
from flexmbs.errors import CaseError
from flexmbs.model.casefile import case_path
from flexmbs.problem import Problem

ROBOT = {"time.t_end": 0.05, "time.h": "auto"}


def _reach(message, key):
    """The tolerance `key` a refusal names as reached by the shortest steps."""
    return float(re.search(rf"reach about {key} = ([0-9.e+-]+)", message).group(1))


def test_unreachable_tolerance_is_refused_with_the_one_reached():
    """Robot (cases/robot_2dof.toml, 0.05 s, outputs every 0.5 ms): rtol = 1e-300 and 1e-9
    are refused (CaseError naming time.rtol), and the tolerance the refusal names is the
    error of a uniform run at the shortest step allowed, h / 512 (1 ms / 1024): the largest
    error of each deviation history relative to its largest value, by Richardson
    extrapolation of the runs at h / 256 and h / 512 (second order: error = difference / 3;
    the differences of this case fall by 4 per halving from h to h / 256), within a factor 2
    of it. Measured: 3.13e-9 named, 3.2e-9 by Richardson."""
    for rtol in (1e-300, 1e-9):
        p = Problem("robot_2dof", {**ROBOT, "time.rtol": rtol})
        with pytest.raises(CaseError, match=rf"time.rtol = {rtol:.3g} is out of reach") as e:
            p.evaluate(None, gradient=False)
        reach = _reach(str(e.value), "time.rtol")
    r256, r512 = (Problem("robot_2dof", {"time.t_end": 0.05, "time.h": 5e-4 / k})
                  .evaluate(None, gradient=False).values for k in (256, 512))
    err = max(np.abs(np.asarray(r256[n])[::256] - np.asarray(r512[n])[::512]).max() / 3
              / np.abs(r512[n]).max() for n in ("deviation_28", "deviation_30"))
    assert reach / 2 < err < 2 * reach, (reach, err)


def test_tolerance_near_the_limit_runs_at_the_shortest_steps_and_says_so(capsys):
    """Robot, 0.05 s, rtol 1.1 times the tolerance the shortest steps reach (the refusal's): the
    grid reaches it by the error model (estimated error at most 1), no step is shorter than
    1/1024 of the coarse pilot's 1 ms (but the last two, which halve what is left of t_end
    when it is up to 1.5 steps), part of the run asks for shorter ones (`saturated`
    between 0 and 1), and `flexmbs simulate` says both: the tolerance reached and the part
    taken at the shortest steps."""
    with pytest.raises(CaseError) as e:
        choose_steps(Problem("robot_2dof", {**ROBOT, "time.rtol": 1e-300}))
    rtol = 1.1 * _reach(str(e.value), "time.rtol")
    info = {}
    g = choose_steps(Problem("robot_2dof", {**ROBOT, "time.rtol": rtol}), info=info)
    assert info["estimated_error"] <= 1 and 0 < info["saturated"] < 1, info
    dh, h_min = np.diff(g), 1e-3 / SHORTEST
    assert dh[:-2].min() >= h_min * (1 - 1e-9) and dh[-2:].min() >= h_min / 2
    assert main(["simulate", "robot_2dof", "--t-end", "0.05", "--set", "time.h=auto",
                 "--set", f"time.rtol={rtol!r}"]) == 0
    out = capsys.readouterr().out
    assert f"rtol = {rtol:g} reached" in out and "shorter than the shortest allowed" in out


def test_absolute_tolerance_out_of_reach_is_refused_on_the_command_line(capsys):
    """`flexmbs simulate robot --set time.h=auto --set time.tol=1e-300`: exit status 2 and one
    line on stderr naming time.tol, its value and the tolerance reached instead (no run on
    the coarsest grid with exit status 0)."""
    assert main(["simulate", "robot_2dof", "--t-end", "0.05", "--set", "time.h=auto",
                 "--set", "time.tol=1e-300"]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "time.tol = 1e-300 is out of reach" in lines[0], err
    assert _reach(lines[0], "time.tol") > 0 and "deviation" not in out


@pytest.mark.parametrize("key", ["tol", "rtol"])
def test_a_tolerance_every_grid_reaches_runs_on_the_longest_steps(capsys, key):
    """tol or rtol = 1e300: every grid is within it, so the steps are the longest allowed
    (t_end / 20 by default, rounded down to the ladder H 2^(k/4): at most 2^(1/4) x 20 steps,
    fewer than the 100 of the response grid), and the output says the tolerance is
    reached (summary line and JSON resolution.grid)."""
    args = ["simulate", "robot_2dof", "--t-end", "0.05", "--set", "time.h=auto",
            "--set", f"time.{key}=1e300"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert f"{key} = 1e+300 reached" in out
    assert main(args + ["--json"]) == 0
    grid = json.loads(capsys.readouterr().out)["resolution"]["grid"]
    assert grid["tolerance_reached"] and grid["estimated_error"] <= 1
    assert 20 <= grid["steps"] <= 20 * 2 ** 0.25 and grid["h_max"] <= 0.05 / 20 * (1 + 1e-9)


def test_a_grid_of_more_steps_than_the_core_counts_is_refused_before_it_is_built(monkeypatch):
    """A tolerance whose grid would hold more steps than the core counts (MAX_STEPS, here
    lowered to 1000 for the robot's 0.05 s at rtol 1e-6, a grid of about 10^4 steps) is a
    ResourceError naming time.rtol and the steps, raised before the grid is marched."""
    import flexmbs.analysis.adaptive as adaptive
    from flexmbs.errors import ResourceError

    monkeypatch.setattr(adaptive, "MAX_STEPS", 1000)
    p = Problem("robot_2dof", {**ROBOT, "time.rtol": 1e-6})
    with pytest.raises(ResourceError, match=r"time.rtol = 1e-06 needs about .* steps .* "
                                            r"more than the core's 1000"):
        choose_steps(p)


BAD = ["0", "-1", "nan", "inf", "-inf"]


@pytest.mark.parametrize("key", ["tol", "rtol"])
@pytest.mark.parametrize("value", BAD)
def test_bad_tolerances_are_refused_naming_the_key(tmp_path, capsys, key, value):
    """tol and rtol of 0, -1, nan, +-inf: a CaseError (one line, exit status 2, on the command
    line) naming time.tol / time.rtol, from the case file, from --set, from Python's
    overrides and from choose_steps's arguments; never a run."""
    text = open(case_path("robot_2dof")).read()
    case = tmp_path / "robot.toml"
    case.write_text(text.replace("h = 5.0e-4\n", f'h = "auto"\n{key} = {value}\n', 1))
    match = rf"time\.{key}"
    with pytest.raises(CaseError, match=match):
        Problem(str(case))
    assert main(["simulate", str(case)]) == 2
    assert re.search(match, capsys.readouterr().err)
    assert main(["simulate", "robot_2dof", "--set", "time.h=auto",
                 "--set", f"time.{key}={value}"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and re.search(match, err), err
    with pytest.raises(CaseError, match=match):
        Problem("robot_2dof", {"time.h": "auto", f"time.{key}": float(value)})
    p = Problem("robot_2dof", {**ROBOT, "time.rtol": 1e-2})
    with pytest.raises(CaseError, match=match):
        choose_steps(p, **{key: float(value)})


# ----------------------------------------------------------------------------- long runs
def _no_run(monkeypatch):
    """Replace the evaluation by an interruption: what is printed comes before the run."""
    def interrupted(self, *a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(Problem, "evaluate", interrupted)


def test_a_long_run_is_announced_before_it_starts(monkeypatch, capsys):
    """three_arm_robot with t_end = 1500 s (h = 0.5 ms: 3 000 000 steps) prints its steps and a
    rough time on stderr before the run (the run replaced by a Ctrl-C: exit status 130); the
    case's own 0.5 s (1000 steps, below LONG_RUN_STEPS) prints nothing before it."""
    _no_run(monkeypatch)
    assert main(["simulate", "three_arm_robot", "--t-end", "1500"]) == 130
    err = capsys.readouterr().err
    assert "flexmbs simulate: 3000000 time steps (h = 0.0005 s to t = 1500 s), roughly" in err
    assert main(["evaluate", "three_arm_robot", "--t-end", "0.5"]) == 130
    assert capsys.readouterr().err.strip() == "flexmbs evaluate: interrupted"


def test_error_controlled_runs_announce_pilots_and_grid(monkeypatch, capsys):
    """With time.h = "auto" the pilots' steps (3/2 of the response grid's: 150 for the robot's
    0.05 s) are announced before they run, the chosen grid's after, the --error runs counted
    (the grid, halved and quartered: 7 times its steps); LONG_RUN_STEPS lowered to 10."""
    monkeypatch.setattr(common, "LONG_RUN_STEPS", 10)
    _no_run(monkeypatch)
    assert main(["simulate", "robot_2dof", "--t-end", "0.05", "--set", "time.h=auto",
                 "--set", "time.rtol=1e-2", "--error"]) == 130
    lines = capsys.readouterr().err.strip().splitlines()
    steps = choose_steps(Problem("robot_2dof", {**ROBOT, "time.rtol": 1e-2})).size - 1
    assert lines[0].startswith("flexmbs simulate: 150 time steps (the two pilot runs")
    assert lines[1].startswith(f"flexmbs simulate: {7 * steps} time steps ({steps} "
                               "error-controlled steps to t = 0.05 s, and twice and four "
                               "times as many for --error), roughly")
