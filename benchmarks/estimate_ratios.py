"""Estimated against true time-discretisation errors on every shipped case (flexmbs.analysis.accuracy).

For each case and the steps h0 and h0/2 (h0 the case's step), every simulated response's
estimate (the rule of docs/accuracy.md: h, h/2, h/4, and h/8 when a ratio there is ambiguous;
the same estimates `Problem.evaluate(x, error=True)` gives) beside its true error, the
difference of its value (a history: its maximum) from the same design at h0/REF, and their
ratio estimate / true. The library promises, for every estimate it calls reliable, a ratio
within [0.5, 2]; the last column flags those outside.

    .venv/bin/python benchmarks/estimate_ratios.py [--ref 64] [--only CASE ...]

Cases: cases/*.toml at their start designs, the four-bar at the light design of
tests/test_accuracy.py (54.11, 15.14, 16.19 mm) and the undamped crank-rocker
tests/data/crank_rocker_undamped.toml. The table is written to
benchmarks/results/estimate_ratios.txt with the commit and the command.
"""
from __future__ import annotations

import argparse
import math
import pathlib
import subprocess
import sys
import time

import numpy as np

from flexmbs import Problem
from flexmbs.analysis.accuracy import estimate_errors, needs_fourth_level

ROOT = pathlib.Path(__file__).resolve().parents[1]
BAND = (0.5, 2.0)

CASES = [(p.stem, str(p), None) for p in sorted((ROOT / "cases").glob("*.toml"))] + [
    ("fourbar (light)", "fourbar", [54.11, 15.14, 16.19]),
    ("crank_rocker_undamped", str(ROOT / "tests" / "data" / "crank_rocker_undamped.toml"), None),
]


def ladder_estimates(evs, h0, first):
    """The estimates of `Problem.evaluate(error=True)` at h0/2^first from the evaluations
    evs[k] at h0/2^k: three levels, a fourth when one of them is 'unconfirmed'."""
    levels = [h0 / 2 ** (first + k) for k in range(4)]
    est = estimate_errors(evs[first:first + 3], levels[:3])
    if needs_fourth_level([*est[0].values(), est[1], *est[2].values()]):
        est = estimate_errors(evs[first:first + 4], levels)
    return est[0]


def case_rows(label, case, x, ref):
    prob = Problem(case)
    h0 = float(prob.description.time.grid_h)
    kmax = int(round(math.log2(ref)))
    evs = [prob.evaluate(x, gradient=False)] + [prob.refined(2 ** k).evaluate(x, gradient=False)
                                                for k in range(1, kmax + 1)]
    fine = evs[-1]
    rows = []
    for first in (0, 1):
        for name, e in ladder_estimates(evs, h0, first).items():
            v = fine.values[name]
            if not np.ndim(v):
                continue                      # a value that needs no simulation (a mass)
            true = abs(e.value - float(np.max(v)))
            ratio = e.error / true if true > 0 else math.inf
            flag = ""
            if e.reliable and not BAND[0] <= ratio <= BAND[1]:
                flag = "OUTSIDE"
            rows.append((label, name, f"h0/{2 ** first}", e.value, e.error, true, ratio,
                         e.status, e.n_levels, flag))
    return rows


def fmt(r):
    return (f"{r[0]:30s} {r[1]:20s} {r[2]:>6s} {r[3]:12.6g} {r[4]:10.3g} {r[5]:10.3g} "
            f"{r[6]:8.3g}  {r[7]:15s} {r[8]:2d}  {r[9]}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", type=int, default=64, help="the reference step is h0/REF "
                    "(a power of two >= 16)")
    ap.add_argument("--only", nargs="*", help="case labels to run (default: all)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "estimate_ratios.txt"))
    args = ap.parse_args(argv)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    t0 = time.perf_counter()
    head = (f"{'case':30s} {'response':20s} {'level':>6s} {'value':>12s} {'estimate':>10s} "
            f"{'true':>10s} {'est/true':>8s}  {'status':15s} {'n':>2s}")
    lines = [head]
    rows = []
    for label, case, x in CASES:
        if args.only and label not in args.only:
            continue
        new = case_rows(label, case, x, args.ref)
        rows += new
        lines += [fmt(r) for r in new]
        print("\n".join(fmt(r) for r in new), file=sys.stderr, flush=True)
    reliable = [r for r in rows if r[7] in ("asymptotic", "converged")]
    outside = [r for r in reliable if r[9]]
    finite = [r[6] for r in reliable if math.isfinite(r[6])]
    lines.append(f"{len(reliable)} of {len(rows)} estimates reliable"
                 + (f", ratios {min(finite):.3g}-{max(finite):.3g}" if finite else "")
                 + f"; {len(outside)} reliable outside [{BAND[0]}, {BAND[1]}]")
    lines.append(f"true error: the difference from h0/{args.ref}; n: levels used; "
                 f"wall time {time.perf_counter() - t0:.0f} s")
    lines.append(f"commit {commit}; command: .venv/bin/python benchmarks/estimate_ratios.py "
                 + " ".join(sys.argv[1:] if argv is None else argv))
    text = "\n".join(lines)
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
