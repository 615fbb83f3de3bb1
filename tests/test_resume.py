"""Long runs: progress shown only when asked (flexmbs.progress, tqdm), and resumable
optimizations (`resume=` / ``--resume``) that end at the same design as an uninterrupted run
with fewer simulations.

The reference of every resume test is the same optimization run once without interruption:
the optimizers are deterministic, so a resumed run that replays its recorded analyses (fully
coupled) or restarts from its last completed cycle (weakly coupled) must reach the same design,
to rounding (compared to 1e-12 relative; a replay that changed a single analysis would move
the design by far more). Cheap setups: the robot of cases/robot_2dof.toml over 0.1-0.15 s.
"""
from __future__ import annotations

import io

import numpy as np
import pytest

from flexmbs.cli.main import main
from flexmbs.errors import ModelError
from flexmbs.optimize import optimize_fully, optimize_weakly, read_history
from flexmbs.problem import Problem


class _Counted(Problem):
    """The robot with its simulations counted (evaluate: fully coupled; simulate: weakly)."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.evaluations = 0
        self.simulations = 0

    def evaluate(self, *a, **k):
        self.evaluations += 1
        return super().evaluate(*a, **k)

    def simulate(self, *a, **k):
        self.simulations += 1
        return super().simulate(*a, **k)


def _robot(t_end=0.1):
    return _Counted("robot_2dof", {"time.t_end": t_end})


class _Interrupt(Exception):
    pass


def _stop_at(k):
    def progress(rec):
        if rec["iteration"] == k:
            raise _Interrupt
    return progress


@pytest.mark.parametrize("optimizer, t_end", [("mma", 0.1), ("sqp", 0.1),
                                              ("nlopt-ccsaq", 0.15)])
def test_fully_interrupted_run_resumes_to_the_same_design(tmp_path, optimizer, t_end):
    """A fully coupled run interrupted after 3 iterations (an exception from the progress
    callback, as Ctrl-C) and resumed from its history ends at the design of the uninterrupted
    run (1e-12 relative), with as many iterations, and the resumed run simulates fewer designs:
    exactly those of the uninterrupted run after the recorded ones (counted on the problem)."""
    ref_problem = _robot(t_end)
    ref = optimize_fully(ref_problem, optimizer=optimizer)
    assert ref.iterations > 3

    h = tmp_path / "h.jsonl"
    first = _robot(t_end)
    with pytest.raises(_Interrupt):
        optimize_fully(first, optimizer=optimizer, history=h, progress=_stop_at(3))
    recs = read_history(h)
    assert [r["iteration"] for r in recs] == [0, 1, 2, 3]
    recorded = sum(len(r["evaluations"]) for r in recs)
    assert recorded == first.evaluations        # every analysis is in the file
    # of each response its largest value only, not its history (the file stays small)
    assert all(not isinstance(v, list) for r in recs for e in r["evaluations"]
               for v in e["values"].values())

    again = _robot(t_end)
    res = optimize_fully(again, optimizer=optimizer, history=h, resume=True)
    np.testing.assert_allclose(res.design, ref.design, rtol=1e-12, atol=0)
    assert res.iterations == ref.iterations and res.converged == ref.converged
    assert res.details["replayed_simulations"] == recorded
    # the uninterrupted run's analyses, less the replayed ones (both include the final check)
    assert again.evaluations == ref_problem.evaluations - recorded
    assert again.evaluations < ref_problem.evaluations
    # the file now holds the whole run, iterations 0..n once each
    assert [r["iteration"] for r in read_history(h)] == list(range(ref.iterations + 1))


def test_fully_resume_with_more_iterations_after_a_killed_job(tmp_path):
    """A run stopped by max_iterations=2 whose history ends in a line cut short (a job killed
    while writing) resumes, with the default iteration limit, to the uninterrupted design
    (1e-12 relative); the cut line is dropped from the file with a warning."""
    ref = optimize_fully(_robot())
    h = tmp_path / "h.jsonl"
    optimize_fully(_robot(), history=h, options=dict(max_iterations=2))
    with open(h, "a", encoding="utf-8") as fh:
        fh.write('{"iteration": 3, "design": [37.5')
    with pytest.warns(UserWarning, match="cut short"):
        res = optimize_fully(_robot(), history=h, resume=True)
    np.testing.assert_allclose(res.design, ref.design, rtol=1e-12, atol=0)
    assert [r["iteration"] for r in read_history(h)] == list(range(ref.iterations + 1))


def test_fully_resume_with_other_start_is_refused(tmp_path):
    """Resuming a history with another start: ModelError naming the file and the start (the
    option x0) that differs from the history's fingerprint."""
    h = tmp_path / "h.jsonl"
    optimize_fully(_robot(), history=h, options=dict(max_iterations=1))
    with pytest.raises(ModelError, match=r"h\.jsonl' does not answer this run.*option x0: "
                                         r"\[50\.0, 50\.0, 50\.0, 50\.0\] -> \[45\.0"):
        optimize_fully(_robot(), [45.0, 45.0, 45.0, 45.0], history=h, resume=True)


