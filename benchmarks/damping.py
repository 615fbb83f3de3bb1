"""Material (Kelvin-Voigt) damping of the beams: convergence in h and cost, on the slider-crank
press (cases/slider_crank_press.toml, and cases/slider_crank_press_damped.toml: 2 % at the rod's
first bending frequency, 316 Hz).

For h = 5e-4 / 2^k (k = 0 .. 4; --quick: 0 .. 3), rho_inf = 0.5, 0.3 s, both cases: the largest
rod stress and ram error (Problem.evaluate at the start design, gradient=False), their
differences between successive h and the observed order log2(d_k / d_{k+1}); and the CPU time of
one flexmbs.analysis.simulate of each case (min of repeats; Newton iterations and factorizations), with
and without the damping, and of a gradient evaluation (direct and adjoint, 0.3 s, the case's
per-step constraints).

Usage: python benchmarks/damping.py [--quick]   (or benchmarks/run.py --only damping)
"""
from __future__ import annotations

import argparse
import json
import os
import sys

if __name__ == "__main__":                  # single-threaded BLAS, as benchmarks/run.py sets it
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import format_table, machine_summary, time_call  # noqa: E402
from flexmbs.analysis.settings import InitialConditions, SimulationSettings  # noqa: E402

CASES = ("slider_crank_press", "slider_crank_press_damped")
H0 = 5e-4


def convergence(levels, log):
    """Largest rod stress (MPa) and ram error (um) per case and h, with differences and orders."""
    from flexmbs.problem import Problem
    rows, out = [], {}
    for case in CASES:
        vals = []
        for k in range(levels):
            h = H0 / 2 ** k
            p = Problem(case, overrides={"time.h": h})
            ev = p.evaluate(p.start, gradient=False)
            vals.append((h, float(np.max(ev.values["rod_stress"])) / 1e6,
                         float(np.max(ev.values["ram_error"])) * 1e6))
        out[case] = vals
        ds = np.abs(np.diff([v[1] for v in vals]))
        de = np.abs(np.diff([v[2] for v in vals]))
        for k, (h, s, e) in enumerate(vals):
            d_s = f"{ds[k - 1]:.2e}" if k else ""
            d_e = f"{de[k - 1]:.2e}" if k else ""
            o_e = f"{np.log2(de[k - 2] / de[k - 1]):.2f}" if k >= 2 else ""
            o_s = f"{np.log2(ds[k - 2] / ds[k - 1]):.2f}" if k >= 2 else ""
            rows.append([case, f"{h:.4e}", f"{s:.6f}", d_s, o_s, f"{e:.6f}", d_e, o_e])
    log(format_table(["case", "h (s)", "max stress MPa", "diff", "order", "max ram err um",
                      "diff", "order"], rows,
                     title="largest rod stress and ram error against h (rho_inf = 0.5, 0.3 s)"))
    return out


def cost(repeats, log):
    """CPU time of one simulation and one gradient evaluation of each case (h = 5e-4)."""
    from flexmbs import simulate
    from flexmbs.problem import Problem
    rows, out = [], {}
    for case in CASES:
        p = Problem(case)
        mech = p.mechanism
        q0, qd0 = mech.initial_state()
        settings = SimulationSettings(rho_inf=0.5, validity="off")
        initial = InitialConditions(q0=q0, qd0=qd0)
        res, t_sim = time_call(lambda: simulate(mech.model, 0.3, H0, settings, initial=initial),
                               repeats=repeats, budget=10.0)
        st = res.stats
        grads = {}
        for method in ("direct", "adjoint"):
            # a fresh Problem per call: an evaluation at the same design is not recomputed
            _, t_g = time_call(lambda a: a.evaluate(a.start, method=method), repeats=repeats,
                               budget=10.0, setup=lambda: Problem(case))
            grads[method] = t_g.cpu_min * 1e3
        out[case] = dict(sim_ms=t_sim.cpu_min * 1e3, newton=int(st["newton_iterations"]),
                         factorizations=int(st["factorizations"]), **{f"{k}_ms": v
                                                                      for k, v in grads.items()})
        rows.append([case, f"{t_sim.cpu_min * 1e3:.1f}", st["newton_iterations"],
                     st["factorizations"], f"{grads['direct']:.1f}", f"{grads['adjoint']:.1f}"])
    log(format_table(["case", "simulate ms", "Newton it.", "factorizations", "direct grad ms",
                      "adjoint grad ms"], rows,
                     title=f"cost at h = {H0} (0.3 s, 600 steps), CPU time, min of {repeats} "
                           f"repeats; {machine_summary()}"))
    return out


def run(quick=False, outdir=None, log=print):
    """Entry point of benchmarks/run.py."""
    res = dict(machine=machine_summary(), convergence=convergence(4 if quick else 5, log),
               cost=cost(3 if quick else 5, log))
    if outdir:
        with open(os.path.join(outdir, "damping.json"), "w") as f:
            json.dump(res, f, indent=1)
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    run(quick=ap.parse_args().quick)
