"""Running many independent jobs: serially, on local worker processes, or on a Dask cluster.

A job is a call `func(**kwargs)` of a top-level (importable) function whose result is
JSON-serializable. `run_batch` runs a dict of named jobs through an executor and, when a
`store` folder is given, saves each result as `<store>/<name>.json` as soon as it is done,
so that an interrupted batch loses nothing and rerunning the same command skips what is
already there. Every file is written to a temporary name in the same folder, flushed to disk
and renamed (`atomic_open`), so a crash or a full disk never leaves a half-written result
under a result's name; a stored file that cannot be read anyway (truncated by another tool)
is named in a warning and its job is run again.

A local worker process that dies in the middle of a batch (killed by the kernel for lack of
memory, or by a user) breaks the process pool: the jobs that were running or waiting are run
again on a new pool, up to `retries` times (default 2), and the results already finished are
kept. Ctrl-C stops the workers (they ignore SIGINT; the main process ends them) and raises
KeyboardInterrupt in the caller, with every finished job stored. A local worker whose caller
dies without ending it (killed with SIGKILL) exits by itself within about a second
(`_watch_parent`).

Executors:
- ``workers=1``: in this process (serial);
- ``workers=N`` (default: the number of cores): N local worker processes;
- ``dask="tcp://host:8786"``: an existing Dask distributed scheduler (e.g. one started by
  `dask scheduler` or by dask-jobqueue on a cluster); ``dask="local"`` starts a
  `LocalCluster` with one single-threaded worker process per core (`local_cluster`).

Local workers start fresh interpreters ('spawn', default) or fork from one that has imported
flexmbs once (``start_method="forkserver"``); the calling process is never forked. Each worker
(local or Dask) builds the Problem of a case once and reuses it for every design it runs.

Example: `flexmbs.sweep` runs one simulation per design of a case:

>>> from flexmbs.batch import run_batch
>>> from flexmbs.sweep import max_deviation_job, sweep_jobs
>>> jobs = sweep_jobs("robot_2dof", [[50, 50, 50, 50], [40, 30, 35, 25]])
>>> results = run_batch(max_deviation_job, jobs, workers=2)       # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import sys
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict

from flexmbs.errors import ModelError, SimulationError
from flexmbs.files import check_store, read_stored, write_atomic
from flexmbs.model.fingerprint import differences
from flexmbs.progress import Bar

__all__ = ["run_batch", "local_cluster", "Progress", "check_dask", "invalid_result",
           "result_schema", "stale_result", "StoredResult", "job_name", "START_METHODS"]

_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


def job_name(text):
    """A job name (letters, digits, '_', '-', '.') made from any text, e.g. a case file's name
    'my case.toml': every other character becomes '_', and a short hash of the text is added
    when any did, so that two texts never share a name ('my case' -> 'my_case-1b2c3d', not
    'my_case')."""
    import hashlib
    clean = re.sub(r"[^A-Za-z0-9_.\-]", "_", text).strip(".") or "_"
    if clean == text:
        return text
    return f"{clean}-{hashlib.sha1(text.encode('utf-8', 'surrogatepass')).hexdigest()[:6]}"


class Progress:
    """Progress of a batch: a tqdm bar (`flexmbs.progress.Bar`) on stderr when it is a
    terminal (enabled=None), always (True, or a text stream given as `stream`), or never;
    `update(n, postfix)` counts n more finished jobs and shows `postfix` beside the count."""

    def __init__(self, total, label="jobs", enabled=None, stream=None):
        self.total = total
        self.done = 0
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else bool(enabled)
        self._bar = None
        if self.enabled:
            self._bar = Bar(total, label, self.stream)

    def update(self, n=1, postfix=None):
        self.done += n
        if self._bar is None or n <= 0 and postfix is None:
            return
        if postfix is not None:
            self._bar._bar.set_postfix_str(postfix, refresh=False)
        self._bar._bar.update(n)
        if self.done >= self.total:
            self.close()

    def close(self):
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def check_dask(dask, what="dask"):
    """Check a Dask scheduler address once, before any job: None, 'local', or an address
    whose host resolves and that has a port (tcp://host:8786, host:8786, tls://..., inproc://...;
    distributed.comm.resolve_address). ModelError naming `what` and the value otherwise (no
    connection is made here: an unreachable scheduler is found by the first Client)."""
    if dask is None or (isinstance(dask, str) and dask == "local"):
        return dask
    if not isinstance(dask, str) or not dask.strip():
        raise ModelError(f"{what} must be a Dask scheduler address (tcp://HOST:PORT) or "
                         f"'local', got {dask!r}")
    from distributed.comm.addressing import resolve_address
    try:
        resolve_address(dask)
    except (ValueError, TypeError, OSError) as exc:
        reason = getattr(exc, "strerror", None) or exc
        raise ModelError(f"{what} {dask!r} is not a Dask scheduler address ({reason}); "
                         "expected 'local' or SCHEME://HOST:PORT, e.g. tcp://host:8786") from None
    return dask


def invalid_result(value, schema):
    """Why a stored result does not have the content of its job's results (a short phrase
    naming the first wrong key), or None when it does. `schema`: a pydantic model of the
    result (strict: a string is no number), or None (any JSON value)."""
    if schema is None:
        return None
    from pydantic import ValidationError
    if not isinstance(value, dict):
        return f"a {type(value).__name__}, not a result (a JSON object)"
    try:
        schema.model_validate(value)
    except ValidationError as exc:
        errs = exc.errors()
        e = errs[0]
        where = ".".join(map(str, e["loc"])) or "(top level)"
        more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
        got = "" if e["type"] == "missing" else f", got {_short_value(e.get('input'))}"
        return f"key {where!r}: {e['msg']}{got}{more}"
    return None


def _short_value(v, n=40):
    text = repr(v)
    return text if len(text) <= n else text[:n - 3] + "..."


def result_schema(func):
    """The pydantic model of `func`'s results (its attribute ``result_schema``), or None."""
    return getattr(func, "result_schema", None)


