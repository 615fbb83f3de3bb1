"""Per-call cost of the compiled core's boundary, two builds side by side.

Each child process (one build's interpreter) times, after a warm-up, the CPU time of the process
per call (the least over 5 blocks of calls of their mean: the least loaded block of a shared
machine):

- short: `simulate` of the robot (cases/robot_2dof.toml, start design, klu) over 3 steps, where
  sending and building the model dominates the call; short_core: of it, the compiled call
  (flexmbs.analysis.simulate's `simulate_arrays`: argument conversion, the model's set-up, the
  3 steps);
- sysmat: `system_matrices` of the robot at its reference configuration (dense);
- evaluate: `Problem("robot_2dof").evaluate(x)` (the whole run, 1301 time points, direct
  differentiation) and with method='adjoint', x the start design scaled by 1 + 1e-3 k at the
  k-th call (the same designs in every child).

The driver runs the children of the builds in turn (A, B, A, B, ...: the machine's speed drifts
between minutes) and prints, per quantity, the median over the rounds of each build and the
median over the rounds of the ratio B / A of the round's two children.

    .venv/bin/python benchmarks/core_overhead.py --rounds 5 A=/path/a/.venv/bin/python B=.venv/bin/python
    .venv/bin/python benchmarks/core_overhead.py --elements 200 --eval 0 --adjoint 0 A=... B=...
"""
import argparse
import json
import math
import statistics
import subprocess
import sys
import time


def child(n_short, n_eval, n_adjoint, elements):
    import warnings

    import numpy as np

    import flexmbs as fx
    import flexmbs.analysis.simulate as simulate_module
    from flexmbs.analysis.simulate import system_matrices
    from flexmbs.problem import Problem

    warnings.simplefilter("ignore")
    cpu = time.process_time
    prob = Problem("robot_2dof", {"bodies.arm1.elements": elements,
                                  "bodies.arm2.elements": elements} if elements else None)
    mech = prob.mechanism
    model = mech.set_design(mech.start)
    h = mech.h
    q = model.reference_coordinates()

    def per_call(f, n, blocks=5):
        """CPU time per call: the least over `blocks` blocks of n / blocks calls of their mean
        (the least loaded block of a shared machine)."""
        f(0)
        best, k = math.inf, 1
        for _ in range(blocks):
            t0 = cpu()
            for _ in range(max(n // blocks, 1)):
                f(k)
                k += 1
            best = min(best, (cpu() - t0) / max(n // blocks, 1))
        return best

    def design(k):     # another design each call (evaluate keeps the last design's results)
        return np.asarray(mech.start, float) * (1 + 1e-3 * k)

    real, inside = simulate_module.simulate_arrays, []

    def timed(**kw):       # the compiled call as simulate makes it (where_time_goes.py)
        t0 = cpu()
        try:
            return real(**kw)
        finally:
            inside.append(cpu() - t0)

    # KLU in the settings object; a build without SimulationSettings (commit 3cacae5) takes it
    # as simulate's keyword
    klu = (dict(settings=fx.SimulationSettings(solver="klu"))
           if hasattr(fx, "SimulationSettings") else dict(solver="klu"))
    simulate_module.simulate_arrays = timed
    out = dict(short=per_call(lambda k: fx.simulate(model, 3 * h, h, **klu), n_short))
    blocks = np.array(inside[1:1 + 5 * (n_short // 5)]).reshape(5, -1)
    out["short_core"] = float(blocks.mean(axis=1).min())
    simulate_module.simulate_arrays = real
    out["sysmat"] = per_call(lambda k: system_matrices(model, q), n_short)
    if n_eval:
        out["evaluate"] = per_call(lambda k: prob.evaluate(design(k), method="direct"), n_eval)
    if n_adjoint:
        out["evaluate_adjoint"] = per_call(lambda k: prob.evaluate(design(k), method="adjoint"),
                                           n_adjoint)
    print(json.dumps(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("builds", nargs="*", help="NAME=python of a build (two or more)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--short", type=int, default=200, help="calls of the short run per child")
    ap.add_argument("--eval", type=int, default=5, help="evaluations per child")
    ap.add_argument("--adjoint", type=int, default=2, help="adjoint evaluations per child")
    ap.add_argument("--elements", type=int, default=0,
                    help="elements per arm (overrides bodies.arm1/arm2.elements; 0: the case's)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.short, a.eval, a.adjoint, a.elements)
        return
    builds = [b.split("=", 1) for b in a.builds]
    got = {name: [] for name, _ in builds}
    for r in range(a.rounds):
        for name, py in builds:
            res = subprocess.run([py, __file__, "--child", "--short", str(a.short), "--eval",
                                  str(a.eval), "--adjoint", str(a.adjoint),
                                  "--elements", str(a.elements)], capture_output=True, text=True, check=True)
            got[name].append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1} {name}: {got[name][-1]}", file=sys.stderr, flush=True)
    keys = list(got[builds[0][0]][0])
    first = builds[0][0]
    print(f"{'quantity':18s}" + "".join(f"{name:>14s}" for name, _ in builds)
          + "   median of the rounds' ratios to " + first)
    for k in keys:
        med = {name: statistics.median(x[k] for x in got[name]) for name, _ in builds}
        # the ratio of each round's neighbouring children (their machine speed is alike)
        pair = {name: statistics.median(b[k] / f[k] for b, f in zip(got[name], got[first]))
                for name, _ in builds[1:]}
        print(f"{k:18s}" + "".join(f"{med[name] * 1e3:12.3f}ms" for name, _ in builds)
              + "   " + " ".join(f"{pair[name]:.3f}" for name, _ in builds[1:]))


if __name__ == "__main__":
    main()
