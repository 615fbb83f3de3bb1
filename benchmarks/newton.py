"""Newton strategies side by side: full / reuse / auto, simulation and simulation with
direct design sensitivities, on the paper's robot (cases/robot_2dof.toml: 2 elements per
arm, 1300 steps, 4 design variables) and the same robot with 32 and 128 elements per arm (a dict
override of `elements`).

For each size and strategy: process CPU time of Problem.simulate (the whole call, and the
Fortran core alone: the compiled run flexmbs.core.simulate_arrays wrapped by a timer, as in where_time_goes.py),
minimum over interleaved repeats (the six runs of a size alternate, so that a change of the
machine's load hits them alike); the ratios sensitivities / simulation (target <= 1.5 in
every mode) and time / full Newton's; Newton iterations and factorizations (of which, made for
the derivative solves); and the largest difference of the coordinates from full Newton's.

Usage: python benchmarks/newton.py [--quick] [--repeat N]   (or benchmarks/run.py --only newton)
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

if __name__ == "__main__":                  # single-threaded BLAS, as benchmarks/run.py sets it
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import tomllib
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import format_table, machine_summary  # noqa: E402
from where_time_goes import core_timer  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "cases" / "robot_2dof.toml"
MODES = ("full", "reuse", "auto")


def robot_problem(elements, newton):
    """The robot of cases/robot_2dof.toml with `elements` per arm and a Newton strategy."""
    from flexmbs.problem import Problem
    raw = tomllib.loads(CASE.read_text())
    for body in raw["bodies"]:
        if body.get("type") == "beam":
            body["elements"] = elements
    raw["time"]["newton"] = newton
    return Problem(raw)


def measure_size(elements, repeats, budget, log):
    """Every strategy, with and without sensitivities, interleaved; min CPU times."""
    probs = {mode: robot_problem(elements, mode) for mode in MODES}
    best = {}
    results = {}
    spent = 0.0
    with core_timer() as ct:
        for rep in range(repeats):
            for mode in MODES:
                for grad in (False, True):
                    n0 = len(ct.calls)
                    c0, w0 = time.process_time(), time.perf_counter()
                    res = probs[mode].simulate(gradient=grad)
                    cpu = time.process_time() - c0
                    spent += time.perf_counter() - w0
                    core = sum(c for _, c in ct.calls[n0:])
                    b = best.setdefault((mode, grad), [np.inf, np.inf])
                    b[0], b[1] = min(b[0], cpu), min(b[1], core)
                    results[(mode, grad)] = res
            if rep >= 1 and spent > budget:
                break
    rows = []
    ref = {g: results[("full", g)] for g in (False, True)}
    for mode in MODES:
        sim, sens = best[(mode, False)], best[(mode, True)]
        rs, rg = results[(mode, False)], results[(mode, True)]
        rows.append(dict(
            elements=elements, unknowns=rs.stats["unknowns"], steps=rs.stats["steps"], newton=mode,
            sim_ms=1e3 * sim[0], sim_core_ms=1e3 * sim[1], sens_ms=1e3 * sens[0],
            sens_core_ms=1e3 * sens[1], sens_over_sim=sens[0] / sim[0],
            sens_over_sim_core=sens[1] / sim[1],
            sim_over_full=sim[0] / best[("full", False)][0],
            sens_over_full=sens[0] / best[("full", True)][0],
            sens_over_full_sim=sens[0] / best[("full", False)][0],
            iterations=rs.stats["newton_iterations"], factorizations=rs.stats["factorizations"],
            sens_iterations=rg.stats["newton_iterations"],
            sens_factorizations=rg.stats["factorizations"],
            sens_for_derivatives=rg.stats["sensitivity_factorizations"],
            dq_vs_full=float(np.abs(rs.q - ref[False].q).max()),
            dqdp_vs_full_rel=float((np.abs(rg.dq - ref[True].dq).max(axis=(0, 1))
                                    / np.abs(ref[True].dq).max(axis=(0, 1))).max()),
            repeats=rep + 1))
    return rows


def run(quick=False, outdir=None, log=print, repeat=None):
    """Entry point of benchmarks/run.py."""
    sizes = [2, 32] if quick else [2, 32, 128]
    repeats = repeat or (3 if quick else 7)
    rows = []
    for nel in sizes:
        t0 = time.perf_counter()
        rows += measure_size(nel, repeats if nel < 128 else max(3, repeats // 2),
                             budget=20.0 if nel < 128 else 60.0, log=log)
        log(f"  {nel} elements per arm: {time.perf_counter() - t0:.1f} s")
    table = [[r["elements"], r["unknowns"], r["newton"], r["sim_ms"], r["sens_ms"],
              r["sens_over_sim"], r["sim_over_full"], r["sens_over_full"], r["sens_over_full_sim"],
              r["sim_core_ms"], r["sens_core_ms"], r["sens_over_sim_core"],
              f"{r['iterations']}/{r['factorizations']}",
              f"{r['sens_iterations']}/{r['sens_factorizations']} ({r['sens_for_derivatives']})",
              f"{r['dq_vs_full']:.1e}", f"{r['dqdp_vs_full_rel']:.1e}"] for r in rows]
    log(format_table(
        ["el/arm", "n", "newton", "sim ms", "+sens ms", "sens/sim", "sim/full", "sens/full",
         "sens/full sim", "core sim", "core sens", "core s/s", "sim it/fact",
         "sens it/fact (deriv.)", "|dq| vs full", "dq/dp vs full"],
        table, title=f"robot_2dof, 1300 steps, 4 design variables; CPU time, min of interleaved "
                     f"repeats; {machine_summary()}"))
    log("sens/sim: Problem.simulate with gradient=True over the same strategy without; "
        "sim/full, sens/full: over full Newton's; sens/full sim: over full Newton's simulation; "
        "core: the Fortran call alone; it/fact: Newton iterations / factorizations (those of "
        "the derivative solves in parentheses); |dq| vs full: largest coordinate difference (m); "
        "dq/dp vs full: largest relative difference of the derivatives.")
    if outdir:
        with open(os.path.join(outdir, "newton.json"), "w") as f:
            json.dump(dict(machine=machine_summary(), rows=rows), f, indent=1)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 and 32 elements per arm only")
    ap.add_argument("--repeat", type=int, default=None, help="repeats per run (default 7)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    run(args.quick, args.out, print, args.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
