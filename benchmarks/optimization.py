"""Table 1 (robot, deviation (28), 0.65 s, start 50 mm) by both methods and every fully
coupled optimizer: wall time, simulations, factorizations, iterations.
Usage: python benchmarks/optimization.py
"""
import time

from flexmbs.analysis.simulate import simulate
from flexmbs.optimize import optimize_fully, optimize_weakly
import flexmbs.problem
from flexmbs.problem import Problem

_count = {"factorizations": 0}


def _counting(simulate_fn):
    def wrapped(*args, **kw):
        r = simulate_fn(*args, **kw)
        _count["factorizations"] += r.stats["factorizations"]
        return r
    return wrapped


def run(quick=False, outdir=None, log=print):
    # count factorizations of every simulation the optimizers run
    flexmbs.problem.simulate = _counting(simulate)
    prob = Problem("robot_2dof")
    rows = []
    start = [50, 50, 50, 50]
    runs = [("weakly", "-", lambda: optimize_weakly(prob, start)),
            ("fully", "mma", lambda: optimize_fully(prob, start, optimizer="mma")),
            ("fully", "sqp", lambda: optimize_fully(prob, start, optimizer="sqp"))]
    for method, opt, fn in runs:
        _count["factorizations"] = 0
        t0 = time.perf_counter()
        res = fn()
        wall = time.perf_counter() - t0
        rows.append((method, opt, res.mass_kg, res.iterations, res.simulations,
                     _count["factorizations"], wall, res.converged))
    log("Table 1 (robot, (28), 0.65 s, start [50, 50, 50, 50] mm); paper: 0.962 kg both methods")
    log(f"{'method':>7} {'optim.':>7} {'mass kg':>8} {'iter':>5} {'sims':>5} "
        f"{'factorizations':>15} {'wall s':>7} converged")
    for method, opt, mass, it, sims, nf, wall, conv in rows:
        log(f"{method:>7} {opt:>7} {mass:8.4f} {it:5d} {sims:5d} {nf:15d} {wall:7.2f} {conv}")
    return rows


if __name__ == "__main__":
    run()
