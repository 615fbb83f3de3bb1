"""Many designs: one batch of designs serially, on 2 local worker processes and on Dask.

The batch: 64 designs of the robot (cases/robot_2dof.toml, 1300 steps) with 128 elements per
arm (about 0.45 s each on one core), each `flexmbs.sweep.max_deviation_job` (one simulation
without gradients: the mass and the largest constrained deviation), run through
`flexmbs.batch.run_batch` exactly as a user runs it, side by side in one process:

1. ``workers=1``: serially in this process (flexmbs already imported, as in a user's script);
2. ``workers=2``: two local worker processes, each a fresh interpreter (``start_method='spawn'``,
   the default) that imports flexmbs and builds the Problem once;
3. ``workers=2, start_method='forkserver'``: the workers are forked from a fork server started
   by this batch, which imported flexmbs once;
4. ``dask=<address>``: `flexmbs.batch.local_cluster(2)` (the LocalCluster of ``dask="local"``:
   2 single-threaded worker processes), started before the timing (its start-up is printed
   apart: a cluster is started once for many batches).

Printed per run: the wall time (what the user waits for) and its ratio to the serial run (the
target is >= 1.8 on 2 cores), then where the time goes:
- start-up: from the call of run_batch to each worker's first job (process start, imports,
  receiving the job), mean over the workers; first build: the Problem built by each worker's
  first job (model, rigid reference; the first time also imports what only a build needs);
- steady state: a job's mean wall and CPU time once its worker's Problem is built (process CPU,
  which counts the worker's own threads: Dask's event loop; the job thread's alone in brackets);
- busy share: sum of the jobs' wall times / (workers x wall): below 1 by start-up and idle
  time; CPU share: sum of the jobs' process CPU / (workers x wall): 1 when each worker had a
  core to itself, less when the machine is shared (then the ratio says how much of the 2 cores
  the batch got, not how it scales);
- after start-up: (serial wall - its start-up) / (wall - start-up), what a longer batch of the
  same jobs tends to;
- caller CPU: the CPU time of the calling process during the batch (parallel runs): sending
  jobs and receiving results, and for Dask the client and the LocalCluster's scheduler, which
  run in it and compete with the workers for the cores.
Every run's deviations are compared with the serial ones (max |dev - serial|, 0 expected).

The machine's speed drifts by up to +-30 % over minutes (VM neighbours): one serial run
against one parallel run minutes later measured 1.52 to 2.42 (2-core reference machine), the steady job's
CPU time moving 0.39 <-> 0.50 s between the runs. ``--rounds R`` therefore also alternates
R serial and R default parallel (spawn) runs, each round's speed-up against the serial run
just before it, and the ratio of the summed wall times (what drift does not bias).
Before the runs: what a fresh interpreter pays to import flexmbs.batch (CPU, best of 3), with
the two costs a development checkout adds to it and an installed wheel does not (sources
compiled at every start when PYTHONDONTWRITEBYTECODE is set; the rebuild check of an editable
install). The load average is printed at the start and the end: on a shared machine the
ratios are only as good as the load allows.

`python benchmarks/batch_scaling.py [--designs 64] [--elements 128] [--no-dask]
[--rounds R]` (about 90 s on an idle 2-core machine, and some 40 s per round); not part of
run.py's default list.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import resource
import subprocess
import sys
import time

import numpy as np


def timed_job(case, design, overrides=None):
    """max_deviation_job, timed: the Problem build apart (non-zero on a worker's first job of
    the case), the whole job's wall, process CPU and thread CPU time, its start (time.time(),
    comparable between processes) and the worker's process id."""
    from flexmbs import batch
    start = time.time()
    t0, c0, h0 = time.perf_counter(), time.process_time(), time.thread_time()
    prob = batch._problem(case, overrides)          # the worker's cached Problem (built once)
    built = not getattr(prob, "_batch_scaling_seen", False)
    prob._batch_scaling_seen = True
    build = time.perf_counter() - t0
    out = batch.max_deviation_job(case, design, overrides)
    out.update(start=start, built=built, build_s=build if built else 0.0,
               job_s=time.perf_counter() - t0, job_cpu_s=time.process_time() - c0,
               job_thread_s=time.thread_time() - h0, pid=os.getpid())
    return out


def _jobs(n, elements):
    rng = np.random.default_rng(16)
    designs = rng.uniform(30.0, 60.0, size=(n, 4))
    ov = {"bodies.arm1.elements": elements, "bodies.arm2.elements": elements}
    return {f"d{k:03d}": dict(case="robot_2dof", design=d.tolist(), overrides=ov)
            for k, d in enumerate(designs)}


