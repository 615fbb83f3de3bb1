"""Stored results are reused only for the question they answer (flexmbs.model.fingerprint).

A history resumed by `optimize --resume`, a multi-start's stored start, a batch job's stored
result and a study's stored optimization carry the fingerprint of what they answer (the case
description as resolved, the method and its options, the flexmbs version): a resume that
differs is refused naming what differs; a stored result that differs is computed again, with a
warning naming its file.
"""
import json
import shutil
import warnings
from pathlib import Path

import pytest

from flexmbs.batch import run_batch
from flexmbs.cli.main import main
from flexmbs.methods.result import read_history
from flexmbs.model.fingerprint import differences, fingerprint
from flexmbs.problem import Problem
from flexmbs.sweep import job_fingerprint

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("method, stop", [("fully", "--max-iterations"),
                                          ("weakly", "--max-cycles")])
def test_cli_resume_with_another_t_end_is_refused(tmp_path, capsys, method, stop):
    """`optimize robot_2dof --t-end 0.1 --history h` then the same with --t-end 0.05
    --resume: refused (exit 2), the message names the history file and the case's 'time';
    the history is left as it was (one fingerprinted run)."""
    h = tmp_path / "h.jsonl"
    base = ["optimize", "robot_2dof", "--method", method, "--history", str(h), stop, "1"]
    main(base + ["--t-end", "0.1"])
    before = h.read_text()
    assert read_history(h)[0]["fingerprint"]["method"] == method
    capsys.readouterr()
    assert main(base + ["--t-end", "0.05", "--resume"]) == 2
    err = capsys.readouterr().err
    assert str(h) in err and "does not answer this run" in err
    assert "the case description's time" in err
    assert h.read_text() == before


def test_history_without_a_fingerprint_is_refused(tmp_path):
    """A history from before fingerprints (records without one) cannot be resumed: ModelError
    saying it has no fingerprint."""
    from flexmbs.errors import ModelError
    from flexmbs.optimize import optimize_fully
    h = tmp_path / "h.jsonl"
    h.write_text(json.dumps({"iteration": 0, "design": [50.0] * 4}) + "\n")
    with pytest.raises(ModelError, match="no fingerprint"):
        optimize_fully(Problem("robot_2dof", overrides={"time.t_end": 0.1}), history=h,
                       resume=True)


