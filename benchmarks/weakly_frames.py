"""The weakly coupled method's corotational frames on every shipped case (a benchmark, not a test).

    .venv/bin/python benchmarks/weakly_frames.py                         # every case, every kind
    .venv/bin/python benchmarks/weakly_frames.py --cases fourbar --kinds auto,tangent
    .venv/bin/python benchmarks/weakly_frames.py --cases fourbar,fourbar_no_masses \
        --kinds auto,follower_chord --move-limit 0.1                     # with a move limit
    .venv/bin/python benchmarks/weakly_frames.py --print                 # the table from the JSON

For each shipped case with a deviation constraint (cases/*.toml) and each frame kind of
`optimize_weakly` ('auto': from each beam's joints; 'tangent': the paper's; 'chord';
'follower_chord': the four-bar's follower on its chord, crank and coupler tangent, the paper's
study's Table 3 variant), one run with the method's defaults (and --move-limit) from the
case's start: the mass of the returned design, its largest
constraint value from a fresh simulation at the case's step h and at h/4 (`Problem(case,
overrides={"time.h": h / 4})`; feasible when <= 1e-6), the ratio of the static form's deviation
to the simulated one at the returned design (details static_to_simulated), the cycles, the
diagnosis and the wall time. Where 'auto' gives every beam the same kind as 'tangent' (the
robots: every arm driven) the two runs are one and the same and 'auto' is not run again.
Results are merged into benchmarks/results/weakly_frames.json (--out). docs/optimizers.md
("Corotational frames") records the numbers.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import warnings  # noqa: E402

import numpy as np  # noqa: E402

CASES = ["fourbar", "slider_crank_press", "slider_crank_press_tapered", "fourbar_no_masses",
         "robot_2dof", "robot_2dof_tracking", "robot_2dof_tapered", "fourbar_tubes",
         "three_arm_robot", "robot_2dof_tapered_tubes"]
KINDS = ["auto", "tangent", "chord", "follower_chord"]
#: kind name -> optimize_weakly's frame_kind
FRAME_KIND = {"auto": "auto", "tangent": "tangent", "chord": "chord",
              "follower_chord": {"crank": "tangent", "coupler": "tangent", "follower": "chord"}}


def _max_g(case, x, overrides=None):
    from flexmbs.problem import Problem
    g = np.asarray(Problem(case, overrides=overrides or {}).evaluate(x, gradient=False)
                   .constraints, float)
    return float(g.max()) if g.size else None


def run_one(case, kind, move_limit=None):
    """One weakly coupled run: a dict of the measured numbers."""
    from flexmbs.optimize import optimize_weakly
    from flexmbs.problem import Problem
    from flexmbs.methods.weakly import StaticModel
    prob = Problem(case)
    kinds = StaticModel(prob, frame_kind=FRAME_KIND[kind]).kinds
    h = float(prob.description.time.h)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        r = optimize_weakly(prob, options=dict(frame_kind=FRAME_KIND[kind], move_limit=move_limit))
        wall = time.perf_counter() - t0
        g_h = _max_g(case, r.design)
        g_h4 = _max_g(case, r.design, {"time.h": h / 4})
    return dict(case=case, kind=kind, move_limit=move_limit, frame_kinds=kinds, h=h, mass_kg=float(r.mass_kg),
                design=[float(v) for v in r.design], max_constraint_h=g_h,
                max_constraint_h4=g_h4, feasible_h=g_h is None or g_h <= 1e-6,
                feasible_h4=g_h4 is None or g_h4 <= 1e-6,
                static_to_simulated=r.details["static_to_simulated"], cycles=int(r.iterations),
                converged=bool(r.converged), diagnosis=r.details["diagnosis"],
                wall_time_s=wall, reason=r.reason)


def print_table(results, cases, file=sys.stdout):
    """One row per case and kind: mass, largest constraint at h and h/4, ratio, cycles."""
    print(f"{'case':<28} {'kind':<24} {'mass kg':>10} {'g(h)':>9} {'g(h/4)':>9} "
          f"{'static/sim':>12} {'cyc':>4} diagnosis", file=file)
    for case in cases:
        for key in [k for k in results if k.split("/")[0] == case]:
            r = results[key]
            kind = "/".join(key.split("/")[1:])
            ratio = ", ".join("-" if v is None else f"{v:.3f}"
                              for v in r["static_to_simulated"].values())
            print(f"{case:<28} {kind:<24} {r['mass_kg']:10.4f} {r['max_constraint_h']:+9.3g} "
                  f"{r['max_constraint_h4']:+9.3g} {ratio:>12} {r['cycles']:4d} "
                  f"{r['diagnosis']}  {r['wall_time_s']:.0f} s", file=file)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--kinds", default="auto,tangent,chord", help="comma-separated, of "
                    + ", ".join(KINDS))
    ap.add_argument("--move-limit", type=float, default=None, metavar="F",
                    help="optimize_weakly's move_limit (default none)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"
                                         / "weakly_frames.json"))
    ap.add_argument("--print", action="store_true", help="only print the stored results")
    a = ap.parse_args(argv)
    cases = [c for c in a.cases.split(",") if c]
    kinds = [k for k in a.kinds.split(",") if k]
    out = Path(a.out)
    results = json.loads(out.read_text()) if out.is_file() else {}
    if not a.print:
        from flexmbs.problem import Problem
        from flexmbs.methods.weakly import StaticModel
        for case in cases:
            same = (StaticModel(Problem(case), frame_kind="auto").kinds
                    == StaticModel(Problem(case), frame_kind="tangent").kinds)
            for kind in kinds:
                if kind not in FRAME_KIND:
                    ap.error(f"unknown kind {kind!r} (known: {', '.join(KINDS)})")
                if kind == "auto" and same:
                    continue
                res = run_one(case, kind, a.move_limit)
                key = f"{case}/{kind}" + ("" if a.move_limit is None else f"/move{a.move_limit:g}")
                results[key] = res
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(results, indent=1))
                print(f"{key}: {res['mass_kg']:.4f} kg, g(h) "
                      f"{res['max_constraint_h']:+.3g}, g(h/4) {res['max_constraint_h4']:+.3g}, "
                      f"static/sim {res['static_to_simulated']}, {res['cycles']} cycles, "
                      f"{res['diagnosis']}, {res['wall_time_s']:.0f} s", flush=True)
    print_table(results, cases)
    return 0


if __name__ == "__main__":
    sys.exit(main())
