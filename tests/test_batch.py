"""Batch runs (flexmbs.batch.run_batch): the jobs give the published Table 1 numbers; local
processes (spawned or forked from a fork server) and a Dask LocalCluster give the same results
as a serial run; a store makes reruns skip finished jobs; an error in one job is raised after
the other jobs are stored; faults lose nothing: a worker process killed mid-batch (its jobs run
again), a truncated stored result (named in a warning, recomputed), a full disk while storing
(no half-written file is left under a result's name or read back); and a worker's start-up
(import, first Problem build) loads no scipy."""
import errno
import json
import math
import os
import signal
import time

import numpy as np
import pytest

from flexmbs.batch import run_batch
from flexmbs.errors import ModelError, SimulationError
from flexmbs.files import write_atomic
from flexmbs.sweep import max_deviation_job, sweep_jobs

#: Three robot designs: the paper's Table 1 fully coupled optimum, a design between it and the
#: start, and the start (50 mm). Each is one ~50 ms simulation.
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


def test_serial_results_against_published_numbers(serial):
    """The batch jobs give numbers known independently of the code: the beam mass of every
    design is rho * A * L summed over the four 0.3 m tube elements (A = 0.36 pi/4 p^2, rho =
    2700 kg/m^3, docs/paper-cases.md: m = 229.02 sum p^2), and at the paper's Table 1 optimum
    (d0000) the maximum deviation sits on the 1 mm limit (docs/paper-cases.md: 0.99-1.00 mm at the Table 1
    optima; tolerance 3 %, the spread the paper's stopping test allows between designs), while
    the 50 mm start (stiffer everywhere) stays well inside it."""
    for name, p in zip(sorted(serial), DESIGNS):
        mass = sum(2700.0 * 0.36 * math.pi / 4 * (v * 1e-3) ** 2 * 0.3 for v in p)
        assert serial[name]["mass_kg"] == pytest.approx(mass, rel=1e-9), name
        assert serial[name]["design"] == p
    assert serial["d0000"]["max_deviation_m"] == pytest.approx(1.0e-3, rel=0.03)
    assert serial["d0002"]["max_deviation_m"] < 0.5e-3
    assert max(serial["d0000"]["deviation_at_steps_m"]) <= serial["d0000"]["max_deviation_m"]


def test_local_processes_match_serial(serial, tmp_path):
    """Two local worker processes (spawned) give the serial results, and store every job."""
    res = run_batch(max_deviation_job, _jobs(), workers=2, store=tmp_path, progress=False)
    _assert_same(res, serial)
    assert sorted(p.name for p in tmp_path.glob("*.json")) == [f"{n}.json" for n in sorted(serial)]


def test_forkserver_workers_match_serial(serial):
    """Two local workers forked from a fork server that preloaded flexmbs
    (start_method='forkserver') give the serial results (rtol 1e-12: the same arithmetic)."""
    import multiprocessing
    if "forkserver" not in multiprocessing.get_all_start_methods():
        pytest.skip("no forkserver start method on this platform")
    res = run_batch(max_deviation_job, _jobs(), workers=2, start_method="forkserver",
                    progress=False)
    _assert_same(res, serial)


def test_bad_start_method():
    """An unknown start method is a ModelError naming the argument, the value and the choices
    (before any job runs); 'fork' is refused (it would fork the caller's BLAS threads)."""
    for bad in ("fork", None, 2):
        with pytest.raises(ModelError, match=rf"start_method must be one of 'spawn', "
                                             rf"'forkserver', got {bad!r}"):
            run_batch(count_calls, {"a": dict(log=os.devnull, value=1)}, workers=2,
                      start_method=bad)


