"""Every shipped case optimized from its start, fully and weakly coupled (a benchmark, not a test).

    .venv/bin/python benchmarks/shipped_cases.py                       # every case, both methods
    .venv/bin/python benchmarks/shipped_cases.py --cases fourbar --methods weakly
    .venv/bin/python benchmarks/shipped_cases.py --print               # the table from the JSON

Each run is `flexmbs optimize CASE --method METHOD --json` with the case's own options, in a
subprocess with a time limit (--timeout, s). The table: mass of the returned design, whether
the run converged (weakly: its diagnosis), whether the design is feasible at the step its
verification reached (`OptimizationResult.verification`: feasible within its rtol, largest
constraint value g relative to its limit), that step, and the wall time. A method the case
does not support (a CaseError) is listed with its message. Results are merged into
benchmarks/results/shipped_cases.json (--out); docs/optimizers.md records the numbers.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "shipped_cases.json"


def run(case, method, timeout):
    """One optimization in a subprocess: a dict of the table's columns."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "flexmbs", "optimize", case, "--method", method,
                            "--json"], capture_output=True, text=True, timeout=timeout, env=env,
                           cwd=ROOT)
    except subprocess.TimeoutExpired:
        return dict(case=case, method=method, error=f"not ended after {timeout:g} s")
    wall = time.perf_counter() - t0
    try:                # exit status 1: a result that did not converge or is infeasible
        r = json.loads(p.stdout)
    except json.JSONDecodeError:
        return dict(case=case, method=method, wall_s=wall,
                    error=(p.stderr.strip().splitlines() or ["exit status %d" % p.returncode])[-1])
    v = r.get("verification") or {}
    return dict(case=case, method=method, mass_kg=r["mass_kg"], converged=r["converged"],
                diagnosis=r.get("diagnosis"), iterations=r["iterations"],
                max_violation_h=r["max_violation"], feasible=v.get("feasible"),
                verified=v.get("verified"), g_verified=v.get("max_violation"),
                h_verified=v.get("h"), case_h=v.get("case_h"), wall_s=wall,
                design=r["design"], reason=r["reason"])


def table(rows):
    lines = ["| case | method | mass | converged | feasible (verified) | largest g there | "
             "verified at h | wall time |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['method']} | {r['error']} | | | | | |")
            continue
        conv = r["diagnosis"] or ("converged" if r["converged"] else "not converged")
        step = ("-" if r["h_verified"] is None else
                f"{r['h_verified']:.3g} s (h/{round(r['case_h'] / r['h_verified'])})")
        g = "-" if r["g_verified"] is None else f"{r['g_verified']:+.2g}"
        lines.append(f"| {r['case']} | {r['method']} | {r['mass_kg']:.4g} kg | {conv} | "
                     f"{r['feasible']} | {g} | {step} | {r['wall_s']:.0f} s |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=None, help="comma-separated (default: cases/*.toml)")
    ap.add_argument("--methods", default="fully,weakly")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--print", action="store_true", help="print the table of --out and exit")
    a = ap.parse_args(argv)
    out = Path(a.out)
    stored = json.loads(out.read_text()) if out.exists() else []
    if not a.print:
        cases = (a.cases.split(",") if a.cases else
                 sorted(p.stem for p in (ROOT / "cases").glob("*.toml")))
        for case in cases:
            for method in a.methods.split(","):
                r = run(case, method, a.timeout)
                stored = [s for s in stored if (s["case"], s["method"]) != (case, method)]
                stored.append(r)
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(stored, indent=1))
                print(table([r]).splitlines()[-1], flush=True)
    print(table(sorted(stored, key=lambda s: (s["case"], s["method"]))))


if __name__ == "__main__":
    main()
