"""Non-uniform step grids (flexmbs.analysis.simulate's `steps`, ga_settings%tgrid in the core) and
error-controlled steps (time.h = "auto", flexmbs.analysis.adaptive), docs/accuracy.md.

Generalized-alpha is second order on a smoothly varying grid too (the step of every interval
in the predictor, eqs. 3-5, and in the iteration matrix, eq. 7), and on a grid whose step
keeps changing by a fixed ratio (the acceleration variable a rescaled at every change of
step, docs/adjoint.md (A0)); on a grid frozen for an
optimization run the responses are smooth in the design, so direct differentiation and the
discrete adjoint (their seeds carried through the output interpolation's transpose) are
exact derivatives of them (Taylor tests)."""
import warnings

import numpy as np
import pytest
from scipy.linalg import eigh

import flexmbs as fx
from flexmbs.analysis.adaptive import subdivide
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings
from flexmbs.analysis.simulate import interpolation_matrix, simulate, system_matrices
from flexmbs.errors import CaseError
from flexmbs.problem import Problem


def _runs(case, over):
    p = Problem(case, over)
    model, t_end, h, kw = p._run(None, False, None, "all")
    return p, model, t_end, h, kw


def test_interpolation_is_exact_for_cubics():
    """interpolation_matrix: cubic Lagrange through 4 grid points reproduces any cubic
    polynomial exactly (to rounding, 1e-12 relative) on a random non-uniform grid, at the ends
    too, and takes the grid value itself at a grid time (weights exactly 1 and 0)."""
    rng = np.random.default_rng(1)
    tg = np.concatenate([[0.0], np.sort(rng.uniform(0, 1, 30)), [1.0]])
    t = np.linspace(0, 1, 101)
    w = interpolation_matrix(tg, t)
    c = rng.standard_normal(4)
    y = np.polyval(c, tg)
    assert np.abs(w @ y - np.polyval(c, t)).max() < 1e-12 * np.abs(y).max()
    w2 = interpolation_matrix(tg, tg[5:9])
    assert np.array_equal(w2.toarray(), np.eye(tg.size)[5:9])


def test_uniform_times_give_the_fixed_step_solution():
    """The core's non-uniform path on the times j h of the uniform grid repeats the fixed-step
    run (robot, 0.1 s, full Newton): the same states to 1e-12 m (only the times' rounding
    differs)."""
    p, model, t_end, h, kw = _runs("robot_2dof", {"time.t_end": 0.1, "time.newton": "full"})
    fixed = simulate(model, t_end, h, **kw)
    grid = simulate(model, t_end, h, steps=h * np.arange(fixed.t.size), **kw)
    assert grid.steps is not None and grid.stats["steps"] == fixed.stats["steps"]
    assert np.abs(grid.q - fixed.q).max() < 1e-12


def test_second_order_on_a_smoothly_varying_grid():
    """Robot (cases/robot_2dof.toml, 0.2 s): steps from the map t(s) = T (s + 0.3
    sin(2 pi s) / (2 pi)) (neighbouring steps differ by O(1/N), longest / shortest 1.86);
    halving every step divides the largest error of every coordinate, against a fixed-step
    run 16 times finer than the finest grid, by 4: observed orders in [1.8, 2.2]
    (generalized-alpha's second order, Chung & Hulbert 1993). Measured: 2.08, 2.00."""
    p, model, t_end, h, kw = _runs("robot_2dof", {"time.t_end": 0.2, "time.newton": "full"})
    ref = simulate(model, t_end, h / 32, **kw)

    def grid(n):
        s = np.linspace(0, 1, n + 1)
        return t_end * (s + 0.3 * np.sin(2 * np.pi * s) / (2 * np.pi))

    err = [np.abs(simulate(model, t_end, h, steps=grid(n), **kw).q - ref.q[::32]).max()
           for n in (200, 400, 800)]
    orders = np.log2(np.array(err[:-1]) / np.array(err[1:]))
    assert np.all((orders > 1.8) & (orders < 2.2)), (err, orders)


