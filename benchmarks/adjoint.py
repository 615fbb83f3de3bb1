"""Cost of a gradient by the discrete adjoint against direct differentiation (issue 18).

The robot of the paper (cases/robot_2dof.toml: 0.65 s, h = 5e-4, static start), one aggregated
functional (KS of the tip deviation, or here the weighted sum the adjoint sees), nv design
variables made by combining the case's section derivatives at random (the cost of both methods
does not depend on what the variables are, only on how many). Prints, for each nv, the wall
time of a plain simulation, of a simulation with direct differentiation, and of the adjoint
gradient (forward run storing every state + backward pass), and their ratios.

    .venv/bin/python benchmarks/adjoint.py [nv ...]      # default: 4 32 128 512
"""
import sys
import time

import numpy as np

from flexmbs.adjoint import adjoint_gradient, simulate_for_adjoint
from flexmbs.problem import Problem
from flexmbs.simulate import simulate


def best(f, repeat=2):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def main(nvs):
    p = Problem("robot_2dof", {"time.newton": "full"})
    mech = p.mechanism
    x = mech.start
    model = mech.set_design(x)
    ts = p.description.time
    q0, qd0 = mech.initial_state()
    kw = dict(rho_inf=ts.rho_inf, start=ts.start, newton="full", q0=q0,
              qd0=None if ts.start == "static" else qd0)
    base = mech.element_property_derivatives(x)
    t_sim, run = best(lambda: simulate(model, mech.t_end, ts.h, **kw))
    nt = run.t.size
    print(f"robot_2dof: {nt - 1} steps, {model.ndof} coordinates, start {ts.start}; "
          f"simulation {t_sim:.3f} s")
    print(f"{'nv':>6} {'direct s':>9} {'adjoint s':>10} {'direct/sim':>11} {'adjoint/sim':>12} "
          f"{'backward/sim':>13}")
    t_fwd, fwd = best(lambda: simulate_for_adjoint(model, mech.t_end, ts.h, **kw))
    rng = np.random.default_rng(0)
    for nv in nvs:
        dprop = np.einsum("kev,vw->kew", base, rng.standard_normal((base.shape[2], nv)))
        t_dir, _ = best(lambda: simulate(model, mech.t_end, ts.h, design_derivatives=dprop,
                                         sensitivity_dofs=np.arange(model.ndof), **kw), 1)

        def adjoint():
            r = simulate_for_adjoint(model, mech.t_end, ts.h, **kw)
            gq = np.zeros((nt, model.ndof))
            gq[:, 0] = 1.0 / nt
            return adjoint_gradient(model, r, dprop, gq)

        t_adj, _ = best(adjoint, 2)
        gq = np.zeros((nt, model.ndof))
        gq[:, 0] = 1.0 / nt
        t_back, _ = best(lambda: adjoint_gradient(model, fwd, dprop, gq), 2)
        print(f"{nv:>6} {t_dir:>9.3f} {t_adj:>10.3f} {t_dir / t_sim:>11.2f} {t_adj / t_sim:>12.2f} "
              f"{t_back / t_sim:>13.2f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [4, 32, 128, 512])
