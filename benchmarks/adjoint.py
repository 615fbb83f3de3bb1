"""Cost of a gradient by the discrete adjoint against direct differentiation.

The robot of the paper (cases/robot_2dof.toml: 0.65 s, h = 5e-4, static start, the case's
automatic Newton), one functional (a weighted sum over the history, what the adjoint sees of
a KS aggregate), nv design variables made by combining the case's section derivatives at
random (the cost of both methods depends on how many variables there are, not on what they
are). Prints, for each nv, the wall time of a plain simulation, of a simulation with direct
differentiation, and of the adjoint gradient (its forward run keeping the tape, polished, plus
the backward pass), and their ratios to the simulation (best of a few repeats).

    .venv/bin/python benchmarks/adjoint.py [nv ...]      # default: 4 32 128 512
"""
import sys
import time

import numpy as np

from flexmbs.analysis.adjoint import adjoint_gradient, simulate_for_adjoint
from flexmbs.analysis.simulate import simulate
from flexmbs.problem import Problem
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions


def best(f, repeat=3):
    ts = []
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def main(nvs):
    p = Problem("robot_2dof")
    mech = p.mechanism
    x = mech.start
    model = mech.set_design(x)
    ts = p.description.time
    q0, qd0 = mech.initial_state()
    kw = dict(settings=p.settings,
              initial=InitialConditions(q0=q0, qd0=None if ts.start == "static" else qd0))
    base = mech.element_property_derivatives(x)
    t_sim, run = best(lambda: simulate(model, mech.t_end, ts.h, **kw))
    t_fwd, fwd = best(lambda: simulate_for_adjoint(model, mech.t_end, ts.h, **kw))
    nt = run.t.size
    gq = np.zeros((nt, model.ndof))
    gq[:, 0] = 1.0 / nt
    print(f"robot_2dof: {nt - 1} steps, {model.ndof} coordinates, start {ts.start}, newton "
          f"{ts.newton}; simulation {t_sim:.3f} s, adjoint's forward run (tape, polished) "
          f"{t_fwd:.3f} s = {t_fwd / t_sim:.2f} simulations")
    print(f"{'nv':>6} {'direct s':>9} {'adjoint s':>10} {'direct/sim':>11} {'adjoint/sim':>12} "
          f"{'backward/sim':>13}")
    rng = np.random.default_rng(0)
    for nv in nvs:
        dprop = np.einsum("kev,vw->kew", base, rng.standard_normal((base.shape[2], nv)))
        t_dir, _ = best(lambda: simulate(model, mech.t_end, ts.h,
                                         derivatives=DesignDerivatives(properties=dprop,
                                                                       dofs=np.arange(model.ndof)),
                                         **kw),
                        3 if nv <= 128 else 1)
        t_back, _ = best(lambda: adjoint_gradient(model, fwd, dprop, gq))
        t_adj = t_fwd + t_back
        print(f"{nv:>6} {t_dir:>9.3f} {t_adj:>10.3f} {t_dir / t_sim:>11.2f} {t_adj / t_sim:>12.2f} "
              f"{t_back / t_sim:>13.2f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [4, 32, 128, 512])
