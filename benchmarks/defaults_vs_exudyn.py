"""flexmbs with its default settings against Exudyn, side by side in one process.

A reduced form of work_precision.py: the robot of docs/paper-cases.md (p = 50 mm, static start, 0.65 s) in
both codes (common.py), at each mesh and step asked; flexmbs runs `flexmbs.analysis.simulate` with its
defaults (solver 'auto', newton 'auto', as `flexmbs simulate` does) and, beside it, full Newton
and 'reuse' (KLU); Exudyn runs its sparse (EigenSparse) solver with full and modified Newton
(dense too up to 32 elements per arm) at the tightest working tolerance (work_precision.py),
and the faster of its configurations is the one compared. At equal mesh and step both codes
solve the same discrete equations, so their errors are equal (column |fx-ex|, m): the ratio
here is the ratio at equal error of work_precision.py at that point.

Per flexmbs run also the work per step: Newton iterations (solves), factorizations, residual
evaluations, and the floor of the linear algebra alone (klu_refactor x factorizations +
klu_solve x solves, where_time_goes.py's measure with the same libKLU through ctypes).

CPU time of the process, minimum over interleaved repeats. Usage:
    python benchmarks/defaults_vs_exudyn.py [--nel 2 8 32 128] [--h 5e-4 ...] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

if __name__ == "__main__":
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import (ExudynFailed, ExudynRobot, deviation30, format_table,  # noqa: E402
                    machine_summary, robot_flexmbs)
from flexmbs.analysis.settings import SimulationSettings  # noqa: E402
from where_time_goes import iteration_matrix, klu_costs  # noqa: E402
from work_precision import EXUDYN_RTOLS, _static_rtol, steps_for  # noqa: E402

T_END = 0.65
FX_MODES = [("default", {}), ("full", dict(solver="klu", newton="full")),
            ("reuse", dict(solver="klu", newton="reuse"))]


def fx_run(model, tip, h, kw):
    import flexmbs as fx
    n = steps_for(h, T_END)
    c0 = time.process_time()
    res = fx.simulate(model, n * h, h,
                      settings=SimulationSettings(start="static", store=[tip], **kw))
    return time.process_time() - c0, res


def ex_run(nel, h, sparse, modified, rtol):
    n = steps_for(h, T_END)
    rob = ExudynRobot(nel)
    ss = rob.settings(h, n * h, modified_newton=modified, sparse=sparse, rtol=rtol,
                      static_rtol=_static_rtol(nel))
    c0 = time.process_time()
    t, tip = rob.run(ss)
    return time.process_time() - c0, t, tip, rob.stats


def measure(nel, hs, repeats, log):
    model, _, a2 = robot_flexmbs(nel)
    model.compile()
    model.pattern("klu")
    ex_cfgs = [(True, False), (True, True)] + ([(False, False), (False, True)] if nel <= 32 else [])
    rows = []
    for h in hs:
        klu = klu_costs(model, iteration_matrix(model, h=h))
        rtol = {}
        for cfg in ex_cfgs:             # tightest working tolerance
            for rt in EXUDYN_RTOLS:
                try:
                    ex_run(nel, h, *cfg, rt)
                    rtol[cfg] = rt
                    break
                except ExudynFailed:
                    continue
        best_fx = {name: np.inf for name, _ in FX_MODES}
        best_ex = {cfg: np.inf for cfg in rtol}
        res_fx, res_ex = {}, {}
        for _ in range(repeats):
            for name, kw in FX_MODES:
                c, r = fx_run(model, a2.last, h, kw)
                best_fx[name] = min(best_fx[name], c)
                res_fx[name] = r
            for cfg, rt in rtol.items():
                c, t, tip, st = ex_run(nel, h, *cfg, rt)
                best_ex[cfg] = min(best_ex[cfg], c)
                res_ex[cfg] = (t, tip, st)
        excfg = min(best_ex, key=best_ex.get)
        t_ex = best_ex[excfg]
        et, etip, est = res_ex[excfg]
        dev_ex = deviation30(et, etip)
        for name, _ in FX_MODES:
            r = res_fx[name]
            st = r.stats
            nstep = st["steps"]
            dev = deviation30(r.t, r.position(a2.last))
            floor = (st["factorizations"] * klu["factor"]
                     + (st["newton_iterations"] + st["static_iterations"]) * klu["solve"])
            rows.append(dict(
                elements=nel, h=h, unknowns=st["unknowns"], mode=name, cpu=best_fx[name],
                ex_cpu=t_ex, ex_cfg=f"{'sparse' if excfg[0] else 'dense'}"
                                    f"{' modified' if excfg[1] else ''} {rtol[excfg]:.0e}",
                ratio=t_ex / best_fx[name], us_step=best_fx[name] / nstep * 1e6,
                it_step=st["newton_iterations"] / nstep, fact_step=st["factorizations"] / nstep,
                res_step=st["residual_evaluations"] / nstep, floor_us=floor / nstep * 1e6,
                klu_fact_us=klu["factor"] * 1e6, klu_solve_us=klu["solve"] * 1e6,
                over_floor=best_fx[name] / floor, diff_ex=float(np.max(np.abs(dev - dev_ex)))))
        log(f"  {nel} el/arm h={h:g}: ex {excfg} {t_ex * 1e3:.1f} ms; "
            + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in best_fx.items()))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nel", type=int, nargs="+", default=[2, 8, 32, 128])
    ap.add_argument("--h", type=float, nargs="+", default=[5e-4])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    print(machine_summary())
    rows = []
    for nel in args.nel:
        rows += measure(nel, args.h, args.repeat, print)
    print(format_table(
        ["el/arm", "h", "n", "flexmbs", "cpu ms", "Exudyn best", "ex ms", "ex/fx", "us/step",
         "it/step", "fact/step", "res/step", "KLU fact us", "KLU solve us", "floor us/step",
         "fx/floor", "|fx-ex| m"],
        [[r["elements"], r["h"], r["unknowns"], r["mode"], r["cpu"] * 1e3, r["ex_cfg"],
          r["ex_cpu"] * 1e3, r["ratio"], r["us_step"], r["it_step"], r["fact_step"], r["res_step"],
          r["klu_fact_us"], r["klu_solve_us"], r["floor_us"], r["over_floor"], f"{r['diff_ex']:.1e}"]
         for r in rows],
        title="flexmbs defaults / full / reuse against Exudyn's fastest configuration "
              "(CPU time, min of interleaved repeats)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
