"""Every fully coupled optimizer side by side on general-format cases (a benchmark, not a test).

    .venv/bin/python benchmarks/optimizers.py                       # robot_2dof and fourbar
    .venv/bin/python benchmarks/optimizers.py --cases fourbar --optimizers nlopt-ccsaq,mma
    .venv/bin/python benchmarks/optimizers.py --starts 8            # + a multi-start row each
    .venv/bin/python benchmarks/optimizers.py --cases comparison     # Tables 1,2,5,6,7 + examples

A run is a case name, optionally with overrides and a start (mm, one value per variable or
one for all): ``robot_2dof:time.t_end=0.66@55,45,35,25``. ``--cases comparison`` is the set
docs/optimizers.md reports: the robot's Tables 1, 2, 5, 6 and 7 (the four starts of 6 and 7) and
three mechanisms beyond the paper (slider_crank_press, three_arm_robot, fourbar_tubes).

For each case (cases/NAME.toml, from the case's start) and optimizer
(flexmbs.methods.fully.OPTIMIZERS): wall time, simulations, final objective (mass),
constraint violation of the final design re-simulated, and the optimizer's share of the wall
time (the time outside Problem.evaluate: the optimizer's own subproblems, the stopping test,
the history). With --starts N, a multi-start row per case and optimizer (N Sobol starts,
--workers processes): best feasible mass, how many starts reached it, feasible starts.
Every number is written to benchmarks/results/optimizers.json (--out).

Single-threaded BLAS (OPENBLAS_NUM_THREADS=1), as run.py does. docs/optimizers.md records
the numbers behind the default optimizer.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

HERE = Path(__file__).resolve().parent
CASES = HERE.parent / "cases"


def _commit():
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True,
                              capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


#: The runs of the comparison of docs/optimizers.md: label -> run spec (see the module's docstring).
COMPARISON = {
    "T1": "robot_2dof:time.t_end=0.65",
    "T2": "robot_2dof_tracking:time.t_end=0.65",
    "T5": "robot_2dof:time.t_end=0.66",
    "T6-55": "robot_2dof:time.t_end=0.65@55",
    "T6-55/45/35/25": "robot_2dof:time.t_end=0.65@55,45,35,25",
    "T6-45": "robot_2dof:time.t_end=0.65@45",
    "T7-50": "robot_2dof:time.t_end=0.6685",
    "T7-55": "robot_2dof:time.t_end=0.6685@55",
    "T7-55/45/35/25": "robot_2dof:time.t_end=0.6685@55,45,35,25",
    "T7-45": "robot_2dof:time.t_end=0.6685@45",
    "press": "slider_crank_press",
    "3-arm": "three_arm_robot",
    "tubes": "fourbar_tubes",
}


def parse_run(spec):
    """(case, overrides, start or None) of a run spec ``case[:k=v;k=v][@s1,s2,...]``."""
    from flexmbs.model.casefile import parse_override

    spec, _, start = spec.partition("@")
    case, _, over = spec.partition(":")
    overrides = dict(parse_override(o) for o in over.split(";") if o)
    x0 = [float(v) for v in start.split(",")] if start else None
    return case, overrides, x0


def run_one(spec, optimizer, max_simulations):
    import numpy as np

    from flexmbs.methods.fully import optimize_fully
    from flexmbs.problem import Problem

    case, overrides, x0 = parse_run(spec)
    problem = Problem(case, overrides=overrides)
    if x0 is not None:
        x0 = np.broadcast_to(np.asarray(x0), problem.start.shape).copy()
    t = time.perf_counter()
    try:
        r = optimize_fully(problem, x0, optimizer=optimizer,
                           options=dict(max_iterations=max_simulations,
                                        max_simulations=max_simulations))
    except Exception as exc:     # noqa: BLE001 - a benchmark reports, it does not stop
        return dict(case=case, optimizer=optimizer, error=f"{type(exc).__name__}: {exc}",
                    wall_time_s=time.perf_counter() - t)
    return dict(case=case, optimizer=optimizer, wall_time_s=r.wall_time_s,
                simulations=r.simulations, objective=r.objective, max_violation=r.max_violation,
                optimizer_share=r.details["optimizer_share"], converged=r.converged,
                design=[float(v) for v in r.design], reason=r.reason)


def run_multi(spec, optimizer, starts, workers, max_simulations):
    from flexmbs.methods.multistart import multistart
    from flexmbs.problem import Problem

    case, overrides, _ = parse_run(spec)
    r = multistart(Problem(case, overrides=overrides), starts, workers=workers, progress=False,
                   options=dict(optimizer=optimizer),
                   fully=dict(max_iterations=max_simulations, max_simulations=max_simulations))
    feas = [o for o in r.optima if o["feasible"]]
    return dict(case=case, optimizer=optimizer, starts=starts, wall_time_s=r.wall_time_s,
                simulations=r.simulations,
                objective=None if r.best is None else r.best["objective"],
                max_violation=None if r.best is None else r.best["max_violation"],
                reached_best=r.reached_best, feasible_starts=len(feas),
                optimizer_share=(sum(o["optimizer_share"] * o["wall_time_s"] for o in r.optima)
                                 / max(sum(o["wall_time_s"] for o in r.optima), 1e-300)),
                optima=[(o["objective"], o["max_violation"]) for o in r.optima])


def _fmt(v, f):
    return "-" if v is None else format(v, f)


def main(argv=None):
    from flexmbs.methods.fully import OPTIMIZERS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="robot_2dof,fourbar",
                    help="comma-separated run specs (case[:k=v][@start]; ';'-separated when a "
                         "start is given), or 'comparison' (default robot_2dof,fourbar)")
    ap.add_argument("--optimizers", default=",".join(OPTIMIZERS))
    ap.add_argument("--max-simulations", type=int, default=300)
    ap.add_argument("--starts", type=int, default=0,
                    help="also a multi-start row per case and optimizer (N Sobol starts)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)
    if args.cases == "comparison":
        cases = dict(COMPARISON)
    else:
        cases = {c: c for c in args.cases.split(";" if "@" in args.cases else ",") if c}
    opts = [o for o in args.optimizers.split(",") if o]
    print(f"# optimizers benchmark: {platform.node()}, load {os.getloadavg()[0]:.1f}, "
          f"commit {_commit()}", flush=True)
    head = (f"{'optimizer':12s} {'case':12s} {'starts':>6s} {'wall s':>8s} {'sims':>6s} "
            f"{'mass':>9s} {'violation':>9s} {'opt share':>9s}  notes")
    print(head)
    print("-" * len(head))
    rows = []
    for case, spec in cases.items():
        for opt in opts:
            r = run_one(spec, opt, args.max_simulations)
            r["case"] = case
            rows.append(r)
            note = r.get("error") or ("converged" if r["converged"] else r["reason"][:40])
            print(f"{opt:12s} {case:12s} {1:6d} {r['wall_time_s']:8.1f} "
                  f"{r.get('simulations', 0):6d} {_fmt(r.get('objective'), '9.4f')} "
                  f"{_fmt(r.get('max_violation'), '9.1e')} "
                  f"{_fmt(r.get('optimizer_share'), '9.2f')}  {note}", flush=True)
            if args.starts:
                m = run_multi(spec, opt, args.starts, args.workers, args.max_simulations)
                m["case"] = case
                rows.append(m)
                print(f"{opt:12s} {case:12s} {args.starts:6d} {m['wall_time_s']:8.1f} "
                      f"{m['simulations']:6d} {_fmt(m['objective'], '9.4f')} "
                      f"{_fmt(m['max_violation'], '9.1e')} {m['optimizer_share']:9.2f}  "
                      f"best reached by {m['reached_best']}, feasible "
                      f"{m['feasible_starts']}/{args.starts}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "optimizers.json").write_text(json.dumps(dict(commit=_commit(), rows=rows),
                                                    indent=1, default=float))
    print(f"# written {out / 'optimizers.json'}")


if __name__ == "__main__":
    sys.exit(main())
