"""Cost of a gradient against the number of variables: finite differences, direct
differentiation and the discrete adjoint, through `Problem.evaluate` (the table of docs/adjoint.md).

Rows:

- robot_2dof (the paper's robot, 4 diameters) with its own constraint, the deviation (28) at
  every step (1301 rows: as many adjoint right-hand sides per step, the case direct
  differentiation is meant for), and with that deviation KS-aggregated (1 functional);
- the hollow tapered robot (cases/robot_2dof_tapered_tubes.toml: an outer diameter and a wall
  thickness per element of each arm) with its KS-aggregated deviation (28) as the only
  constraint (1 functional; the stress response is dropped: direct differentiation of a
  stress stores the derivatives of every node of the arms, nv x 3 (4 E + 2) per step,
  gigabytes at nv = 512) and E elements per arm (overrides bodies.arm1.elements =
  bodies.arm2.elements = E), so nv = 4 E variables; the model grows with E too (3 (4 E + 2)
  coordinates), so every column is also given relative to the simulation of the same model.

With --case-constraints the tapered rows keep the case's own responses and constraints instead:
the KS deviation (28) and the KS stress of both arms (2 functionals; direct differentiation
is then not run beyond 32 variables unless --direct-max says so: the stress's derivatives of
every node of the arms).

For each row it times (wall time, or with --cpu the process's CPU time; best of a few
repeats, sim and adjoint interleaved; --repeat-large for the largest):

- sim: `evaluate(x, gradient=False)`, the simulation and the responses;
- direct: `evaluate(x, gradient='used', method='direct')` (nv right-hand sides per step);
- adjoint: `evaluate(x, gradient='used', method='adjoint')`, and its split (of the best
  repeat): fwd, the core's forward run with the tape (polished: every step converged to the
  rounding level); bwd, the core's backward pass (`_core.simulate_adjoint`); py, the
  rest (model set-up, responses and their per-step partials, memory checks);
- FD: forward finite differences, (nv + 1) simulations: reported as (nv + 1) x sim.

Direct differentiation is not run beyond --direct-max variables (default 128; at 512 it takes
about a minute, at 2048 some 15 minutes: its cost grows like nv x elements).

    nice .venv/bin/python benchmarks/gradient_cost.py [--t-end 0.65] [E ...]   # default 1 8 32 128 512
    nice .venv/bin/python benchmarks/gradient_cost.py --no-robot --case-constraints --cpu 64
"""
import argparse
import importlib
import time

import numpy as np

from flexmbs.problem import Problem

# the modules (flexmbs.analysis.simulate is also the name of a function in the package's namespace)
simulate_module = importlib.import_module("flexmbs.analysis.simulate")
adjoint_module = importlib.import_module("flexmbs.analysis.adjoint")


RESPONSES = [
    {"name": "deviation_28", "type": "deviation",
     "terms": [{"body": "arm1", "at": "A", "component": "y"},
               {"body": "arm2", "at": "tip", "component": "y",
                "relative_to": {"body": "arm1", "at": "A"}}]},
    {"name": "mass", "type": "mass"}]
CONSTRAINT = {"response": "deviation_28", "upper": 1.0e-3, "over": "ks", "parameter": 200.0}
#: the clock of every timing: time.perf_counter (wall), or time.process_time with --cpu
clock = time.perf_counter


class _CoreTimer:
    """Time of the core's forward runs and backward passes during a call (the core's
    functions `simulate_arrays` and `simulate_adjoint_arrays`, as the modules imported them,
    replaced by timed proxies for its duration)."""

    PATCHES = ((simulate_module, "simulate_arrays", "fwd"),
               (adjoint_module, "simulate_arrays", "fwd"),
               (adjoint_module, "simulate_adjoint_arrays", "bwd"))

    def __init__(self):
        self.fwd = self.bwd = 0.0

    def __enter__(self):
        timer = self

        def timed(call, field):
            def run(*a, **kw):
                t0 = clock()
                try:
                    return call(*a, **kw)
                finally:
                    setattr(timer, field, getattr(timer, field) + clock() - t0)
            return run

        self._real = [(m, name, getattr(m, name)) for m, name, _ in self.PATCHES
                      if hasattr(m, name)]
        for m, name, field in self.PATCHES:
            if hasattr(m, name):
                setattr(m, name, timed(getattr(m, name), field))
        return self

    def __exit__(self, *exc):
        for m, name, real in self._real:
            setattr(m, name, real)


def best(f, repeat):
    ts = []
    for _ in range(repeat):
        t0 = clock()
        f()
        ts.append(clock() - t0)
    return min(ts)


