"""Cost of design sensitivities for the robot.

Prints, measured side by side in one run: the wall time of a plain simulation, of a
simulation with direct sensitivities for the 4 design variables, and of forward finite
differences (the paper's method: 1 + 4 simulations), and their ratios. Each timing is the
best of `repeat` runs. Usage: python benchmarks/sensitivity.py [--repeat N]
"""
import argparse
import time

import numpy as np

from flexmbs.problem import Problem


def best_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def run(quick=False, outdir=None, log=print, repeat=None):
    """Entry point of benchmarks/run.py."""
    return measure(repeat or (3 if quick else 7), log)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args(argv)
    return measure(args.repeat, print)


def measure(repeat, log):
    p = np.array([39.29, 28.33, 34.94, 25.19])
    rows = []
    for mode in ("full", "reuse", "auto"):
        prob = Problem("robot_2dof", overrides={"time.newton": mode})

        def forward_differences():
            base = prob.evaluate(p, gradient=False)
            for k in range(p.size):
                q = p.copy()
                q[k] *= 1 + 1e-6
                prob.evaluate(q, gradient=False)
            return base

        t_sim = best_time(lambda: prob.evaluate(p, gradient=False), repeat)
        t_dir = best_time(lambda: prob.evaluate(p, gradient=True), repeat)
        t_fd = best_time(forward_differences, repeat)
        rows.append((mode, t_sim, t_dir, t_fd))
    log("robot_2dof, Table 1 design, 1301 steps, 4 design variables (best of %d)" % repeat)
    log(f"{'Newton':>9} {'simulation':>11} {'+direct':>9} {'forward FD':>11} "
          f"{'direct/sim':>11} {'FD/sim':>8} {'FD/direct':>10}")
    for name, ts, td, tf in rows:
        log(f"{name:>9} {ts * 1e3:9.1f}ms {td * 1e3:7.1f}ms {tf * 1e3:9.1f}ms "
              f"{td / ts:11.2f} {tf / ts:8.2f} {tf / td:10.2f}")
    return rows


if __name__ == "__main__":
    main()