def test_multistart_store_of_another_t_end_is_computed_again(tmp_path):
    """A multi-start store filled with t_end = 0.1 s and reused with t_end = 0.05 s: every
    start runs again (warning naming each start's file and the case's 'time'), and the store
    then holds the new fingerprints; a third run with the same settings reuses them (no
    warning)."""
    from flexmbs.methods.multistart import multistart
    store = tmp_path / "store"
    kw = dict(starts=2, workers=1, store=store, fully=dict(max_iterations=1))
    multistart(Problem("robot_2dof", overrides={"time.t_end": 0.1}), **kw)
    prob = Problem("robot_2dof", overrides={"time.t_end": 0.05})
    with pytest.warns(UserWarning, match=r"2 stored result\(s\) answer another question") as rec:
        multistart(prob, **kw)
    text = " ".join(str(w.message) for w in rec)
    assert "start000.json" in text and "start001.json" in text
    assert "the case description's time" in text
    stored = json.loads((store / "start000.json").read_text())["fingerprint"]
    assert stored["description"] == fingerprint(prob.description, "")["description"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        multistart(prob, **kw)


CALLS = []


def _job(case, overrides=None, k=0):
    CALLS.append(k)
    return {"k": k}


def test_batch_job_reruns_when_its_case_file_or_options_change(tmp_path):
    """run_batch(fingerprints=job_fingerprint): a stored job is reused while its case file and options
    are the same; editing the case file (another t_end) or changing an option (k) runs it
    again, with a warning naming the stored file (and the option: not given before, 1 now)."""
    case = tmp_path / "c.toml"
    shutil.copy(ROOT / "cases" / "robot_2dof.toml", case)
    store = tmp_path / "s"
    CALLS.clear()
    run_batch(_job, {"a": dict(case=str(case))}, workers=1, store=store, fingerprints=job_fingerprint)
    run_batch(_job, {"a": dict(case=str(case))}, workers=1, store=store, fingerprints=job_fingerprint)
    assert CALLS == [0]
    text = case.read_text()
    assert "t_end = 0.65" in text
    case.write_text(text.replace("t_end = 0.65", "t_end = 0.3"))
    with pytest.warns(UserWarning, match=r"a\.json \(the case description's time\)"):
        run_batch(_job, {"a": dict(case=str(case))}, workers=1, store=store,
                  fingerprints=job_fingerprint)
    with pytest.warns(UserWarning, match=r"a\.json \(option k: null -> 1\)"):
        out = run_batch(_job, {"a": dict(case=str(case), k=1)}, workers=1, store=store,
                        fingerprints=job_fingerprint)
    assert CALLS == [0, 0, 1] and out["a"]["k"] == 1


def test_differences_name_what_changed():
    """differences() names the version, the method, each option and each description key
    that differ; a dict that is not a fingerprint has none."""
    d = Problem("robot_2dof").description
    a = fingerprint(d, "fully", {"eps": 0.01})
    b = dict(fingerprint(d, "weakly", {"eps": 0.02}), flexmbs="9")
    assert differences(a, a) == []
    assert differences(a, b)[:3] == [f"flexmbs {a['flexmbs']} -> 9", "method fully -> weakly",
                                     "option eps: 0.01 -> 0.02"]
    assert differences({"k": 1}, a) == [
        "no fingerprint (written before fingerprints, or by another program)"]


def test_shipped_reproduction_answers_the_shipped_study():
    """Every stored optimization of docs/reproduction/jobs answers the run of the shipped
    study it is stored for (its fingerprint is the job's): `reproduce` re-renders the report
    from them without running any."""
    from flexmbs.paper.reproduce import optimization_job
    from flexmbs.paper.study import load_study
    study = load_study()
    store = ROOT / "docs" / "reproduction" / "jobs" / "optimizations"
    for t in study.tables.values():
        for r in t.runs():
            stored = json.loads((store / f"{r.name}.json").read_text()).get("fingerprint")
            assert differences(stored, job_fingerprint(optimization_job, r.job())) == [], r.name


def test_what_cannot_change_an_answer_keeps_the_fingerprint():
    """[solver] memory_limit cannot change an answer (it decides whether a run starts, and
    whether the adjoint checkpoints, with gradients equal to rounding): the fingerprint of
    fourbar with it changed has no difference from the case's own; a changed tol,
    linear_solver or kscale does (the description's 'solver'), and so do the validity checks'
    mode and limits (a result stored under looser checks may be one the current checks
    refuse). A Description and its JSON dict give the same digests."""
    from flexmbs.model.fingerprint import description_digest
    base = fingerprint(Problem("fourbar").description, "fully", {})
    assert differences(base, fingerprint(Problem("fourbar", {"solver.memory_limit": 8e9})
                                         .description, "fully", {})) == []
    for change in ({"solver.tol": 1e-12}, {"solver.linear_solver": "dense"},
                   {"solver.kscale": 1e5, "solver.memory_limit": 8e9},
                   {"solver.validity": "error"},
                   {"solver.drift_warn": 1e-7, "solver.energy_fail": 0.5}):
        assert differences(base, fingerprint(Problem("fourbar", change).description,
                                             "fully", {})) == ["the case description's solver"]
    d = Problem("fourbar", {"solver.tol": 1e-12}).description
    assert description_digest(d) == description_digest(
        d.model_dump(mode="json", by_alias=True, exclude_defaults=True))


def test_fingerprint_records_the_settings_as_they_run():
    """The fingerprint's settings record is the settings that run, keyed as
    SimulationSettings.to_dict(): time.reuse_jacobian = true records newton 'reuse' (what
    Problem.settings runs), linear_solver as 'solver'; every field that can change an answer
    equals the problem's SimulationSettings."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        p = Problem("fourbar", {"time.reuse_jacobian": True, "solver.linear_solver": "dense",
                                "solver.kscale": 1e5})
    record = fingerprint(p.description, "fully", {})["settings"]
    resolved = p.settings.to_dict()
    assert record["newton"] == resolved["newton"] == "reuse"
    for k in ("rho_inf", "start", "newton", "tol", "max_iter", "max_cuts", "solver", "kscale",
              "penalty", "polish"):
        assert record[k] == resolved[k], k
    assert set(record) <= set(resolved)