def test_worker_start_up_imports_no_scipy():
    """What a batch worker does before its first simulation (import flexmbs.batch, build the
    robot's Problem, whose motors follow the rigid reference: 'reference' laws) loads no scipy
    module: scipy.linalg, .interpolate and .sparse cost a spawned worker about 0.5 s of
    start-up (benchmarks/README.md, batch_scaling.py)."""
    import subprocess
    import sys
    code = ("import sys, flexmbs.batch\n"
            "from flexmbs.problem import Problem\n"
            "p = Problem('robot_2dof', overrides={'bodies.arm1.elements': 8})\n"
            "assert p.mechanism.reference is not None\n"
            "print(sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip().splitlines()[-1]
    assert out == "[]"


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
    ModelError after the two valid jobs have finished and been stored."""
    jobs = sweep_jobs("robot_2dof", [DESIGNS[0], [-1.0, 30.0, 35.0, 25.0], DESIGNS[2]])
    with pytest.raises(ModelError, match="positive"):
        run_batch(max_deviation_job, jobs, workers=workers, store=tmp_path, progress=False)
    assert sorted(p.name for p in tmp_path.glob("*.json")) == ["d0000.json", "d0002.json"]
    # the rerun runs only the failed job again (and fails again)
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.json")}
    with pytest.raises(ModelError, match="positive"):
        run_batch(max_deviation_job, jobs, workers=workers, store=tmp_path, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("*.json")} == before


def test_bad_job_names_and_workers(tmp_path):
    with pytest.raises(ModelError, match="job name"):
        run_batch(count_calls, {"a/b": {}}, workers=1)
    with pytest.raises(ModelError, match="workers"):
        run_batch(count_calls, {"a": dict(log=os.devnull, value=1)}, workers=0)


# ----------------------------------------------------------------------------- faults
def count_or_die(log, value, marker=None, always=False):
    """`count_calls`, except that with `marker` the job kills its own worker process (SIGKILL,
    as the kernel's out-of-memory killer does) the first time it runs (while `marker` does not
    exist), or every time when `always`."""
    if marker is not None and (always or not os.path.exists(marker)):
        with open(marker, "w") as fh:
            fh.write("killed\n")
        os.kill(os.getpid(), signal.SIGKILL)
    return count_calls(log, value)


def test_killed_worker_is_retried_and_nothing_is_lost(tmp_path):
    """A worker killed in the middle of a batch (2 local processes): the batch finishes with
    every result (2 * value), the killed job ran again, every result is stored (and nothing
    else: no temporary file), and a rerun computes nothing."""
    store = tmp_path / "store"
    log = tmp_path / "calls.txt"
    jobs = {f"j{k}": dict(log=str(log), value=k) for k in range(5)}
    jobs["j2"]["marker"] = str(tmp_path / "marker")
    with pytest.warns(UserWarning, match=r"worker process died.*j2"):
        res = run_batch(count_or_die, jobs, workers=2, store=store, progress=False)
    assert (tmp_path / "marker").exists()                     # the worker was killed once
    assert res == {f"j{k}": {"value": 2 * k} for k in range(5)}
    assert {p.stem: json.loads(p.read_text()) for p in store.glob("*.json")} == res
    assert sorted(os.listdir(store)) == sorted(f"{n}.json" for n in res)
    calls = log.read_text().split()
    assert sorted(set(calls)) == ["0", "1", "2", "3", "4"]   # each job at least once
    assert calls.count("2") == 1                              # j2 finished on its retry only
    again = run_batch(count_or_die, jobs, workers=2, store=store, progress=False)
    assert again == res and log.read_text().split() == calls


def test_worker_that_always_dies_gives_up_after_the_retries(tmp_path):
    """A job whose worker dies on every attempt: after `retries` new pools the batch raises
    SimulationError naming the job; the other job's result is stored."""
    log = tmp_path / "calls.txt"
    jobs = {"bad": dict(log=str(log), value=0, marker=str(tmp_path / "m"), always=True),
            "ok": dict(log=str(log), value=1)}
    with pytest.raises(SimulationError, match=r"died 2 times.*bad"), \
            pytest.warns(UserWarning, match="worker process died"):
        run_batch(count_or_die, jobs, workers=2, store=tmp_path / "s", progress=False, retries=1)
    assert json.loads((tmp_path / "s" / "ok.json").read_text()) == {"value": 2}
    assert os.listdir(tmp_path / "s") == ["ok.json"]


def test_truncated_stored_result_is_named_and_recomputed(tmp_path):
    """A stored result cut short (e.g. by a crash of another tool or a copy) is not read back
    as a result: the warning names the file, that job alone runs again, its file is whole."""
    log = tmp_path / "calls.txt"
    store = tmp_path / "store"
    jobs = {f"j{k}": dict(log=str(log), value=k) for k in range(3)}
    run_batch(count_calls, jobs, workers=1, store=store, progress=False)
    (store / "j1.json").write_text('{"val')
    with pytest.warns(UserWarning, match=r"j1\.json"):
        res = run_batch(count_calls, jobs, workers=1, store=store, progress=False)
    assert res == {f"j{k}": {"value": 2 * k} for k in range(3)}
    assert log.read_text().split() == ["0", "1", "2", "1"]
    assert json.loads((store / "j1.json").read_text()) == {"value": 2}


def test_full_disk_leaves_no_half_written_result(tmp_path, monkeypatch):
    """The disk fills up while results are stored (fsync reports ENOSPC after part of the file
    was written): the batch raises the OSError, the result stored earlier is byte-identical,
    no file of the failed jobs (complete or temporary) is left, and once there is room again the
    rerun computes exactly the jobs that were not stored."""
    log = tmp_path / "calls.txt"
    store = tmp_path / "store"
    jobs = {f"j{k}": dict(log=str(log), value=k) for k in range(3)}
    run_batch(count_calls, {"j0": jobs["j0"]}, workers=1, store=store, progress=False)
    before = (store / "j0.json").read_bytes()
    written = []

    def full_disk(fd):
        written.append(os.fstat(fd).st_size)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        run_batch(count_calls, jobs, workers=1, store=store, progress=False)
    monkeypatch.undo()
    assert written and all(n > 0 for n in written)      # partial data had reached the temp file
    assert (store / "j0.json").read_bytes() == before
    assert os.listdir(store) == ["j0.json"]
    res = run_batch(count_calls, jobs, workers=1, store=store, progress=False)
    assert res == {f"j{k}": {"value": 2 * k} for k in range(3)}
    assert log.read_text().split() == ["0", "1", "2", "1", "2"]


def test_write_atomic_keeps_the_previous_file_when_the_rename_fails(tmp_path, monkeypatch):
    """write_atomic: a failure at the last moment (os.replace, e.g. ENOSPC on a network file
    system) leaves the previous complete file untouched and no temporary file behind."""
    f = tmp_path / "result.json"
    write_atomic(f, '{"complete": true}')

    def fail(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError):
        write_atomic(f, '{"complete": false, "long": "' + "x" * 10000 + '"}')
    monkeypatch.undo()
    assert json.loads(f.read_text()) == {"complete": True}
    assert os.listdir(tmp_path) == ["result.json"]