def stale_result(value, fp):
    """What differs (flexmbs.model.fingerprint.differences) between a stored result's fingerprint
    and `fp`; [] when it answers `fp`."""
    return differences(value.get("fingerprint") if isinstance(value, dict) else None, fp)


def _save(store, name, value):
    """Write a result as standard JSON: NaN and infinities (not JSON; Python's json writes
    them as bare NaN, which other readers refuse) become null."""
    write_atomic(Path(store) / f"{name}.json",
                 json.dumps(_finite(value), default=_to_json, allow_nan=False))


def _finite(obj):
    """A copy of obj with every non-finite float (Python's or numpy's, in dicts, lists,
    tuples and arrays) replaced by None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


def _to_json(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON-serializable")


def _call(func, kwargs):
    return func(**kwargs)


def _ignore_sigint():
    """Ctrl-C (sent to the whole process group) is handled by the main process, which ends the
    workers; they must not print tracebacks of their own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: How often (seconds) a local worker checks that the process that started the batch lives.
PARENT_POLL_S = 1.0


def _alive(pid):
    """Whether process `pid` exists and is not a zombie (killed, not yet reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return fh.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


def _watch_parent(caller):
    """End this worker (os._exit) when the process that started the batch (`caller`) dies, e.g.
    killed with SIGKILL, which gives it no chance to end its workers: on Linux at once by the
    kernel (prctl PR_SET_PDEATHSIG: SIGTERM when the worker's parent dies -- the caller with
    'spawn', the fork server, which exits with the caller, with 'forkserver'); everywhere by a
    daemon thread that checks every PARENT_POLL_S seconds that the caller lives and that the
    worker's parent is still the one it started with."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)     # 1 = PR_SET_PDEATHSIG
    parent = os.getppid()

    def watch():
        while os.getppid() == parent and _alive(caller):
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    # the parent may have died before prctl: the thread's first check sees it
    threading.Thread(target=watch, name="flexmbs-parent-watch", daemon=True).start()