def _cantilever_mode():
    """A steel cantilever (1 m, circle of 20 mm, 2 quadratic elements) set swinging in its
    lowest mode at small amplitude (largest coordinate 1e-4 m: linear to 1e-8): the model, its
    reference coordinates, the free coordinates, the mass matrix on them, the mode (M-normalised),
    omega and the amplitude of the modal coordinate."""
    m = fx.Model("cantilever")
    b = m.add_beam("beam", (0, 0), (1.0, 0), 2, section=fx.Circle(0.02),
                   material=fx.Material(E=210e9, nu=0.3, rho=7800))
    m.clamp(b.first)
    ref = m.reference_coordinates()
    _, k = system_matrices(m, ref)
    _, mm = system_matrices(m, ref, cm=1.0, ck=0.0)
    free = np.setdiff1d(np.arange(m.ndof), b.dofs[:3])
    k, mm = k[np.ix_(free, free)], mm[np.ix_(free, free)]
    w2, vecs = eigh(k, mm)
    amp = 1e-4 / np.abs(vecs[:, 0]).max()
    return m, ref, free, mm, vecs[:, 0], float(np.sqrt(w2[0])), amp


def test_second_order_when_the_step_alternates():
    """Steps alternating h and 1.5 h (the ratio kept as h is halved): the lowest mode of a
    cantilever at small amplitude (a linear oscillator, omega = 91 rad/s, the higher modes not
    excited) over two periods. Against the analytic eta(t) = A sin(omega t) (eta the modal
    coordinate) the largest error of eta, eta' and eta'' at the grid points, relative to
    A, A omega, A omega^2, falls by 4 per halving: observed orders in [1.9, 2.1]. The
    acceleration variable a_n approximates qdd(t_n + (alpha_m - alpha_f) h) (Arnold & Bruls
    2007, Multibody Syst Dyn 18:185-202): without its rescaling at a change of step, an O(h)
    inconsistency at every change, the orders fell to 1.95, 1.85, 1.60, 1.27 (eta') and the
    finest errors were 1.9-2.5x larger. Measured: 1.992 .. 2.000 (errors 2.7e-2 to 9.4e-5)."""
    m, ref, free, mm, mode, omega, amp = _cantilever_mode()
    period = 2 * np.pi / omega
    qd0 = np.zeros(m.ndof)
    qd0[free] = amp * omega * mode
    err = []
    for n in (50, 100, 200, 400, 800):
        steps = np.tile([1.0, 1.5], n) * 2 * period / (2.5 * n)
        g = np.concatenate([[0.0], np.cumsum(steps)])
        r = fx.simulate(m, g[-1], g[-1] / (2 * n),
                        settings=SimulationSettings(tol=1e-14, validity="off"),
                        initial=InitialConditions(qd0=qd0), steps=g, tape=True)
        cols = np.asarray(r.tape["grid"])[: g.size] - 1
        eta = [(r.tape[k][free][:, cols] - (ref[free, None] if k == "q" else 0)).T @ mm @ mode
               for k in ("q", "qd", "qdd")]
        s, c = np.sin(omega * g), np.cos(omega * g)
        err.append([np.abs(eta[0] - amp * s).max() / amp,
                    np.abs(eta[1] - amp * omega * c).max() / (amp * omega),
                    np.abs(eta[2] + amp * omega ** 2 * s).max() / (amp * omega ** 2)])
    err = np.array(err)
    orders = np.log2(err[:-1] / err[1:])
    assert np.all((orders > 1.9) & (orders < 2.1)), (err, orders)


def _adaptive_robot():
    return Problem("robot_2dof", {"time.t_end": 0.05, "time.h": "auto", "time.rtol": 1e-2,
                                  "time.newton": "full", "constraints.0.over": "ks"})


def test_frozen_grid_direct_and_adjoint_gradients_agree():
    """Robot from static equilibrium, 0.05 s, time.h = "auto" (rtol 1e-2): the grid chosen at
    the start design is non-uniform and stays the same at another design; on it the KS
    deviation constraint's gradient by the discrete adjoint equals direct differentiation
    (both through the output interpolation) to 1e-8 relative, with the tape of every step and
    with checkpoints every 5 steps (segments re-run on the same grid), as on a uniform grid
    (tests/test_adjoint.py). Measured: 32 steps of 0.97 to 2 ms (outputs every 0.5 ms),
    3e-11."""
    p = _adaptive_robot()
    x = np.asarray(p.start, float)
    direct = p.evaluate(x, method="direct")
    g = p.steps()
    assert np.ptp(np.diff(g)) > 0.1 * np.diff(g).max()          # really non-uniform
    adj = p.evaluate(x, method="adjoint")
    assert p.evaluate(0.9 * x, gradient=False) is not None and p.steps() is g
    rel = np.abs(adj.jacobian - direct.jacobian).max() / np.abs(direct.jacobian).max()
    assert rel < 1e-8, rel
    # the checkpointed adjoint re-runs its segments on the same grid
    ck = Problem(p.description, checkpoints=5)
    ck._steps = g
    rel = np.abs(ck.evaluate(x, method="adjoint").jacobian - direct.jacobian).max() \
        / np.abs(direct.jacobian).max()
    assert rel < 1e-8, rel


