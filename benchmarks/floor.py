"""flexmbs's default run against its own linear-algebra floor, optionally beside another checkout.

The robot of docs/paper-cases.md (p = 50 mm, h = 5e-4 s, 1300 steps, static start, the tip
stored) with 2, 8, 32, 128 quadratic elements per arm, run by `flexmbs.analysis.simulate` with its
defaults (solver 'auto' = KLU, newton 'auto'). Per size:

- the CPU time of the call (minimum over the repeats) and its Python set-up (total minus
  the compiled run, flexmbs.core.simulate_arrays, median; where_time_goes.core_timer);
- the floor: factorizations x klu_refactor + solves (Newton and static iterations) x
  klu_solve, each timed alone with the same libKLU through ctypes on the model's iteration
  matrix (where_time_goes.klu_costs, with KLU's default row scaling; flexmbs refactors
  without it), and the ratio time / floor;
- with --perf, the shares of the samples of the timed loop (where_time_goes.perf_profile).

With --compare DIR (another checkout with its own .venv, e.g. a worktree of an older commit),
the two checkouts' flexmbs run in alternating child processes (`--rounds` alternations; the
minimum of each over them), with these benchmark helpers, side by side; the last column is the
largest difference of the two tip histories (m).

Usage:
    python benchmarks/floor.py [--nel 2 8 32 128] [--repeat 5] [--compare DIR] [--rounds 3]
                               [--perf]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

if __name__ == "__main__":
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np

BENCH = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, BENCH)
from common import format_table, machine_summary  # noqa: E402
from flexmbs.analysis.settings import SimulationSettings  # noqa: E402

H = 5e-4
STEPS = 1300


def measure(nels, repeats):
    """{nel: numbers} of the default run of the flexmbs this interpreter imports."""
    import flexmbs as fx
    from common import robot_flexmbs
    from where_time_goes import core_timer, iteration_matrix, klu_costs
    out = {}
    for nel in nels:
        model, _, a2 = robot_flexmbs(nel)
        model.compile()
        model.pattern("klu")
        klu = klu_costs(model, iteration_matrix(model, h=H))
        fx.simulate(model, STEPS * H, H,
                    settings=SimulationSettings(start="static", store=[a2.last]))      # warm-up
        cpus, pys = [], []
        with core_timer() as ct:
            for _ in range(repeats):
                n0 = len(ct.calls)
                c0 = time.process_time()
                res = fx.simulate(model, STEPS * H, H,
                                  settings=SimulationSettings(start="static", store=[a2.last]))
                cpu = time.process_time() - c0
                cpus.append(cpu)
                pys.append(cpu - sum(c for _, c in ct.calls[n0:]))
        st = res.stats
        solves = st["newton_iterations"] + st["static_iterations"]
        floor = st["factorizations"] * klu["factor"] + solves * klu["solve"]
        out[nel] = dict(cpu=min(cpus), python=float(np.median(pys)), floor=floor,
                        unknowns=st["unknowns"], steps=st["steps"], solves=solves,
                        factorizations=st["factorizations"],
                        residuals=st["residual_evaluations"], klu_factor=klu["factor"],
                        klu_solve=klu["solve"], tip=np.asarray(res.position(a2.last)).tolist())
    return out


def _commit(root):
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                               capture_output=True, timeout=10).stdout.strip() or "?"
    except (OSError, subprocess.SubprocessError):
        return "?"


def _child(python, nels, repeats):
    cmd = [python, os.path.abspath(__file__), "--child", "--repeat", str(repeats), "--nel",
           *map(str, nels)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, check=True)
    return {int(k): v for k, v in json.loads(proc.stdout.splitlines()[-1]).items()}


def _merge(runs):
    """Per size: the minimum CPU time and floor over alternations, the rest of the last."""
    best = {}
    for run in runs:
        for nel, r in run.items():
            b = best.setdefault(nel, dict(r))
            b["cpu"] = min(b["cpu"], r["cpu"])
            b["floor"] = min(b["floor"], r["floor"])
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nel", type=int, nargs="+", default=[2, 8, 32, 128])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--compare", help="another checkout (with .venv) to run beside this one")
    ap.add_argument("--rounds", type=int, default=3, help="alternations with --compare")
    ap.add_argument("--perf", action="store_true", help="profile shares of the timed loop")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.nel, args.repeat)))
        return 0
    root = os.path.dirname(BENCH)
    sides = [("this", sys.executable, root)]
    if args.compare:
        other = os.path.abspath(args.compare)
        sides.insert(0, ("other", os.path.join(other, ".venv", "bin", "python"), other))
    print(machine_summary())
    runs = {name: [] for name, _, _ in sides}
    for _ in range(args.rounds if args.compare else 1):
        for name, python, _ in sides:
            runs[name].append(_child(python, args.nel, args.repeat))
    best = {name: _merge(r) for name, r in runs.items()}
    this = best["this"]
    headers = ["el/arm", "unknowns", "solves/step", "fact/step", "res/step", "KLU fact us",
               "KLU solve us", "floor ms"]
    labels = [f"{name} ({_commit(r)})" for name, _, r in sides]
    for lab in labels:
        headers += [f"{lab} ms", f"{lab} /floor", f"{lab} Python ms"]
    if args.compare:
        headers.append("max |tip this - other| m")
    rows = []
    for nel in args.nel:
        r = this[nel]
        floor = min(best[name][nel]["floor"] for name, _, _ in sides)
        row = [nel, r["unknowns"], r["solves"] / r["steps"], r["factorizations"] / r["steps"],
               r["residuals"] / r["steps"], r["klu_factor"] * 1e6, r["klu_solve"] * 1e6, floor * 1e3]
        for name, _, _ in sides:
            b = best[name][nel]
            row += [b["cpu"] * 1e3, b["cpu"] / floor, b["python"] * 1e3]
        if args.compare:
            row.append(float(np.max(np.abs(np.asarray(this[nel]["tip"])
                                           - np.asarray(best["other"][nel]["tip"])))))
        rows.append(row)
    print(format_table(headers, rows, title=(
        f"flexmbs.analysis.simulate defaults against the KLU floor (robot, h = {H:g} s, {STEPS} steps; CPU "
        f"time, min of {args.repeat} repeats" + (f" x {args.rounds} alternations" if args.compare
                                                  else "") + "; floor: min over the runs)")))
    if args.perf:
        from where_time_goes import perf_available, perf_profile
        if not perf_available():
            print("perf not available: no profile")
            return 0
        prows, names = [], None
        for nel in args.nel:
            for (name, python, _), lab in zip(sides, labels):
                sh = perf_profile(nel, "auto", False, seconds=3.0, newton="auto", python=python)
                if sh is None:
                    continue
                names = list(sh)
                prows.append([nel, lab] + [sh[k] for k in names])
        if names:
            print(format_table(["el/arm", "checkout"] + names, prows,
                               title="\nperf: % of the samples of the timed loop"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