def _init_worker(caller):
    """Worker initializer: ignore Ctrl-C (`_ignore_sigint`) and exit when the caller, the
    process that started the batch (pid `caller`), dies (`_watch_parent`)."""
    _ignore_sigint()
    _watch_parent(caller)


#: How local worker processes start (run_batch's `start_method`).
START_METHODS = ("spawn", "forkserver")
#: The modules a forkserver imports once, before it forks the workers (with the main module
#: and the job function's module).
FORKSERVER_PRELOAD = ("flexmbs.batch", "flexmbs.problem", "flexmbs.model.kinematics")


def _context(start_method, func):
    """The multiprocessing context of local workers. Neither forks the calling process (whose
    BLAS thread pools may be running): 'spawn' starts a fresh interpreter per worker, which
    imports flexmbs and the job's module itself; 'forkserver' starts one fresh interpreter per
    calling process (multiprocessing's fork server, on the first batch that asks for it), which
    imports them once (`FORKSERVER_PRELOAD`) and forks every worker from that state."""
    if start_method == "spawn":
        return get_context("spawn")
    try:
        ctx = get_context("forkserver")
    except ValueError:
        raise ModelError("start_method 'forkserver' is not available on this platform "
                         f"({sys.platform}); use 'spawn'") from None
    module = getattr(func, "__module__", None)
    extra = [module] if module and module != "__main__" and module not in FORKSERVER_PRELOAD \
        else []
    # a preload that fails to import is skipped by the server; the worker imports it then
    ctx.set_forkserver_preload(["__main__", *FORKSERVER_PRELOAD, *extra])
    return ctx


def _run_pool(func, todo, workers, finish, start_method="spawn"):
    """Run the jobs `todo` on one process pool; return the names whose worker died (the pool
    broke) and so have no result."""
    broken = []
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=_context(start_method, func),
                               initializer=_init_worker, initargs=(os.getpid(),))
    try:
        futs = {pool.submit(_call, func, kw): name for name, kw in todo.items()}
        for fut in as_completed(futs):
            try:
                value = fut.result()
            except BrokenProcessPool:
                broken.append(futs[fut])
                continue
            except Exception as exc:    # noqa: BLE001 - reported after the others finish
                finish(futs[fut], error=exc)
                continue
            try:
                finish(futs[fut], value)
            except Exception as exc:    # noqa: BLE001 - e.g. the store's disk is full
                finish(futs[fut], error=exc)
    except BaseException:
        # Ctrl-C or an error in finish (e.g. a full disk): end the workers now rather than
        # waiting for every queued job
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            with contextlib.suppress(Exception):
                proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    return broken


def _run_isolated(func, todo, workers, finish, start_method="spawn"):
    """Each job on a pool of its own (one worker process), `workers` pools at a time, so that a
    job whose worker dies takes no other job down with it; return the names without a result."""
    lock = threading.Lock()

    def locked_finish(*args, **kwargs):
        with lock:
            finish(*args, **kwargs)

    with ThreadPoolExecutor(max_workers=workers) as threads:
        parts = list(threads.map(lambda item: _run_pool(func, dict([item]), 1, locked_finish,
                                                        start_method), todo.items()))
    return [name for part in parts for name in part]


