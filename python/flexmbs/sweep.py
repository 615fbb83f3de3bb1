"""Designs of a case run as a batch of jobs (flexmbs.batch.run_batch): one simulation per
design, the job's fingerprint for stored results.

    sweep_jobs           jobs {name: kwargs} of `max_deviation_job`, one per design
    max_deviation_job    mass and largest constrained deviation of one design
    job_fingerprint      what a stored result of a job answers (flexmbs.model.fingerprint)

Example: the deviation over a grid of designs (each point one simulation)

>>> from flexmbs.batch import run_batch
>>> from flexmbs.sweep import max_deviation_job, sweep_jobs
>>> jobs = sweep_jobs("robot_2dof", [[50, 50, 50, 50], [40, 30, 35, 25]])
>>> results = run_batch(max_deviation_job, jobs, workers=2)       # doctest: +SKIP
"""
from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np

from flexmbs.batch import StoredResult
from flexmbs.errors import ModelError
from flexmbs.model.casefile import case_path
from flexmbs.model.fingerprint import canonical, description_digest, fingerprint
from flexmbs.problem import Problem, _description

__all__ = ["sweep_jobs", "max_deviation_job", "MaxDeviationResult", "job_fingerprint"]


#: descriptions' digests by (case file, its modification time and size, overrides)
_DESCRIPTIONS = {}


def job_fingerprint(func, kwargs):
    """The fingerprint (flexmbs.model.fingerprint) of a batch job `func(**kwargs)` whose `case` (a
    case name or path, or a Description or dict) and `overrides` give its description (read
    and resolved here, once per case and overrides: the case file's content counts, not its
    name); the other arguments are its options."""
    kwargs = dict(kwargs)
    case, overrides = kwargs.pop("case", None), kwargs.pop("overrides", None)
    if isinstance(case, (str, bytes)) or hasattr(case, "__fspath__"):
        path = case_path(case)
        stamp = Path(path).stat()
        key = (str(path), stamp.st_mtime_ns, stamp.st_size,
               json.dumps(canonical(overrides or {}), sort_keys=True))
        if key not in _DESCRIPTIONS:
            _DESCRIPTIONS[key] = description_digest(_description(case, overrides or None))
        digest = _DESCRIPTIONS[key]
    else:
        digest = description_digest(_description(case, overrides or None)
                                    if case is not None else None)
    fp = fingerprint(None, getattr(func, "__name__", str(func)), kwargs)
    fp["description"] = digest
    return fp


def sweep_jobs(case, designs, overrides=None):
    """Jobs {name: kwargs} for `max_deviation_job`, one per design (names d0000, d0001, ...)."""
    designs = np.atleast_2d(np.asarray(designs, float))
    return {f"d{k:04d}": dict(case=case, design=d.tolist(), overrides=overrides)
            for k, d in enumerate(designs)}


_local = threading.local()


def _problem(case, overrides):
    """The Problem of (case, overrides), built once per worker thread: a batch of many designs
    of one case (a design-domain map) pays the model and its rigid reference once, not per job.
    Thread-local, so that jobs running in threads of one process never share a Problem."""
    key = (str(case), json.dumps(overrides or {}, sort_keys=True))
    cache = getattr(_local, "problems", None)
    if cache is None:
        cache = _local.problems = {}
    if key not in cache:
        if len(cache) >= 4:
            cache.pop(next(iter(cache)))
        cache[key] = Problem(case, overrides=overrides or None)
    return cache[key]


class MaxDeviationResult(StoredResult):
    """A stored result of `max_deviation_job`."""
    design: list[float]
    mass_kg: float
    max_deviation_m: float
    t_at_max_s: float
    step_at_max: int
    max_violation: float
    limit_m: float | None = None
    deviation_m: list[float] | None = None
    deviation_at_steps_m: list[float] | None = None


def max_deviation_job(case, design, overrides=None, steps=None):
    """Simulate one design of a case (a shipped case's name or a path; `overrides` as
    `flexmbs.problem.Problem`): its mass, the largest constrained deviation (the step-by-step
    maximum of the deviation responses under a constraint), its maximum and its limit, and that
    history at the given 0-based steps (every step if `steps` is 'all')."""
    prob = _problem(case, overrides)
    ev = prob.evaluate(np.asarray(design, float), gradient=False)
    dev = prob.constrained_deviation(ev.values)
    if dev is None:
        raise ModelError(f"case {case!r} constrains no deviation response")
    j = int(np.argmax(dev))
    out = dict(design=list(map(float, design)), mass_kg=prob.design_mass(ev.x, ev.values),
               max_deviation_m=float(dev[j]), t_at_max_s=float(ev.t[j]), step_at_max=j + 1,
               max_violation=ev.max_violation, limit_m=prob.deviation_limit())
    if steps == "all":
        out["deviation_m"] = dev.tolist()
    elif steps is not None:
        out["deviation_at_steps_m"] = [float(dev[s]) for s in steps]
    return out


max_deviation_job.result_schema = MaxDeviationResult
