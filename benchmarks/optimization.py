"""Table 1 (robot, deviation (28), 0.65 s, start 50 mm) by both methods, with direct
sensitivities and with the paper's finite differences: wall time, simulations,
factorizations, iterations. Usage: python benchmarks/optimization.py
"""
import time

from flexmbs.cases import load_case
from flexmbs.optimize import optimize_fully, optimize_weakly
from flexmbs.simulate import simulate

_count = {"factorizations": 0}


def _counting(simulate_fn):
    def wrapped(*args, **kw):
        r = simulate_fn(*args, **kw)
        _count["factorizations"] += r.stats["factorizations"]
        return r
    return wrapped


def run(quick=False, outdir=None, log=print):
    import flexmbs.cases
    import flexmbs.sensitivity
    # count factorizations of every simulation the optimizers run
    flexmbs.cases._simulate = _counting(simulate)
    flexmbs.sensitivity.simulate = _counting(simulate)
    case = load_case("robot_2dof")
    rows = []
    runs = [("weakly", "-", lambda: optimize_weakly(case, [50, 50, 50, 50])),
            ("fully", "direct", lambda: optimize_fully(case, [50, 50, 50, 50], sensitivity="direct")),
            ("fully", "fd", lambda: optimize_fully(case, [50, 50, 50, 50], sensitivity="fd"))]
    for method, sens, fn in runs:
        _count["factorizations"] = 0
        t0 = time.perf_counter()
        res = fn()
        wall = time.perf_counter() - t0
        rows.append((method, sens, res.mass_kg, res.iterations, res.simulations,
                     _count["factorizations"], wall, res.converged))
    log("Table 1 (robot, (28), 0.65 s, start [50, 50, 50, 50] mm); paper: 0.962 kg both methods")
    log(f"{'method':>7} {'sens.':>7} {'mass kg':>8} {'iter':>5} {'sims':>5} {'factorizations':>15} "
        f"{'wall s':>7} converged")
    for method, sens, mass, it, sims, nf, wall, conv in rows:
        log(f"{method:>7} {sens:>7} {mass:8.4f} {it:5d} {sims:5d} {nf:15d} {wall:7.2f} {conv}")
    direct = next(r for r in rows if r[1] == "direct")
    fd = next(r for r in rows if r[1] == "fd")
    log(f"fully coupled: finite differences / direct = {fd[6] / direct[6]:.2f} in wall time, "
        f"{fd[4] / direct[4]:.2f} in simulations")
    return rows


if __name__ == "__main__":
    run()