def run_batch(func, jobs, *, workers=None, dask=None, store=None, progress=None, label="jobs",
              retries=2, describe=None, start_method="spawn", fingerprints=None,
              schema=result_schema):
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
    schema : pydantic model, None or callable, default `result_schema`
        The content a stored result must have to be reused (`invalid_result`; default: the
        job function's attribute ``result_schema``, e.g. `flexmbs.sweep.max_deviation_job`'s): a stored
        file that is JSON but not such a result (``[]``, ``{"foo": 1}``, strings for numbers)
        is not reused: its job runs again, with a warning naming the file and the key.
    fingerprints : dict {name: fingerprint} or callable, optional
        What each job answers (flexmbs.model.fingerprint; a callable is called as
        ``fingerprints(func, kwargs)`` for each job, e.g. `flexmbs.sweep.job_fingerprint`,
        which reads and resolves its case): saved in its result (a dict) under
        'fingerprint'; a stored result whose fingerprint differs, or that has none, is not
        reused: its job runs again, with a warning naming the file and what differs.
    progress : bool, text stream or callable, optional
        Show a progress bar (tqdm) on stderr (True; default: when stderr is a terminal), on
        a given text stream, or not (False); a callable is called as `progress(name,
        result)` when a job finishes (stored results included, first), nothing shown.
    describe : callable, optional
        `describe(results)` ({name: result} of the jobs finished so far) gives the text
        shown beside the bar's count (e.g. the best result so far).
    retries : int, default 2
        Local worker processes: how many times the jobs left without a result by a worker
        process that died (the pool broke) are run again, each on a new pool of its own (so
        that one job that kills its worker cannot take the others down). Jobs that finished
        are kept. (Dask reschedules the tasks of a lost worker itself.)
    start_method : {'spawn', 'forkserver'}, default 'spawn'
        How local worker processes start (`START_METHODS`; not used serially or with Dask).
        'spawn': each worker is a fresh interpreter that imports flexmbs and the job's module
        (about 0.4 s of CPU each). 'forkserver' (POSIX only): one fresh interpreter per calling
        process imports them once (`FORKSERVER_PRELOAD`, the main module and the job's
        module) and forks the workers from it: the import is paid once per process, not per
        worker and per batch, which counts with many workers or many short batches (the
        first batch pays it as 'spawn' does). The fork server is multiprocessing's, one per
        process: one already started (by an earlier batch or other code) is reused with what
        it preloaded. Neither forks the calling process.

    Raises
    ------
    The first exception raised by a job, after the others have finished and been stored;
    SimulationError when worker processes still died after `retries` new pools.
    """
    if not isinstance(jobs, dict):
        raise ModelError("jobs must be a dict {name: kwargs}")
    for name in jobs:
        if not isinstance(name, str) or not _NAME.match(name):
            raise ModelError(f"job name {name!r} must use only letters, digits, '_', '-', '.'")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):
        raise ModelError(f"workers must be a positive integer, got {workers!r}")
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise ModelError(f"retries must be an integer >= 0, got {retries!r}")
    if not isinstance(start_method, str) or start_method not in START_METHODS:
        raise ModelError(f"start_method must be one of {', '.join(map(repr, START_METHODS))}, "
                         f"got {start_method!r}")
    check_dask(dask)
    results = {}
    todo = dict(jobs)
    if schema is result_schema:
        schema = result_schema(func)
    if callable(fingerprints):
        fingerprints = {name: fingerprints(func, kw) for name, kw in jobs.items()}
    if store is not None:
        check_store(store)
        unreadable, stale, invalid = [], [], []
        for name in list(todo):
            path = Path(store) / f"{name}.json"
            if path.exists() or path.is_symlink():
                value = read_stored(path)
                if value is None:
                    unreadable.append(str(path))
                    continue
                why = invalid_result(value, schema)
                if why:
                    invalid.append(f"{path} ({why})")
                    continue
                if fingerprints is not None:
                    diff = stale_result(value, fingerprints[name])
                    if diff:
                        stale.append(f"{path} ({'; '.join(diff)})")
                        continue
                results[name] = value
                del todo[name]
        if unreadable:
            warnings.warn(f"{len(unreadable)} stored result(s) unreadable (truncated or not "
                          f"JSON), their jobs run again: {', '.join(unreadable)}", stacklevel=2)
        if stale:
            warnings.warn(f"{len(stale)} stored result(s) answer another question, their jobs "
                          f"run again: {', '.join(stale)}", stacklevel=2)
        if invalid:
            warnings.warn(f"{len(invalid)} stored result(s) are JSON but not results of "
                          f"{getattr(func, '__name__', 'the job')}, their jobs run again: "
                          f"{', '.join(invalid)}", stacklevel=2)
    callback = progress if callable(progress) and not hasattr(progress, "write") else None
    if callback is not None:
        bar = Progress(len(jobs), label, enabled=False)
    elif hasattr(progress, "write"):
        bar = Progress(len(jobs), label, enabled=True, stream=progress)
    else:
        bar = Progress(len(jobs), label, enabled=progress)
    for name in results:
        if callback is not None:
            callback(name, results[name])
    bar.update(len(results), None if describe is None or not results else describe(results))
    if not todo:
        bar.close()
        return {name: results[name] for name in jobs}
    first_error = None

    def finish(name, value=None, error=None):
        nonlocal first_error
        if error is not None:
            first_error = first_error or error
        else:
            if fingerprints is not None and isinstance(value, dict):
                value = dict(value, fingerprint=fingerprints[name])
            results[name] = value
            if store is not None:
                _save(store, name, value)
            if callback is not None:
                callback(name, value)
        bar.update(1, None if describe is None else describe(results))

    try:
        if dask is not None:
            from distributed import Client, as_completed as dask_completed
            cluster = None
            if dask == "local":
                cluster = local_cluster(workers or os.cpu_count())
                client = Client(cluster)
            else:
                client = Client(dask)
            try:
                futs = {client.submit(_call, func, kw, key=f"flexmbs-{name}-{time.time_ns()}",
                                      pure=False): name
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
            left = dict(todo)
            for attempt in range(retries + 1):
                # after a worker died, each job left runs on a pool of its own: the job that
                # kills its worker is then the only one without a result
                run = _run_pool if attempt == 0 else _run_isolated
                broken = run(func, left, workers or os.cpu_count(), finish, start_method)
                left = {name: left[name] for name in broken}
                if not left:
                    break
                if attempt < retries:
                    warnings.warn(f"a worker process died; {len(left)} job(s) without a result "
                                  f"run again on new workers (retry {attempt + 1} of {retries}): "
                                  f"{', '.join(sorted(left))}", stacklevel=2)
            if left:
                first_error = first_error or SimulationError(
                    f"worker processes died {retries + 1} times (killed, e.g. for lack of "
                    f"memory?); no result for job(s) {', '.join(sorted(left))}")
    finally:
        bar.close()
    if first_error is not None:
        raise first_error
    return {name: results[name] for name in jobs}


#: Dask settings of `local_cluster`: it has no dashboard, so no statistical profiler in the
#: workers (a sample of the running job's stack every 10 ms: ~5-10 % of a job's CPU time), and
#: the event-loop tick (20 ms) and system monitor (0.5 s) that feed the dashboard run rarely:
#: idle, the calling process (client and scheduler) then burns 1.8 % of a core instead of 5.4 %
#: and each worker 0.9 % instead of 2.2 % (measured with 2 workers)
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                        "distributed.admin.tick.interval": "1s",
                        "distributed.admin.system-monitor.interval": "5s"}


def local_cluster(workers):
    """The Dask LocalCluster of ``run_batch(dask="local")``: `workers` single-threaded worker
    processes, no dashboard, `LOCAL_CLUSTER_CONFIG` (its scheduler runs in this process)."""
    import dask.config
    from distributed import LocalCluster
    with dask.config.set(LOCAL_CLUSTER_CONFIG):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None)


class StoredResult(BaseModel):
    """Base of the schemas of stored results: strict types (a string is no number), other
    keys allowed."""
    model_config = ConfigDict(extra="allow", strict=True)