def _run(label, workers, jobs, **kw):
    from flexmbs import batch
    batch._local.__dict__.clear()         # no Problem cached in this process from a prior run
    t_call = time.time()
    t0, c0 = time.perf_counter(), time.process_time()
    res = batch.run_batch(timed_job, jobs, workers=workers, progress=False, **kw)
    wall, caller = time.perf_counter() - t0, time.process_time() - c0
    rs = list(res.values())
    pids = sorted({r["pid"] for r in rs})
    startup = np.mean([min(r["start"] for r in rs if r["pid"] == p) - t_call for p in pids])
    builds = [r["build_s"] for r in rs if r["built"]]
    steady = [r for r in rs if not r["built"]]
    return dict(label=label, wall=wall, caller=caller, workers=workers, processes=len(pids),
                startup=startup,
                build=np.mean(builds) if builds else 0.0,
                steady_s=np.mean([r["job_s"] for r in steady]),
                steady_cpu=np.mean([r["job_cpu_s"] for r in steady]),
                steady_thread=np.mean([r["job_thread_s"] for r in steady]),
                busy=sum(r["job_s"] for r in rs) / (workers * wall),
                cpu_share=sum(r["job_cpu_s"] for r in rs) / (workers * wall),
                results={k: r["max_deviation_m"] for k, r in res.items()})


def _import_cost(repeats=3):
    """CPU seconds (user + system) of `python -c "import flexmbs.batch"`, best of `repeats`."""
    best = np.inf
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([sys.executable, "-c", "import flexmbs.batch"], check=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        best = min(best, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--designs", type=int, default=64)
    ap.add_argument("--elements", type=int, default=128, help="elements per arm")
    ap.add_argument("--no-dask", action="store_true")
    ap.add_argument("--rounds", type=int, default=0,
                    help="alternate this many serial / 2-process (spawn) runs after the table")
    args = ap.parse_args(argv)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from common import format_table, machine_summary
    print(f"batch scaling: {machine_summary()}")
    importlib.import_module("flexmbs.batch")    # the serial run's process has flexmbs imported
    notes = []
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        notes.append("PYTHONDONTWRITEBYTECODE is set: every interpreter compiles flexmbs's "
                     "sources again")
    if any(m.endswith("_editable_loader") for m in sys.modules):
        notes.append("editable install: every interpreter runs meson-python's rebuild check "
                     "(ninja -n) when it imports flexmbs")
    print(f"a fresh interpreter importing flexmbs.batch: {_import_cost():.2f} s CPU (best of 3)"
          + "".join(f"\n  ({n})" for n in notes))
    jobs = _jobs(args.designs, args.elements)
    runs = [_run("serial (workers=1)", 1, jobs),
            _run("2 local processes, spawn (default)", 2, jobs),
            _run("2 local processes, forkserver", 2, jobs, start_method="forkserver")]
    if not args.no_dask:
        from flexmbs.batch import local_cluster
        if importlib.util.find_spec("distributed") is None:
            print("dask.distributed is not installed (pip install flexmbs[batch]): no Dask run")
        else:
            t0 = time.perf_counter()
            cluster = local_cluster(2)
            start = time.perf_counter() - t0
            try:
                r = _run(f"Dask LocalCluster, 2 workers (cluster start {start:.1f} s apart)", 2,
                         jobs, dask=cluster.scheduler_address)
                runs.append(r)
            finally:
                cluster.close()
    base = runs[0]
    for r in runs[1:]:
        r["diff"] = max(abs(r["results"][k] - base["results"][k]) for k in jobs)
    rows = [[r["label"], r["processes"], r["wall"], base["wall"] / r["wall"], r["startup"],
             r["build"], r["steady_s"], f"{r['steady_cpu']:.3f} ({r['steady_thread']:.3f})",
             r["busy"], r["cpu_share"],
             (base["wall"] - base["startup"]) / (r["wall"] - r["startup"]),
             r["caller"] if r is not base else None, r.get("diff")] for r in runs]
    print(format_table(["run", "processes", "wall s", "speed-up", "start-up s", "first build s",
                        "steady job s", "steady job CPU s (thread)", "busy share", "CPU share",
                        "speed-up after start-up", "caller CPU s", "max |dev - serial| m"],
                       rows,
                       title=f"\n{len(jobs)} designs of robot_2dof, {args.elements} elements per "
                             "arm, 1300 steps, one simulation each"))
    if args.rounds > 0:
        pairs = []
        for k in range(args.rounds):
            ser = _run("serial", 1, jobs)
            par = _run("spawn", 2, jobs)
            pairs.append((ser, par))
            print(f"round {k + 1}: serial {ser['wall']:.2f} s (steady job CPU "
                  f"{ser['steady_cpu']:.3f} s), 2 processes {par['wall']:.2f} s "
                  f"({par['steady_cpu']:.3f} s): speed-up {ser['wall'] / par['wall']:.3f}",
                  flush=True)
        total = sum(s_["wall"] for s_, _ in pairs) / sum(p_["wall"] for _, p_ in pairs)
        each = [s_["wall"] / p_["wall"] for s_, p_ in pairs]
        print(f"alternating rounds: speed-up of the summed wall times {total:.3f}; per round "
              f"min {min(each):.3f}, median {float(np.median(each)):.3f}, max {max(each):.3f}")
    print(f"load average at the end: {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
