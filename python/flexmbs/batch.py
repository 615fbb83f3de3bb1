"""Running many independent jobs: serially, on local worker processes, or on a Dask cluster.

A job is a call `func(**kwargs)` of a top-level (importable) function whose result is
JSON-serializable. `run_batch` runs a dict of named jobs through an executor and, when a
`store` folder is given, saves each result as `<store>/<name>.json` as soon as it is done,
so that an interrupted batch loses nothing and rerunning the same command skips what is
already there.

Executors:
- ``workers=1``: in this process (serial);
- ``workers=N`` (default: the number of cores): N local worker processes;
- ``dask="tcp://host:8786"``: an existing Dask distributed scheduler (e.g. one started by
  `dask scheduler` or by dask-jobqueue on a cluster); ``dask="local"`` starts a
  `LocalCluster` with one single-threaded worker process per core.

Example: the deviation over a grid of designs (each point one simulation)

>>> from flexmbs.batch import run_batch, sweep_jobs, max_deviation_job
>>> jobs = sweep_jobs("robot_2dof", [[50, 50, 50, 50], [40, 30, 35, 25]])
>>> results = run_batch(max_deviation_job, jobs, workers=2)       # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["run_batch", "sweep_jobs", "max_deviation_job", "Progress"]

_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


class Progress:
    """A one-line progress bar on stderr (only when stderr is a terminal, or forced)."""

    def __init__(self, total, label="jobs", enabled=None, stream=None):
        self.total = total
        self.done = 0
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self.t0 = time.perf_counter()

    def update(self, n=1):
        self.done += n
        if not self.enabled:
            return
        frac = self.done / max(self.total, 1)
        bar = "#" * int(30 * frac)
        el = time.perf_counter() - self.t0
        eta = el / frac - el if frac > 0 else 0.0
        self.stream.write(f"\r{self.label}: [{bar:<30}] {self.done}/{self.total} "
                          f"{el:6.1f} s elapsed, ~{eta:5.1f} s left")
        if self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()


def _save(store, name, value):
    path = Path(store) / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(value, default=_to_json))
    os.replace(tmp, path)


def _to_json(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON-serializable")


def _call(func, kwargs):
    return func(**kwargs)


def run_batch(func, jobs, *, workers=None, dask=None, store=None, progress=None, label="jobs"):
    """Run `func(**jobs[name])` for every name; return {name: result}.

    Parameters
    ----------
    func : callable
        A top-level function (picklable); its results must be JSON-serializable when
        `store` is given.
    jobs : dict {name: kwargs}
        Names may contain letters, digits, '_', '-', '.'.
    workers : int, optional
        1: serial in this process; N > 1: N local worker processes (default: os.cpu_count()).
    dask : str, optional
        Address of a Dask scheduler, or 'local' for a LocalCluster. Overrides `workers`
        (which then sets the number of local Dask workers).
    store : path, optional
        Folder where each result is saved as it finishes; names already stored are not
        run again (their stored result is returned).
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).

    Raises
    ------
    The first exception raised by a job, after the others have finished and been stored.
    """
    if not isinstance(jobs, dict):
        raise ModelError("jobs must be a dict {name: kwargs}")
    for name in jobs:
        if not isinstance(name, str) or not _NAME.match(name):
            raise ModelError(f"job name {name!r} must use only letters, digits, '_', '-', '.'")
    results = {}
    todo = dict(jobs)
    if store is not None:
        Path(store).mkdir(parents=True, exist_ok=True)
        for name in list(todo):
            path = Path(store) / f"{name}.json"
            if path.exists():
                results[name] = json.loads(path.read_text())
                del todo[name]
    bar = Progress(len(jobs), label, enabled=progress)
    bar.update(len(results))
    if not todo:
        return {name: results[name] for name in jobs}
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ModelError(f"workers must be a positive integer, got {workers!r}")
    first_error = None

    def finish(name, value=None, error=None):
        nonlocal first_error
        if error is not None:
            first_error = first_error or error
        else:
            results[name] = value
            if store is not None:
                _save(store, name, value)
        bar.update()

    if dask is not None:
        from distributed import Client, LocalCluster, as_completed as dask_completed
        cluster = None
        if dask == "local":
            cluster = LocalCluster(n_workers=workers or os.cpu_count(), threads_per_worker=1,
                                   processes=True, dashboard_address=None)
            client = Client(cluster)
        else:
            client = Client(dask)
        try:
            futs = {client.submit(_call, func, kw, key=f"flexmbs-{name}-{time.time_ns()}", pure=False): name
                    for name, kw in todo.items()}
            for fut in dask_completed(futs):
                try:
                    finish(futs[fut], fut.result())
                except Exception as exc:    # noqa: BLE001 - reported after the others finish
                    finish(futs[fut], error=exc)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    elif (workers or os.cpu_count() or 1) == 1 or len(todo) == 1:
        for name, kw in todo.items():
            try:
                finish(name, func(**kw))
            except Exception as exc:    # noqa: BLE001
                finish(name, error=exc)
    else:
        # 'spawn': no fork of a process whose BLAS thread pools are running
        with ProcessPoolExecutor(max_workers=workers or os.cpu_count(),
                                 mp_context=get_context("spawn")) as pool:
            futs = {pool.submit(_call, func, kw): name for name, kw in todo.items()}
            for fut in as_completed(futs):
                try:
                    finish(futs[fut], fut.result())
                except Exception as exc:    # noqa: BLE001
                    finish(futs[fut], error=exc)
    if first_error is not None:
        raise first_error
    return {name: results[name] for name in jobs}


def sweep_jobs(case, designs, **overrides):
    """Jobs {name: kwargs} for `max_deviation_job`, one per design (names d0000, d0001, ...)."""
    designs = np.atleast_2d(np.asarray(designs, float))
    return {f"d{k:04d}": dict(case=case, design_mm=d.tolist(), overrides=overrides)
            for k, d in enumerate(designs)}


def max_deviation_job(case, design_mm, overrides=None, steps=None):
    """Simulate one design of a case (by name or path): mass, max deviation, and the
    deviation at the given 0-based steps (all steps if `steps` is 'all')."""
    from flexmbs.cases import load_case
    c = load_case(case, **(overrides or {}))
    res = c.simulate(np.asarray(design_mm, float))
    out = dict(design_mm=list(map(float, design_mm)), mass_kg=float(res.mass),
               max_deviation_m=float(res.max_deviation), t_at_max_s=float(res.t_at_max))
    if steps == "all":
        out["deviation_m"] = res.deviation.tolist()
    elif steps is not None:
        out["deviation_at_steps_m"] = [float(res.deviation[s]) for s in steps]
    return out
