"""Batch runs (flexmbs.batch.run_batch): local processes and a Dask LocalCluster give the same
results as a serial run; a store makes reruns skip finished jobs; an error in one job is
raised after the other jobs are stored."""
import json
import os
import time

import numpy as np
import pytest

from flexmbs.batch import max_deviation_job, run_batch, sweep_jobs
from flexmbs.errors import CaseError, ModelError

#: Three robot designs around the Table 1 optimum; deviation at steps 200 and 1301 (0-based 199,
#: 1300) and the maximum. Each is one ~50 ms simulation.
DESIGNS = [[39.35, 28.25, 35.14, 24.91], [45.0, 30.0, 35.0, 25.0], [50.0, 50.0, 50.0, 50.0]]


def _jobs():
    jobs = sweep_jobs("robot_2dof", DESIGNS)
    for kw in jobs.values():
        kw["steps"] = [199, 1300]
    return jobs


@pytest.fixture(scope="module")
def serial():
    return run_batch(max_deviation_job, _jobs(), workers=1, progress=False)


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].keys() == b[name].keys()
        for key in a[name]:
            np.testing.assert_allclose(a[name][key], b[name][key], rtol=1e-12, atol=0,
                                       err_msg=f"{name}: {key}")


def test_serial_results_are_the_simulations(serial):
    """The serial batch returns, per job, what Case.simulate gives for that design (the job is
    a plain call), and the designs differ (the comparison below is not trivial)."""
    from flexmbs.cases import load_case
    c = load_case("robot_2dof")
    r = c.simulate(DESIGNS[1])
    out = serial["d0001"]
    assert out["max_deviation_m"] == pytest.approx(r.max_deviation, rel=1e-12)
    assert out["deviation_at_steps_m"] == pytest.approx(r.deviation[[199, 1300]], rel=1e-12)
    maxima = [serial[n]["max_deviation_m"] for n in sorted(serial)]
    assert len(set(np.round(maxima, 9))) == 3


def test_local_processes_match_serial(serial, tmp_path):
    """Two local worker processes (spawned) give the serial results, and store every job."""
    res = run_batch(max_deviation_job, _jobs(), workers=2, store=tmp_path, progress=False)
    _assert_same(res, serial)
    assert sorted(p.name for p in tmp_path.glob("*.json")) == [f"{n}.json" for n in sorted(serial)]


def test_dask_local_cluster_matches_serial(serial, tmp_path):
    """A real Dask LocalCluster (2 single-threaded worker processes) gives the serial results."""
    pytest.importorskip("distributed")
    res = run_batch(max_deviation_job, _jobs(), workers=2, dask="local", store=tmp_path,
                    progress=False)
    _assert_same(res, serial)
    stored = {p.stem: json.loads(p.read_text()) for p in tmp_path.glob("*.json")}
    _assert_same(stored, serial)


def count_calls(log, value):
    """A job that appends one line to `log` per call (works across processes) and returns
    {'value': 2 * value}."""
    with open(log, "a") as fh:
        fh.write(f"{value}\n")
    return {"value": 2 * value}


def test_rerun_skips_stored_jobs(tmp_path):
    """A rerun with the same store calls the function only for the new jobs and returns the
    stored results of the others; stored files are not rewritten."""
    log = tmp_path / "calls.txt"
    store = tmp_path / "store"
    jobs = {f"j{k}": dict(log=str(log), value=k) for k in range(3)}
    first = run_batch(count_calls, jobs, workers=1, store=store, progress=False)
    assert first == {f"j{k}": {"value": 2 * k} for k in range(3)}
    assert log.read_text().split() == ["0", "1", "2"]
    mtimes = {p.name: p.stat().st_mtime_ns for p in store.glob("*.json")}
    time.sleep(0.02)
    jobs["j3"] = dict(log=str(log), value=3)
    second = run_batch(count_calls, jobs, workers=2, store=store, progress=False)
    assert second == {f"j{k}": {"value": 2 * k} for k in range(4)}
    assert log.read_text().split() == ["0", "1", "2", "3"]          # only j3 ran
    for name, t in mtimes.items():
        assert (store / name).stat().st_mtime_ns == t
    # and nothing at all runs when everything is stored
    third = run_batch(count_calls, jobs, workers=2, store=store, progress=False)
    assert third == second and len(log.read_text().split()) == 4


@pytest.mark.parametrize("workers", [1, 2])
def test_error_is_raised_after_the_other_jobs_are_stored(tmp_path, workers):
    """A job with an invalid design (a negative diameter) fails; the batch raises its
    CaseError after the two valid jobs have finished and been stored."""
    jobs = sweep_jobs("robot_2dof", [DESIGNS[0], [-1.0, 30.0, 35.0, 25.0], DESIGNS[2]])
    with pytest.raises(CaseError):
        run_batch(max_deviation_job, jobs, workers=workers, store=tmp_path, progress=False)
    assert sorted(p.name for p in tmp_path.glob("*.json")) == ["d0000.json", "d0002.json"]
    # the rerun runs only the failed job again (and fails again)
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.json")}
    with pytest.raises(CaseError):
        run_batch(max_deviation_job, jobs, workers=workers, store=tmp_path, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.json")} == before


def test_bad_job_names_and_workers(tmp_path):
    with pytest.raises(ModelError, match="job name"):
        run_batch(count_calls, {"a/b": {}}, workers=1)
    with pytest.raises(ModelError, match="workers"):
        run_batch(count_calls, {"a": dict(log=os.devnull, value=1)}, workers=0)