@pytest.mark.parametrize("method", ["direct", "adjoint"])
def test_frozen_grid_gradients_pass_the_taylor_test(method):
    """Taylor test on the frozen grid (robot, 0.05 s, "auto", KS of the deviation): the
    central-difference remainder |(g(x + s d) - g(x - s d)) / 2s - J d| of the direct and of
    the adjoint gradient falls as s^2, observed orders in [1.8, 2.2] over s = 0.02 .. 1.25e-3
    (relative to the design), as on a uniform grid (tests/test_adjoint.py). Measured: 1.996 ..
    2.000 for both; with the slope 1 % off the orders are -0.37 .. -0.005 (the test can
    fail)."""
    p = _adaptive_robot()
    x = np.asarray(p.start, float)
    ev = p.evaluate(x, method=method)
    d = np.array([0.6, -0.3, 0.8, 0.5]) * x
    slope = float(ev.jacobian[0] @ d)
    rem = []
    for s in [0.02 / 2**k for k in range(5)]:
        gp = p.evaluate(x + s * d, gradient=False).constraints[0]
        gm = p.evaluate(x - s * d, gradient=False).constraints[0]
        rem.append(abs((gp - gm) / (2 * s) - slope))
    orders = np.log2(np.array(rem[:-1]) / np.array(rem[1:]))
    assert np.all((orders > 1.8) & (orders < 2.2)), (rem, orders)


def test_achieved_error_is_near_the_tolerance():
    """The robot's point-to-point move with a damped dwell (cases/robot_2dof_dwell.toml,
    0.4 s), time.h = "auto" with rtol = 1e-3: the tip deviation's largest error (relative to
    its largest value) against fixed steps h/8 and h/16 extrapolated (Richardson, second
    order) is within a factor 3 of the tolerance. Measured: 1.15e-3 (783 steps; the fixed
    step h = 5e-4, 800 steps, 1.44e-3)."""
    over = {"time.t_end": 0.4}
    f8, f16 = (Problem("robot_2dof_dwell", {**over, "time.h": 5e-4 / k}).evaluate(
        None, gradient=False).values["tip_deviation"] for k in (8, 16))
    ref = np.asarray(f16)[::16] + (np.asarray(f16)[::16] - np.asarray(f8)[::8]) / 3
    p = Problem("robot_2dof_dwell", {**over, "time.h": "auto", "time.rtol": 1e-3})
    ev = p.evaluate(None, gradient=False)
    err = np.abs(ev.values["tip_deviation"] - ref).max() / np.abs(ref).max()
    assert 1e-3 / 3 < err < 3e-3, err


def test_refined_problem_halves_the_frozen_steps():
    """Problem.refined(2) of an adaptive case runs on the frozen grid with every step halved
    (the Richardson ladder of flexmbs.analysis.accuracy), its outputs on a grid twice as fine."""
    p = _adaptive_robot()
    g = p.steps()
    fine = p.refined(2)
    assert np.array_equal(fine.steps(), subdivide(g, 2))
    assert fine.mechanism.t.size == 2 * p.mechanism.t.size - 1


def test_case_keys():
    """time.h = "auto" needs tol or rtol; tol, rtol, output and h_max need h = "auto";
    --set time.h=auto keeps the case's step as the response grid's spacing (time.output)."""
    with pytest.raises(CaseError, match="needs a tolerance"):
        Problem("robot_2dof", {"time.h": "auto"})
    with pytest.raises(CaseError, match="only with h"):
        Problem("robot_2dof", {"time.rtol": 1e-3})
    p = Problem("robot_2dof", {"time.h": "auto", "time.tol": 1e-6, "time.t_end": 0.01})
    assert p.description.time.output == 5e-4 and p.mechanism.h == 5e-4



