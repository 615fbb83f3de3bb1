"""Remedies against the oscillation of the weakly coupled cycles, side by side (a benchmark,
not a test).

    .venv/bin/python benchmarks/weakly_remedies.py                      # every remedy, tables 3, 4, 1
    .venv/bin/python benchmarks/weakly_remedies.py --remedies paper,damping0.5 --tables 3
    .venv/bin/python benchmarks/weakly_remedies.py --print              # the table from the JSON

Each remedy is a set of options of `flexmbs.optimize.optimize_weakly` (REMEDIES below): move
limits on the relative design change per cycle, ESL averaged over the last two cycles
(esl_blend), a damped design update (damping), and OptiStruct's design-change criterion
(design_tol). Each runs on the paper's Table 3 (four-bar, 5 kg at A and B), Table 4 (four-bar
without masses), both from 250 mm, Table 1 (robot, 0.65 s, from 50 mm) and Table 5 (robot,
0.66 s, from 50 mm: the paper's oscillating case; `--tables 3,4,1,5`), with the cycle
cap and the frames of the paper's study (`PAPER`: 30 cycles, tangent frames, as
cases/studies/paper.toml's [options]) unless the remedy sets its own. For each run: the
mass of the returned design, its largest constraint value from a fresh simulation
(Problem.evaluate; feasible when <= 1e-6), the cycles, the diagnosis and the wall time.
Results are merged into benchmarks/results/weakly_remedies.json (--out), so runs can be made
one remedy at a time. docs/optimizers.md ("Weakly coupled cycles") records the numbers.
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

#: the options of the paper's study for the weakly coupled runs (cases/studies/paper.toml)
PAPER = dict(max_cycles=30, frame_kind="tangent")
#: the four-bar's follower in a chord frame, the crank and the coupler in tangent frames
FCHORD = {"crank": "tangent", "coupler": "tangent", "follower": "chord"}

#: name -> options of optimize_weakly (beyond PAPER)
REMEDIES = {
    "paper": {},
    "paper-100cyc": dict(max_cycles=100),
    "move0.2": dict(move_limit=0.2),
    "move0.1": dict(move_limit=0.1),
    "move0.05": dict(move_limit=0.05),
    "blend0.5": dict(esl_blend=0.5),
    "damping0.5": dict(damping=0.5),
    "damping0.3": dict(damping=0.3),
    "damping0.5+blend0.5": dict(damping=0.5, esl_blend=0.5),
    "design_tol1e-2": dict(design_tol=1e-2),
    "design_tol2e-2": dict(design_tol=2e-2),
    "damping0.5+design_tol2e-2": dict(damping=0.5, design_tol=2e-2),
    "move0.1+design_tol2e-2": dict(move_limit=0.1, design_tol=2e-2),
    # the four-bar's follower (pinned at both ends) in a chord frame C -> B: simply supported
    "fchord": dict(frame_kind=FCHORD),
    "fchord+damping0.5": dict(frame_kind=FCHORD, damping=0.5),
    "fchord+damping0.3": dict(frame_kind=FCHORD, damping=0.3),
    "fchord+move0.1": dict(frame_kind=FCHORD, move_limit=0.1),
    "fchord+move0.2": dict(frame_kind=FCHORD, move_limit=0.2),
    "fchord+move0.05": dict(frame_kind=FCHORD, move_limit=0.05),
    "fchord+move0.1-60cyc": dict(frame_kind=FCHORD, move_limit=0.1,
                                 max_cycles=60),
    "fchord+blend0.5": dict(frame_kind=FCHORD, esl_blend=0.5),
    "fchord+damping0.5+blend0.5": dict(frame_kind=FCHORD, damping=0.5,
                                       esl_blend=0.5),
    "fchord+damping0.5-60cyc": dict(frame_kind=FCHORD, damping=0.5,
                                    max_cycles=60),
}

#: table -> (case, overrides, start)
TABLES = {3: ("fourbar", {}, [250.0] * 3), 4: ("fourbar_no_masses", {}, [250.0] * 3),
          1: ("robot_2dof", {"time.t_end": 0.65}, [50.0] * 4),
          5: ("robot_2dof", {"time.t_end": 0.66}, [50.0] * 4)}


def run_one(table, options):
    """One weakly coupled run: a dict of the measured numbers."""
    from flexmbs.optimize import optimize_weakly
    from flexmbs.problem import Problem
    case, overrides, start = TABLES[table]
    opts = dict(PAPER)
    opts.update(options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        r = optimize_weakly(Problem(case, overrides=overrides), start, options=opts)
        wall = time.perf_counter() - t0
        ev = Problem(case, overrides=overrides).evaluate(r.design, gradient=False)
    g = np.asarray(ev.constraints, float)
    gmax = float(g.max()) if g.size else None
    return dict(table=table, case=case, options=opts, mass_kg=float(r.mass_kg),
                design=[float(v) for v in r.design], max_constraint_resimulated=gmax,
                feasible=gmax is None or gmax <= 1e-6, cycles=int(r.iterations),
                converged=bool(r.converged), diagnosis=r.details["diagnosis"],
                best_feasible_cycle=r.details["best_feasible_cycle"],
                last_mass_kg=r.details["last_mass_kg"],
                last_max_violation=r.details["last_max_violation"],
                wall_time_s=wall, reason=r.reason)


def print_table(results, remedies, tables, file=sys.stdout):
    """The comparison: one row per remedy, per table mass / feasibility / cycles / diagnosis /
    wall time."""
    head = f"{'remedy':<22}" + "".join(f" | Table {t} ({TABLES[t][0]})".ljust(48) for t in tables)
    print(head, file=file)
    print("-" * len(head), file=file)
    for name in remedies:
        cells = []
        for t in tables:
            r = results.get(f"{name}/{t}")
            if r is None:
                cells.append(" | " + "-".ljust(45))
                continue
            g = r["max_constraint_resimulated"]
            feas = "feasible" if r["feasible"] else f"g={g:+.3f}"
            cells.append(f" | {r['mass_kg']:7.3f} kg {feas:<9} {r['cycles']:3d} cyc "
                         f"{r['diagnosis']:<11} {r['wall_time_s']:5.0f} s")
        print(f"{name:<22}" + "".join(cells), file=file)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--remedies", default=",".join(REMEDIES),
                    help=f"comma-separated, of {', '.join(REMEDIES)}")
    ap.add_argument("--tables", default="3,4,1", help="comma-separated, of 3, 4, 1, 5")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"
                                         / "weakly_remedies.json"))
    ap.add_argument("--print", action="store_true", help="only print the stored results")
    a = ap.parse_args(argv)
    remedies = [r for r in a.remedies.split(",") if r]
    tables = [int(t) for t in a.tables.split(",") if t]
    for r in remedies:
        if r not in REMEDIES:
            ap.error(f"unknown remedy {r!r} (known: {', '.join(REMEDIES)})")
    out = Path(a.out)
    results = json.loads(out.read_text()) if out.is_file() else {}
    if not a.print:
        for name in remedies:
            for t in tables:
                res = run_one(t, REMEDIES[name])
                results[f"{name}/{t}"] = res
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(results, indent=1))
                print(f"{name} / Table {t}: {res['mass_kg']:.3f} kg, feasible "
                      f"{res['feasible']}, {res['cycles']} cycles, {res['diagnosis']}, "
                      f"{res['wall_time_s']:.0f} s", flush=True)
    print_table(results, [r for r in REMEDIES if r in remedies], tables)
    return 0


if __name__ == "__main__":
    sys.exit(main())
