"""The grid of a verified continuation of an adaptive case (time.h = "auto"): subdivided or re-chosen.

A design that fails its verification at the step level f = 2^k (flexmbs.methods.verified) is
optimized again on a finer resolution. For an adaptive case the finer problem's grid can be

- "subdivided": the frozen grid (chosen at the case's start design) with every step divided
  by f (Problem.refined(f), what the verification's ladder integrates), or
- "re-chosen": chosen afresh by choose_steps at the design continued from, at the tolerance
  tol / f^2 (a step divided by f has ~f^2 less error in a second-order scheme)
  (`rechosen`).

For each, at designs away from the start: the steps and the relative error of the response
histories (max over time and responses of |r - r_ref| / max |r_ref|) on the finer response
grid (spacing output / f) against a fixed-step reference at that design (steps output / 32
and output / 64 extrapolated, second order).
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

from flexmbs.analysis.adaptive import choose_steps
from flexmbs.problem import Problem

# (label, case, overrides, designs continued from (the case's units))
CASES = [
    ("damped press", "slider_crank_press_damped",
     {"time.h": "auto", "time.rtol": 1e-2}, [[12.0], [40.0]]),
    ("robot move + dwell", "robot_2dof_dwell",
     {"time.h": "auto", "time.rtol": 1e-2}, [[30.0, 30.0, 25.0, 25.0], [60.0, 55.0, 45.0, 40.0]]),
]
FACTORS = (2, 4)


def _histories(ev, stride=1):
    return {n: np.asarray(v, float)[::stride] for n, v in ev.values.items() if np.ndim(v) >= 1}


def _error(hist, ref):
    return max(float(np.abs(hist[n] - ref[n]).max() / np.abs(ref[n]).max()) for n in ref)


def rechosen(problem, factor, x):
    """`problem` with a response grid `factor` times finer, tol and rtol divided by factor^2,
    and its grid chosen at design x."""
    ts = problem.description.time
    over = {"time.output": ts.grid_h / factor, "time.t_end": problem.mechanism.t_end}
    for key in ("tol", "rtol"):
        if getattr(ts, key) is not None:
            over[f"time.{key}"] = getattr(ts, key) / factor**2
    fine = Problem(problem.description, overrides=over)
    fine.adapt(x)
    return fine


def measure(label, case, over, designs, log):
    base = Problem(case, over)
    ts = base.description.time
    out = []
    base.steps()                                  # frozen at the start design
    for x in designs:
        for f in FACTORS:
            # reference at x on the grid of spacing output / f
            fixed = {k: v for k, v in over.items() if k not in ("time.h", "time.tol", "time.rtol")}
            fx = [Problem(case, {**fixed, "time.h": ts.grid_h / k}).evaluate(x, gradient=False)
                  for k in (32, 64)]
            rc, rf = _histories(fx[0], 32 // f), _histories(fx[1], 64 // f)
            ref = {n: rf[n] + (rf[n] - rc[n]) / 3 for n in rf}
            ref_err = _error(rf, ref)
            row = dict(design=list(x), factor=f, reference_error=ref_err)
            sub = base.refined(f)
            ev = sub.evaluate(x, gradient=False)
            row["subdivided"] = dict(steps=int(ev.stats["steps"]), error=_error(_histories(ev), ref))
            cont = rechosen(base, f, x)
            t0 = time.process_time()
            info = {}
            grid = choose_steps(cont, x, info=info)
            choice = time.process_time() - t0
            ev = cont.evaluate(x, gradient=False)
            row["rechosen"] = dict(steps=int(ev.stats["steps"]), error=_error(_histories(ev), ref),
                                   choice_cpu_s=choice, pilot_steps=info["pilot_steps"])
            assert grid.size - 1 == ev.stats["steps"]
            # the grid chosen at x at the coarse tolerance, subdivided: the design's share
            own = Problem(case, over)
            own.adapt(x)
            sub_x = own.refined(f)
            ev = sub_x.evaluate(x, gradient=False)
            row["subdivided_at_x"] = dict(steps=int(ev.stats["steps"]),
                                          error=_error(_histories(ev), ref))
            out.append(row)
            log(f"{label:20s} x={x} f={f}: reference {ref_err:.1e};  subdivided "
                f"{row['subdivided']['steps']:6d} steps err {row['subdivided']['error']:.2e};  "
                f"re-chosen (tol/f^2) {row['rechosen']['steps']:6d} steps err "
                f"{row['rechosen']['error']:.2e} (+{info['pilot_steps']} pilot steps);  "
                f"chosen at x, subdivided {row['subdivided_at_x']['steps']:6d} steps err "
                f"{row['subdivided_at_x']['error']:.2e}")
    return dict(case=case, overrides=over, rtol=ts.rtol, start_steps=int(base.steps().size - 1),
                rows=out)


def run(quick=False, outdir="results", log=print):
    res = {}
    for label, case, over, designs in CASES:
        res[label] = measure(label, case, over, designs[:1] if quick else designs, log)
    path = os.path.join(outdir, f"continuation_grids{'_quick' if quick else ''}.json")
    with open(path, "w") as fh:
        json.dump(res, fh, indent=1, default=float)
    log(f"(numbers in {path})")
    return res