@pytest.mark.parametrize("func", [optimize_fully, optimize_weakly])
def test_resume_needs_a_history_file(func):
    """resume=True without history: ModelError saying history=FILE is needed; a non-bool
    resume is named."""
    with pytest.raises(ModelError, match="resume needs the history file of the interrupted "
                                         "run: give history=FILE"):
        func(_robot(), resume=True)
    with pytest.raises(ModelError, match="resume must be True or False, got 'yes'"):
        func(_robot(), resume="yes")


def test_weakly_interrupted_run_resumes_to_the_same_design(tmp_path):
    """A weakly coupled run interrupted after its 4th cycle and resumed from its history ends
    at the uninterrupted run's design (1e-12 relative) after the same cycles (same designs in
    the history); it simulates 2 designs again (cycles 3 and 4: the previous ESL and the last
    cycle) instead of 4, so 2 fewer simulations in all."""
    ref_problem = _robot()
    # verify=False: the counts below are the cycles' simulations alone
    ref = optimize_weakly(ref_problem, options=dict(verify=False))
    assert ref.iterations > 4
    h = tmp_path / "w.jsonl"
    with pytest.raises(_Interrupt):
        optimize_weakly(_robot(), history=h, progress=_stop_at(4), options=dict(verify=False))
    assert [r["iteration"] for r in read_history(h)] == [1, 2, 3, 4]
    again = _robot()
    res = optimize_weakly(again, history=h, resume=True, options=dict(verify=False))
    np.testing.assert_allclose(res.design, ref.design, rtol=1e-12, atol=0)
    assert res.iterations == ref.iterations and res.converged == ref.converged
    assert [r["design"] for r in res.history] == [r["design"] for r in ref.history]
    assert res.details["resumed_cycles"] == 3
    assert again.simulations == ref_problem.simulations - 2 == res.simulations


def test_weakly_resume_with_other_start_is_refused(tmp_path):
    """Resuming a weakly coupled history from another start: ModelError naming the file, the
    file's start (the case's, 50 mm) and this run's (option x0 of the fingerprint)."""
    h = tmp_path / "w.jsonl"
    optimize_weakly(_robot(), history=h, options=dict(max_cycles=1))
    with pytest.raises(ModelError, match=r"w\.jsonl' does not answer this run.*option x0: "
                                         r"\[50\.0, 50\.0, 50\.0, 50\.0\] -> "
                                         r"\[45\.0, 45\.0, 45\.0, 45\.0\]"):
        optimize_weakly(_robot(), [45.0] * 4, history=h, resume=True)


# ----------------------------------------------------------------------------- progress
def test_progress_shown_only_when_asked(capsys):
    """progress=None prints nothing on stdout or stderr; progress=True draws the tqdm bar on
    stderr (label, count, simulations, mass); a text stream receives the bar instead."""
    optimize_fully(_robot(), options=dict(max_iterations=2))
    optimize_weakly(_robot(), options=dict(max_cycles=2))
    out, err = capsys.readouterr()
    assert out == "" and err == ""

    optimize_fully(_robot(), progress=True, options=dict(max_iterations=2))
    out, err = capsys.readouterr()
    assert out == ""
    assert "iterations:" in err and "2/2" in err and "sims" in err and "kg" in err

    stream = io.StringIO()
    optimize_weakly(_robot(), progress=stream, options=dict(max_cycles=2))
    out, err = capsys.readouterr()
    assert out == "" and err == ""
    text = stream.getvalue()
    assert "cycles:" in text and "2/2" in text and "ESL change" in text


def test_multistart_progress_and_batch(capsys):
    """multistart with progress=True: a bar 'starts' reaching 2/2 with the best feasible
    objective on stderr; a callable receives each start's summary; nothing without progress."""
    from flexmbs.optimize import multistart
    seen = []
    multistart(_robot(), 2, workers=1, progress=lambda rec: seen.append(rec["name"]),
               options=dict(optimizer="mma"), fully=dict(max_iterations=2))
    assert sorted(seen) == ["start000", "start001"]
    out, err = capsys.readouterr()
    assert out == "" and err == ""
    multistart(_robot(), 2, workers=1, progress=True, options=dict(optimizer="mma"),
               fully=dict(max_iterations=2))
    out, err = capsys.readouterr()
    assert "starts:" in err and "2/2" in err and ("best feasible" in err or "no feasible" in err)


def test_cli_progress_switch(tmp_path, capsys):
    """`flexmbs optimize --progress` draws the bar on stderr; --no-progress (and the default
    when stderr is not a terminal, as under pytest) leaves stderr empty."""
    args = ["optimize", "robot_2dof", "--method", "fully", "--set", "time.t_end=0.1",
            "--max-iterations", "1"]
    main(args + ["--progress"])
    out, err = capsys.readouterr()
    assert "iterations:" in err and "iteration   1" in out
    main(args + ["--no-progress"])
    out, err = capsys.readouterr()
    assert err == "" and "iteration   1" in out
    main(args)
    assert capsys.readouterr().err == ""


