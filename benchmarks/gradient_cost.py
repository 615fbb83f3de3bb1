"""Cost of a gradient against the number of variables: finite differences, direct
differentiation and the discrete adjoint, through `Problem.evaluate` (issue 18's table).

The hollow tapered robot (cases/robot_2dof_tapered_tubes.toml: an outer diameter and a wall
thickness per element of each arm) with its KS-aggregated deviation (28) as the only
constraint (1 functional; the stress response is dropped: direct differentiation of a stress
stores the derivatives of every node of the arms, nv x 3 (4 E + 2) per step, gigabytes at
nv = 512) and E elements per arm (overrides bodies.arm1.elements = bodies.arm2.elements =
E), so nv = 4 E variables; the model grows with E too (3 (4 E + 2) coordinates), so every
column is also given relative to the simulation of the same model. For each E it times (best
of a few repeats; one for the largest):

- sim: `evaluate(x, gradient=False)`, the simulation and the responses;
- direct: `evaluate(x, gradient='used', method='direct')` (nv right-hand sides per step);
- adjoint: `evaluate(x, gradient='used', method='adjoint')` (forward run with the tape, one
  backward pass with 1 right-hand side per step, the responses' per-step partials);
- FD: forward finite differences, (nv + 1) simulations: reported as (nv + 1) x sim; measured
  (nv + 1 evaluations without gradient) at the smallest E only, to confirm the estimate.

Direct differentiation is not run beyond --direct-max variables (default 512; at 2048 it
would take some 15 minutes: its cost grows like nv x elements).

    nice .venv/bin/python benchmarks/gradient_cost.py [--t-end 0.65] [E ...]   # default 4 8 16 32 64 128 512
"""
import argparse
import time

import numpy as np

from flexmbs.problem import Problem


RESPONSES = [
    {"name": "deviation_28", "type": "deviation",
     "terms": [{"body": "arm1", "at": "A", "component": "y"},
               {"body": "arm2", "at": "tip", "component": "y",
                "relative_to": {"body": "arm1", "at": "A"}}]},
    {"name": "mass", "type": "mass"}]
CONSTRAINT = {"response": "deviation_28", "upper": 1.0e-3, "over": "ks", "parameter": 200.0}


def best(f, repeat):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("elements", nargs="*", type=int, default=[4, 8, 16, 32, 64, 128, 512])
    ap.add_argument("--t-end", type=float, default=0.65)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--direct-max", type=int, default=512,
                    help="largest nv for which direct differentiation is run (beyond: '-')")
    args = ap.parse_args()
    t_begin = time.perf_counter()
    print(f"robot_2dof_tapered_tubes, t_end {args.t_end} s, h 5e-4, KS deviation (28) (1 "
          "functional); times in s, ratios to sim of the same model")
    print(f"{'E/arm':>5} {'nv':>5} {'ndof':>5} {'sim':>7} {'direct':>8} {'adjoint':>8} "
          f"{'FD est':>8} {'direct/sim':>10} {'adjoint/sim':>11} {'FD/sim':>7} "
          f"{'FD/adjoint':>10} {'direct/adjoint':>14}")
    fd_check = None
    for k, e in enumerate(args.elements):
        p = Problem("robot_2dof_tapered_tubes", {
            "time.t_end": args.t_end, "bodies.arm1.elements": e, "bodies.arm2.elements": e,
            "responses": RESPONSES, "constraints": [dict(CONSTRAINT)]})
        x = p.start
        nv = x.size
        ndof = p.mechanism.model.ndof
        rep = args.repeat if nv <= 128 else 1
        p.evaluate(x, gradient=False)          # warm-up (model compiled, pattern built)
        t_sim = best(lambda: p.evaluate(x, gradient=False), rep + 1)
        ev = {}
        t_adj = best(lambda: ev.__setitem__("a", p.evaluate(x, gradient="used",
                                                            method="adjoint")), rep)
        t_fd = (nv + 1) * t_sim
        if nv <= args.direct_max:
            t_dir = best(lambda: ev.__setitem__("d", p.evaluate(x, gradient="used",
                                                                method="direct")), rep)
            dj, aj = ev["d"].jacobian, ev["a"].jacobian
            rel = float(np.abs(dj - aj).max() / np.abs(dj).max())
            direct = (f"{t_dir:>8.2f}", f"{t_dir / t_sim:>10.1f}", f"{t_dir / t_adj:>14.1f}",
                      f"   (adjoint - direct: {rel:.0e})")
        else:
            direct = (f"{'-':>8}", f"{'-':>10}", f"{'-':>14}", "   (direct not run)")
        print(f"{e:>5} {nv:>5} {ndof:>5} {t_sim:>7.3f} {direct[0]} {t_adj:>8.2f} {t_fd:>8.2f} "
              f"{direct[1]} {t_adj / t_sim:>11.1f} {t_fd / t_sim:>7.0f} "
              f"{t_fd / t_adj:>10.1f} {direct[2]}{direct[3]}", flush=True)
        if k == 0:
            t0 = time.perf_counter()
            for i in range(nv + 1):
                xi = x.copy()
                if i:
                    xi[i - 1] *= 1 + 1e-6
                p.evaluate(xi, gradient=False)
            fd_check = (nv, time.perf_counter() - t0, t_fd)
    if fd_check:
        nv, meas, est = fd_check
        print(f"forward FD measured at nv = {nv}: {nv + 1} evaluations {meas:.2f} s "
              f"(estimate (nv + 1) x sim: {est:.2f} s)")
    print(f"total {time.perf_counter() - t_begin:.0f} s")


if __name__ == "__main__":
    main()