def test_the_grid_is_chosen_at_the_start_design():
    """An adaptive Problem first evaluated at another design runs on the grid chosen at its
    start design (a batch's workers, each with a Problem of its own, share it whatever
    design they simulate first); `adapt(x)` chooses it at x."""
    p, q = _adaptive_robot(), _adaptive_robot()
    p.evaluate(0.8 * p.start, gradient=False)
    assert np.array_equal(p.steps(), q.steps())
    g = q.adapt(0.5 * q.start)
    assert q.steps() is g and not np.array_equal(g, p.steps())


@pytest.mark.parametrize("start", ["rest", "static"])
def test_solvers_newton_modes_and_step_cuts_on_a_varying_grid(start):
    """The slider-crank press (cases/slider_crank_press.toml, 0.05 s) on a varying grid (steps
    0.7 to 1.3 ms), from rest and from static equilibrium: dense and KLU, full, automatic and
    reuse Newton give the same states (1e-8 m: the Newton tolerance's level); with at most 2
    Newton iterations per step the run cuts steps (more than 20: their halves are other
    steps, so the states differ by the discretisation error), and the adjoint of a weighted
    sum over its history equals direct differentiation of the same cut run to 1e-8 relative
    (as on the uniform grid, tests/test_adjoint.py). Measured: 5e-14 m; 192 cuts; 3.6e-10."""
    from flexmbs.analysis.adjoint import adjoint_gradient, simulate_for_adjoint
    p = Problem("slider_crank_press", {"time.t_end": 0.05, "time.start": start})
    mech = p.mechanism
    model = mech.set_design(mech.start)
    s = np.linspace(0, 1, 51)
    g = 0.05 * (s + 0.3 * np.sin(2 * np.pi * s) / (2 * np.pi))
    q0, qd0 = mech.initial_state()
    settings = SimulationSettings(start=start, store="all", tol=1e-12)
    kw = dict(initial=InitialConditions(q0=q0, qd0=None if start == "static" else qd0), steps=g)
    ref = simulate(model, 0.05, 5e-4, settings.replace(solver="dense", newton="full"), **kw)
    for solver in ("dense", "klu"):
        for newton in ("full", "auto", "reuse"):
            r = simulate(model, 0.05, 5e-4, settings.replace(solver=solver, newton=newton), **kw)
            assert np.abs(r.q - ref.q).max() < 1e-8, (solver, newton)
    dprop = mech.element_property_derivatives(mech.start)
    settings = settings.replace(newton="full", max_iter=2, validity="off")
    direct = simulate(model, 0.05, 5e-4, settings, derivatives=DesignDerivatives(properties=dprop),
                      **kw)
    run = simulate_for_adjoint(model, 0.05, 5e-4, settings, **kw)
    assert run.stats["step_cuts"] > 20 and run.tape["h"].size > g.size + 20
    gq = np.random.default_rng(7).standard_normal(run.q.shape)
    adj = adjoint_gradient(model, run, dprop, gq)[:, 0]
    ref_g = np.einsum("td,tdv->v", gq, direct.dq)
    assert np.abs(adj - ref_g).max() < 1e-8 * np.abs(ref_g).max()


@pytest.mark.parametrize("adaptive", [False, True])
def test_refined_problem_keeps_the_horizon(adaptive):
    """A t_end that is not a whole number of steps (0.0103 s, steps of 1 ms) is rounded once,
    to 0.010 s; the refined problems of the error estimates end there too (not at 0.0105 s or
    0.01025 s, the rounding at their finer spacing), and an adaptive one runs on its halved
    frozen grid."""
    over = {"time.t_end": 0.0103, "time.h": 1e-3}
    if adaptive:
        over = {"time.t_end": 0.0103, "time.h": "auto", "time.output": 1e-3, "time.rtol": 1e-2}
    with pytest.warns(UserWarning):
        p = Problem("robot_2dof", over)
    for k in (2, 4):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            fine = p.refined(k)
            assert fine.mechanism.t_end == pytest.approx(p.mechanism.t_end, abs=1e-15)
            fine.evaluate(gradient=False)


def test_a_step_limit_below_the_shortest_step_is_refused():
    """time.h_max below 1/1024 of the coarse pilot's step (1e-9 s against 1 ms / 1024) would
    ask for 10^7 steps: a CaseError naming time.h_max, not a run that does not end."""
    p = Problem("robot_2dof", {"time.t_end": 0.01, "time.h": "auto", "time.rtol": 1e-2,
                               "time.h_max": 1e-9})
    with pytest.raises(CaseError, match="time.h_max = 1e-09 s is below the shortest step"):
        p.steps()
