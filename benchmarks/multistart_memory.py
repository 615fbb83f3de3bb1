"""Memory a multi-start keeps per start besides its drawn design (START_RECORD_BYTES in
flexmbs.methods.multistart): the job (start, options), its fingerprint for the store, and its
result record and optimum, built as `multistart` builds them for N starts of the four-bar
(cases/fourbar.toml), measured by tracemalloc.

Run: ``.venv/bin/python benchmarks/multistart_memory.py`` (a few seconds)."""
from __future__ import annotations

import tracemalloc

import numpy as np

from flexmbs.model.fingerprint import fingerprint
from flexmbs.model.options import FullyOptions
from flexmbs.problem import Problem

N = 5000


def main():
    prob = Problem("fourbar")
    options = FullyOptions().as_dict()
    x0 = np.random.default_rng(0).uniform(15.0, 500.0, (N, 3))
    tracemalloc.start()
    a = tracemalloc.get_traced_memory()[0]
    jobs = {f"start{k:03d}": dict(case=prob.description, start=x.tolist(), optimizer="auto",
                                  options=options) for k, x in enumerate(x0)}
    b = tracemalloc.get_traced_memory()[0]
    fps = {name: fingerprint(prob.description, "multistart start",
                             dict(start=job["start"], optimizer="auto", options=options))
           for name, job in jobs.items()}
    c = tracemalloc.get_traced_memory()[0]
    out = {name: dict(start=list(j["start"]), design=list(j["start"]), objective=1.0,
                      max_violation=0.0, converged=True,
                      reason="converged: the KKT residual is below eps", simulations=20,
                      wall_time_s=1.0, optimizer_share=0.1, grid=None)
           for name, j in jobs.items()}
    optima = [dict(o, feasible=True, recheck_grid=None) for o in out.values()]
    d = tracemalloc.get_traced_memory()[0]
    assert len(fps) == len(optima) == N
    print(f"bytes per start: job {(b - a) / N:.0f}, fingerprint {(c - b) / N:.0f}, "
          f"result and optimum {(d - c) / N:.0f}, total {(d - a) / N:.0f}")


if __name__ == "__main__":
    main()
