"""The cost of the modal check (flexmbs.analysis.modes) in `flexmbs check`: each shipped case's
convergence check timed whole, beside the part the modal check adds (the coarse run keeping
every coordinate, the modes at 3 configurations and the vibration shares), median of 3 runs;
and the modes it names at h/4 (the ladder's finest step) with each response's Richardson status.

    python benchmarks/modal_check_cost.py [CASE ...]
"""
import statistics
import sys
import time
import warnings

from flexmbs.analysis.accuracy import convergence_check
from flexmbs.model.casefile import available_cases
from flexmbs.problem import Problem

CASES = sys.argv[1:] or available_cases()


def median_time(f, n=3):
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


warnings.simplefilter("ignore")
print(f"{'case':28s} {'check (s)':>10s} {'modal (s)':>10s} {'store all (s)':>14s} {'share':>7s}"
      "  modes named at h/4")
for case in CASES:
    prob = Problem(case)
    whole = median_time(lambda: convergence_check(prob))
    result = prob.simulate(store="all")
    modal = median_time(lambda: prob.modal_check(None, result))
    store = median_time(lambda: prob.simulate(store="all")) - median_time(
        lambda: prob.simulate())
    ev = prob.evaluate(gradient=False, error=True)
    named = "; ".join(f"{n} ({e.status}): " + ", ".join(f"{u.frequency:.0f} Hz"
                                                      for u in e.unresolved)
                      for n, e in ev.errors.items() if e.unresolved) or "none"
    print(f"{case:28s} {whole:10.3f} {modal:10.3f} {store:14.3f} "
          f"{100 * (modal + max(store, 0.0)) / whole:6.1f} %  {named}")