def test_cli_resume(tmp_path, capsys):
    """`flexmbs optimize --resume` continues a run stopped by --max-iterations to the design of
    the uninterrupted Python run (1e-12 relative); --resume without --history is refused
    (exit 2, the message names --history)."""
    ref = optimize_fully(_robot())
    h = tmp_path / "h.jsonl"
    args = ["optimize", "robot_2dof", "--method", "fully", "--set", "time.t_end=0.1",
            "--history", str(h), "--json"]
    assert main(args + ["--max-iterations", "2"]) == 1
    capsys.readouterr()
    assert main(args + ["--resume"]) == 0
    import json
    d = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(d["design"], ref.design, rtol=1e-12, atol=0)
    assert d["replayed_simulations"] > 0 and d["simulations"] < ref.simulations
    assert main(["optimize", "robot_2dof", "--resume"]) == 2
    assert "--resume continues the run recorded in --history FILE" in capsys.readouterr().err


def test_ctrl_c_message_names_resume(tmp_path, monkeypatch, capsys):
    """A KeyboardInterrupt in `flexmbs optimize --history FILE` after two records: exit status
    130 and one line on stderr naming FILE and '--resume' (the way to continue); the file holds
    both records."""
    import flexmbs.cli.optimize as command

    def interrupted(problem, x0=None, *, history=None, **kw):
        for k in (1, 2):
            history.write(dict(iteration=k, design=[50.0, 50.0, 50.0, 50.0]))
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "optimize_weakly", interrupted)
    h = tmp_path / "h.jsonl"
    assert main(["optimize", "robot_2dof", "--history", str(h)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(h) in err[0]
    assert "run the same command with --resume" in err[0]
    assert [r["iteration"] for r in read_history(h)] == [1, 2]


def _square(v):
    return {"value": v * v}


def test_batch_progress_on_a_stream_and_callback():
    """run_batch draws its tqdm bar on a given stream (label, 3/3, the describe() text of the
    results so far); a callable progress gets (name, result) of each job; False: nothing."""
    from flexmbs.batch import run_batch
    jobs = {f"j{k}": dict(v=k) for k in range(3)}
    stream = io.StringIO()
    out = run_batch(_square, jobs, workers=1, progress=stream, label="squares",
                    describe=lambda res: f"largest {max(r['value'] for r in res.values())}")
    assert out["j2"] == {"value": 4}
    text = stream.getvalue()
    assert "squares" in text and "3/3" in text and "largest 4" in text
    seen = []
    run_batch(_square, jobs, workers=1, progress=lambda name, res: seen.append((name, res)))
    assert sorted(seen) == [("j0", {"value": 0}), ("j1", {"value": 1}), ("j2", {"value": 4})]


def test_logged_analysis_round_trips_exactly():
    """An analysis as the history logs it (JSON) and as a resumed run replays it: the
    objective, the constraints and the Jacobian come back bit for bit; a Jacobian mostly
    zeros (linear rows of smoothness limits) is logged by its nonzeros, a dense one as is."""
    import json

    from flexmbs.methods.fully import _evaluation_from_log, _log_entry
    from flexmbs.methods.result import jsonable
    p = Problem("robot_2dof", {"time.t_end": 0.02})
    ev = p.evaluate(p.start)
    rng = np.random.default_rng(3)
    sparse = np.zeros((40, 7))
    sparse[rng.integers(0, 40, 12), rng.integers(0, 7, 12)] = rng.normal(size=12)
    for jac in (ev.jacobian, sparse):
        ev.jacobian = jac
        ev.constraint_names = ["c"] * jac.shape[0]
        ev.constraints = np.arange(jac.shape[0], dtype=float)
        entry = json.loads(json.dumps(jsonable(_log_entry(p.start, True, ev))))
        assert isinstance(entry["jacobian"], dict) == (jac is sparse)
        back = _evaluation_from_log(entry, p.start)
        assert np.array_equal(back.jacobian, jac)
        assert np.array_equal(back.constraints, ev.constraints)
        assert back.objective == ev.objective
        # of each response its largest value
        assert all(back.values[k] == np.max(v) for k, v in ev.values.items())


def test_weakly_resume_after_the_move_limits_shrink(tmp_path):
    """The paper's oscillating robot (0.66 s, Table 5; shrink 0.5, the default): the designs
    oscillate from cycle 9 on and the cycles go on with shrinking move limits. A run
    interrupted after cycle 11 and resumed from its history makes the same designs as the
    uninterrupted run to the 12-cycle cap (the limits are rebuilt from the cycles in the file)."""
    p = {"time.t_end": 0.66}
    opts = dict(verify=False, max_cycles=12)
    ref = optimize_weakly(_Counted("robot_2dof", p), options=opts)
    assert ref.details["shrink_cycle"] is not None and ref.details["shrink_cycle"] < 11
    h = tmp_path / "w.jsonl"
    with pytest.raises(_Interrupt):
        optimize_weakly(_Counted("robot_2dof", p), history=h, progress=_stop_at(11),
                        options=opts)
    res = optimize_weakly(_Counted("robot_2dof", p), history=h, resume=True, options=opts)
    assert [r["design"] for r in res.history] == [r["design"] for r in ref.history]
    assert res.details["move_limits"] == ref.details["move_limits"]