def best_split(f, repeat):
    """(total, fwd, bwd) of the fastest of `repeat` calls of f."""
    out = None
    for _ in range(repeat):
        with _CoreTimer() as ct:
            t0 = clock()
            f()
            total = clock() - t0
        if out is None or total < out[0]:
            out = (total, ct.fwd, ct.bwd)
    return out


def row(label, p, repeat, direct_max):
    x = p.start
    nv = x.size
    ndof = p.mechanism.model.ndof
    nf = p.gradient_functionals()
    p.evaluate(x, gradient=False)          # warm-up (model compiled, pattern built)
    ev = {}
    # sim and adjoint interleaved, best of each: the machine's speed drifts (+-30 % on a
    # shared VM), and a ratio of minima taken at different times carries that drift
    t_sim, split = np.inf, None
    for _ in range(repeat):
        t_sim = min(t_sim, best(lambda: p.evaluate(x, gradient=False), 1))
        s = best_split(
            lambda: ev.__setitem__("a", p.evaluate(x, gradient="used", method="adjoint")), 1)
        split = s if split is None or s[0] < split[0] else split
    t_adj, fwd, bwd = split
    py = t_adj - fwd - bwd
    t_fd = (nv + 1) * t_sim
    if nv <= direct_max:
        t_dir = best(lambda: ev.__setitem__("d", p.evaluate(x, gradient="used",
                                                            method="direct")), repeat)
        dj, aj = ev["d"].jacobian, ev["a"].jacobian
        rel = float(np.abs(dj - aj).max() / np.abs(dj).max())
        d_abs, d_rel, note = f"{t_dir:8.2f}", f"{t_dir / t_sim:8.1f}", f"{rel:.0e}"
    else:
        d_abs, d_rel, note = f"{'-':>8}", f"{'-':>8}", "not run"
    print(f"{label:<16} {nv:>5} {ndof:>5} {nf:>4} {t_sim:>7.3f} {t_adj:>8.3f} {d_abs} "
          f"{t_adj / t_sim:>8.2f} {d_rel} {t_fd / t_sim:>7.0f}   "
          f"{fwd / t_sim:>5.2f} {bwd / t_sim:>5.2f} {py / t_sim:>5.2f}   {note}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("elements", nargs="*", type=int, default=[1, 8, 32, 128, 512])
    ap.add_argument("--t-end", type=float, default=0.65)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--repeat-large", type=int, default=1,
                    help="repeats beyond 128 variables (default 1)")
    ap.add_argument("--direct-max", type=int, default=None,
                    help="largest nv for which direct differentiation is run (beyond: '-'; "
                         "default 128, 32 with --case-constraints)")
    ap.add_argument("--no-robot", action="store_true", help="skip the robot_2dof rows")
    ap.add_argument("--case-constraints", action="store_true",
                    help="tapered rows with the case's own KS deviation and KS stress "
                         "constraints (direct not run beyond 32 variables by default)")
    ap.add_argument("--cpu", action="store_true",
                    help="time the process's CPU time instead of the wall time")
    args = ap.parse_args()
    global clock
    if args.cpu:
        clock = time.process_time
    if args.direct_max is None:
        args.direct_max = 32 if args.case_constraints else 128
    t_begin = time.perf_counter()
    print(f"t_end {args.t_end} s, h 5e-4; {'CPU' if args.cpu else 'wall'} times in s (best of {args.repeat}), ratios to sim "
          "of the same model; adjoint split: fwd = forward run with the tape, bwd = backward "
          "pass, py = the rest (Python)")
    print(f"{'case':<16} {'nv':>5} {'ndof':>5} {'nf':>4} {'sim':>7} {'adjoint':>8} {'direct':>8} "
          f"{'adj/sim':>8} {'dir/sim':>8} {'FD/sim':>7}   {'fwd':>5} {'bwd':>5} {'py':>5}   "
          "adjoint - direct")
    if not args.no_robot:
        t = {"time.t_end": args.t_end}
        row("robot_2dof", Problem("robot_2dof", t), 1, args.direct_max)
        row("robot_2dof KS", Problem("robot_2dof", {**t, "constraints.0.over": "ks",
                                                    "constraints.0.parameter": 200.0}),
            args.repeat, args.direct_max)
    for e in args.elements:
        over = {"time.t_end": args.t_end, "bodies.arm1.elements": e, "bodies.arm2.elements": e}
        if not args.case_constraints:
            over.update({"responses": RESPONSES, "constraints": [dict(CONSTRAINT)]})
        p = Problem("robot_2dof_tapered_tubes", over)
        rep = args.repeat if 4 * e <= 128 else args.repeat_large
        row(f"tubes{'+stress' if args.case_constraints else ''} E={e}", p, rep, args.direct_max)
    print(f"total {time.perf_counter() - t_begin:.0f} s")


if __name__ == "__main__":
    main()
