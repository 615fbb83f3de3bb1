"""The discrete adjoint of the generalized-alpha scheme (fortran/adjoint.f90, flexmbs.analysis.adjoint,
Problem.evaluate(method='adjoint')), docs/adjoint.md.

The adjoint is the transpose of the direct differentiation of the same discrete equations, so
both give the same gradient up to the Newton tolerance (the direct method uses the tangent of
the step's last Newton iteration, the adjoint the tangent at the converged state): 1e-8
relative (measured 1e-13 to 2e-10 on these runs), and a central finite difference converges to
it at second order (Taylor test).
"""

import numpy as np
import pytest

from flexmbs import problem as problem_module
from flexmbs.analysis.adjoint import adjoint_gradient, simulate_for_adjoint
from flexmbs.analysis.simulate import simulate
from flexmbs.errors import ModelError, ResourceError
from flexmbs.problem import Problem
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings

REL = 1e-8


def _rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _problem(case, t_end, over, start=None, **more):
    ov = {"time.t_end": t_end, "constraints.0.over": over, "time.newton": "full", **more}
    if start is not None:
        ov["time.start"] = start
    return Problem(case, ov)


@pytest.mark.parametrize("start", ["rest", "static"])
def test_robot_ks_adjoint_equals_direct(start):
    """Robot (cases/robot_2dof.toml, 0.05 s): the KS-aggregated deviation constraint's
    gradient by the adjoint equals direct differentiation to 1e-8 relative, from rest and
    from static equilibrium; the evaluation reports the method used."""
    p = _problem("robot_2dof", 0.05, "ks", start)
    direct = p.evaluate(p.start, method="direct")
    adj = p.evaluate(p.start, method="adjoint")
    assert direct.gradient_method == "direct" and adj.gradient_method == "adjoint"
    assert adj.constraints == pytest.approx(direct.constraints, rel=1e-12)
    assert _rel(adj.jacobian, direct.jacobian) < REL
    assert _rel(adj.d_objective, direct.d_objective) < REL
    assert adj.gradients["deviation_28"] is None          # histories: not by the adjoint


@pytest.mark.parametrize("over,more", [("ks", {}), ("pnorm", {}), ("max", {}),
                                       ("ks", {"constraints.0.window": [0.02, 0.04],
                                               "constraints.0.parameter": 30.0})])
def test_fourbar_aggregates_adjoint_equal_direct(over, more):
    """Four-bar (cases/fourbar.toml, 0.05 s): KS, p-norm and max aggregates of the deviation
    of point A, and KS over a window with its own rho: adjoint against direct
    differentiation, 1e-8 relative."""
    p = _problem("fourbar", 0.05, over, **more)
    direct = p.evaluate(p.start, method="direct")
    adj = p.evaluate(p.start, method="adjoint")
    assert _rel(adj.jacobian, direct.jacobian) < REL


def _robot_runs(start):
    p = Problem("robot_2dof", {"time.t_end": 0.05, "time.start": start})
    mech = p.mechanism
    model = mech.set_design(mech.start)
    ts = p.description.time
    q0, qd0 = mech.initial_state()
    settings = SimulationSettings(rho_inf=ts.rho_inf, start=start, newton="full")
    initial = InitialConditions(q0=q0, qd0=None if start == "static" else qd0)
    dprop = mech.element_property_derivatives(mech.start)
    direct = simulate(model, mech.t_end, ts.h, settings.replace(store="all"), initial=initial,
                      derivatives=DesignDerivatives(properties=dprop, constraint_forces=True))
    run = simulate_for_adjoint(model, mech.t_end, ts.h, settings, initial=initial)
    return model, dprop, direct, run


@pytest.mark.parametrize("start", ["rest", "static"])
def test_final_value_and_forces(start):
    """Final values (every coordinate at t_end, two random functionals) and a weighted sum of
    the constraint forces over the whole history: the adjoint's gradients equal the direct
    method's dq/dp and dmu/dp contracted with the same weights, 1e-8 relative."""
    model, dprop, direct, run = _robot_runs(start)
    nt, ndof = run.q.shape
    nc = run.mu.shape[1]
    rng = np.random.default_rng(3)
    gq = np.zeros((nt, ndof, 3))
    gq[-1, :, :2] = rng.standard_normal((ndof, 2))
    gmu = np.zeros((nt, nc, 3))
    gmu[:, :, 2] = rng.standard_normal((nt, nc))
    adj = adjoint_gradient(model, run, dprop, gq, gmu)
    ref = np.einsum("tdf,tdv->vf", gq, direct.dq) + np.einsum("tdf,tdv->vf", gmu, direct.dmu)
    for f in range(3):
        assert _rel(adj[:, f], ref[:, f]) < REL


def test_taylor_ks_robot():
    """Taylor test (robot from rest, 0.05 s, KS of the deviation): the central-difference
    remainder |(G(x + h d) - G(x - h d)) / 2h - dG . d| of the adjoint gradient falls as h^2:
    observed order within [1.8, 2.2] over h = 0.02 .. 6e-4 (relative to the design)."""
    p = _problem("robot_2dof", 0.05, "ks", "rest")
    x = np.asarray(p.start, float)
    ev = p.evaluate(x, method="adjoint")
    d = np.array([0.6, -0.3, 0.8, 0.5]) * x
    slope = float(ev.jacobian[0] @ d)
    steps = [0.02 / 2**k for k in range(6)]
    rem = []
    for h in steps:
        gp = p.evaluate(x + h * d, gradient=False).constraints[0]
        gm = p.evaluate(x - h * d, gradient=False).constraints[0]
        rem.append(abs((gp - gm) / (2 * h) - slope))
    orders = np.log2(np.array(rem[:-1]) / np.array(rem[1:]))
    assert np.all((orders > 1.8) & (orders < 2.2)), (rem, orders)


def test_auto_picks_the_adjoint_past_the_margin(monkeypatch):
    """method='auto': direct for the robot's 4 variables and 1 functional (below
    ADJOINT_MIN_VARIABLES); the adjoint once the variables exceed the margin (lowered here)."""
    p = _problem("robot_2dof", 0.02, "ks")
    assert p.gradient_method("auto") == "direct"
    monkeypatch.setattr(problem_module, "ADJOINT_MIN_VARIABLES", 1)
    monkeypatch.setattr(problem_module, "ADJOINT_MARGIN", 2)
    assert p.evaluate(p.start, method="auto").gradient_method == "adjoint"


def test_the_automatic_choice_is_reported():
    """The choice of 'auto' is said with its reason: the robot's 4 variables and 1 KS row give direct, and an explicit method is
    reported as asked."""
    p = _problem("robot_2dof", 0.02, "ks")
    why = p.gradient_method_reason("auto")
    assert why.startswith("direct (auto: 4 design variables, 1 aggregated row;"), why
    assert p.gradient_method_reason("adjoint") == "adjoint (as asked)"


def test_bad_input():
    """Typed errors naming the argument: an unknown method, a run that did not store every
    coordinate, partials of the wrong shape, a memory limit the partials exceed."""
    p = _problem("robot_2dof", 0.01, "ks")
    with pytest.raises(ModelError, match="method must be one of .*got 'fast'"):
        p.evaluate(p.start, method="fast")
    mech = p.mechanism
    model = mech.set_design(mech.start)
    dprop = mech.element_property_derivatives(mech.start)
    part = simulate(model, 0.01, 5e-4, settings=SimulationSettings(store=[0]))
    with pytest.raises(ModelError, match="has no tape of its states"):
        adjoint_gradient(model, part, dprop, np.zeros((part.t.size, model.ndof)))
    run = simulate_for_adjoint(model, 0.01, 5e-4)
    with pytest.raises(ModelError, match=r"dG_dq must have shape"):
        adjoint_gradient(model, run, dprop, np.zeros((run.t.size, 3)))
    with pytest.raises(ResourceError, match="per-step partials"):
        adjoint_gradient(model, run, dprop, np.zeros((run.t.size, model.ndof)), memory_limit=100)


def _all_over(case, t_end, over, **overrides):
    d = Problem(case, {"time.t_end": t_end}).description
    ov = {"time.t_end": t_end, "time.newton": "full", **overrides}
    ov.update({f"constraints.{i}.over": over for i in range(len(d.constraints))})
    return Problem(case, ov)


def _rel_by_response(a, b):
    """Largest difference of the jacobians a, b relative to b's largest entry, per response."""
    out = {}
    for n in set(b.constraint_names):
        k = [i for i, m in enumerate(b.constraint_names) if m == n]
        out[n] = _rel(a.jacobian[k], b.jacobian[k])
    return out


def test_torques_and_reactions_three_arm_robot():
    """Three-arm robot (cases/three_arm_robot.toml, 0.05 s): KS of the tip deviation, of the
    three motor torques (both bounds) and of a joint reaction: the adjoint (multiplier seeds
    through dmu) equals direct differentiation to 1e-8 relative (measured 1e-11)."""
    p = _all_over("three_arm_robot", 0.05, "ks")
    direct = p.evaluate(p.start, method="direct")
    adj = p.evaluate(p.start, method="adjoint")
    assert adj.jacobian.shape == direct.jacobian.shape == (p.gradient_functionals(), 3)
    assert max(_rel_by_response(adj, direct).values()) < REL


@pytest.mark.parametrize("case,t_end,over", [("slider_crank_press", 0.02, "pnorm"),
                                             ("slider_crank_press", 0.02, "ks"),
                                             ("fourbar_tubes", 0.01, "every_step")])
def test_stress_responses(case, t_end, over):
    """Stresses (explicit dependence on the section depth) and spring-dampers (the press):
    adjoint against direct differentiation, 1e-8 relative, with the Newton tolerance at 1e-12
    for both runs (at the default 1e-10 the direct method's tangent, taken one Newton
    iteration before convergence, is 3e-8 off the converged one on the press stress; the
    adjoint's is within 1e-9). 'every_step': one adjoint functional per step (the per-step
    partials seeded into every row at once)."""
    p = _all_over(case, t_end, over, **{"solver.tol": 1e-12})
    direct = p.evaluate(p.start, method="direct")
    adj = p.evaluate(p.start, method="adjoint")
    assert max(_rel_by_response(adj, direct).values()) < REL


def test_step_cuts():
    """Slider-crank press (0.05 s) with at most 2 Newton iterations per step and tol 1e-12:
    the run cuts some 300 steps (their sub-steps are on the tape, more than its first room:
    the run is repeated with room for them all); the adjoint gradients of a
    final value and of a weighted sum over the whole history equal direct differentiation
    of the same run (which differentiates every sub-step) to 1e-8 relative (measured 1e-11;
    at tol 1e-10, with or without cuts, the direct method's tangent from the iteration before
    convergence leaves 1e-7 on the press's weighted sum)."""
    p = Problem("slider_crank_press", {"time.t_end": 0.05})
    mech = p.mechanism
    model = mech.set_design(mech.start)
    dprop = mech.element_property_derivatives(mech.start)
    settings = SimulationSettings(newton="full", max_iter=2, validity="off", tol=1e-12)
    direct = simulate(model, 0.05, 5e-4, settings.replace(store="all"),
                      derivatives=DesignDerivatives(properties=dprop))
    run = simulate_for_adjoint(model, 0.05, 5e-4, settings)
    assert run.stats["step_cuts"] > 100 and run.tape["h"].size > run.t.size + 100
    nt, ndof = run.q.shape
    rng = np.random.default_rng(7)
    gq = np.zeros((nt, ndof, 2))
    gq[-1, :, 0] = rng.standard_normal(ndof)
    gq[:, :, 1] = rng.standard_normal((nt, ndof))
    adj = adjoint_gradient(model, run, dprop, gq)
    ref = np.einsum("tdf,tdv->vf", gq, direct.dq)
    for f in range(2):
        assert _rel(adj[:, f], ref[:, f]) < REL


@pytest.mark.parametrize("newton", ["auto", "reuse"])
def test_automatic_newton_paper_horizon(newton):
    """Robot of Table 1 at its full horizon (0.65 s, 1300 steps) with the default automatic
    Newton and with 'reuse': the adjoint gradient of the KS deviation (its forward run
    polished: every step converged to the rounding level, by 'auto''s rules in both) is
    within 1e-8 relative of the exact one (direct differentiation, full Newton, tol 1e-12;
    measured 8e-10 with both; 'reuse' polished by full Newton steps from each step's second
    iteration, with a first held increment below tol accepted: 5e-6). Without polishing, modified Newton's states
    (8e-12 m off) made it 2e-6 off: adjoint_gradient refuses such runs."""
    p = Problem("robot_2dof", {"constraints.0.over": "ks", "time.newton": newton})
    adj = p.evaluate(p.start, method="adjoint")
    exact = Problem("robot_2dof", {"constraints.0.over": "ks", "time.newton": "full",
                                   "solver.tol": 1e-12}).evaluate(p.start, method="direct")
    assert _rel(adj.jacobian, exact.jacobian) < REL
    mech = p.mechanism
    model = mech.set_design(mech.start)
    run = simulate(model, 0.01, 5e-4, settings=SimulationSettings(newton="auto"), tape=True)
    with pytest.raises(ModelError, match="newton='auto' without polish=True"):
        adjoint_gradient(model, run, mech.element_property_derivatives(mech.start),
                         np.zeros((run.t.size, model.ndof)))


def test_polish_converges_states_to_rounding_with_held_matrices():
    """simulate(polish=True) with the automatic Newton (the adjoint's forward run): over the
    robot's 1300 steps its states are those of full Newton (same tolerance, same static
    start) to 1e-12 m (measured 2e-14 m; unpolished 'auto', accepted on its contraction
    estimate, 8e-12 m) and its accelerations to 1e-7 relative (measured 4e-9; unpolished
    3e-8), and it gets there with
    held matrices: fewer than 0.75 factorizations per step (measured 0.47; the full Newton
    steps polish took before, 1.04)."""
    p = Problem("robot_2dof", {"time.newton": "auto"})
    model, t_end, h, kw = p._run(p.start, False, None, None, tape=True)
    pol = simulate(model, t_end, h, **kw)
    assert pol.settings.polish
    ref = simulate(model, t_end, h, **{**kw, "settings": kw["settings"].replace(polish=False,
                                                                               newton="full")})
    assert np.abs(pol.tape["q"] - ref.tape["q"]).max() < 1e-12
    qdd = np.abs(ref.tape["qdd"]).max()
    assert np.abs(pol.tape["qdd"] - ref.tape["qdd"]).max() < 1e-7 * qdd
    assert pol.stats["factorizations"] < 0.75 * pol.stats["steps"]


def test_random_designs_robot_static():
    """Property: over 3 random designs within the bounds (robot from static equilibrium,
    0.03 s, KS and p-norm of the deviation), the adjoint gradient equals direct
    differentiation to 1e-8 relative."""
    rng = np.random.default_rng(18)
    for over in ("ks", "pnorm"):
        p = _problem("robot_2dof", 0.03, over, "static")
        lo, hi = p.lower, p.upper
        for _ in range(3):
            x = lo + (hi - lo) * rng.uniform(0.1, 0.9, lo.size)
            direct = p.evaluate(x, method="direct")
            adj = p.evaluate(x, method="adjoint")
            assert _rel(adj.jacobian, direct.jacobian) < REL


def test_optimization_with_the_adjoint():
    """Problem(gradient_method='adjoint'): an optimizer calling evaluate(x, gradient=True)
    gets adjoint gradients; 8 MMA iterations on the robot (0.1 s, KS deviation <= 0.2 mm)
    follow the same iterates as with direct differentiation (designs within 1e-6 relative;
    measured 1e-10), and a bad gradient_method is refused naming the argument."""
    from flexmbs.methods.fully import optimize_fully

    ov = {"time.t_end": 0.1, "constraints.0.over": "ks", "constraints.0.upper": 2e-4}
    runs = {}
    for gm in ("direct", "adjoint"):
        p = Problem("robot_2dof", ov, gradient_method=gm)
        assert p.evaluate(p.start).gradient_method == gm
        runs[gm] = optimize_fully(p, p.start, options=dict(max_iterations=8))
    assert runs["adjoint"].iterations == runs["direct"].iterations == 8
    np.testing.assert_allclose(runs["adjoint"].design, runs["direct"].design, rtol=1e-6)
    with pytest.raises(ModelError, match="gradient_method must be one of .*got 'adj'"):
        Problem("robot_2dof", ov, gradient_method="adj")


def test_elementwise_tubes_64_variables():
    """cases/robot_2dof_tapered_tubes.toml (16 elements per arm, diameter and wall per element:
    64 variables; KS deviation and KS stress of both arms; the max_step rows): the adjoint's
    Jacobian equals direct differentiation to 1e-8 relative per row (Newton tolerance 1e-12
    for both, as in test_stress_responses), on a design with a different size per element so
    that the largest stress moves between elements; 'auto' takes the adjoint (64 variables,
    2 aggregated rows)."""
    p = Problem("robot_2dof_tapered_tubes", overrides={"time.t_end": 0.05, "solver.tol": 1e-12})
    rng = np.random.default_rng(7)
    x = p.start * (0.8 + 0.2 * rng.random(p.start.size))
    direct = p.evaluate(x, method="direct")
    adj = p.evaluate(x, method="auto")
    assert adj.gradient_method == "adjoint" and direct.gradient_method == "direct"
    assert adj.jacobian.shape == direct.jacobian.shape == (len(direct.constraints), 64)
    for i, name in enumerate(direct.constraint_names):
        scale = np.abs(direct.jacobian[i]).max()
        assert np.abs(adj.jacobian[i] - direct.jacobian[i]).max() <= 1e-8 * scale, name


def test_constraint_weights_are_the_rows_derivatives():
    """constraint_weights (the adjoint's weights of every constraint row over the time steps,
    without identity gradients) against central differences of the rows' values
    (constraint_rows) in the response history: a KS upper bound, a windowed p-norm lower
    bound and a per-step upper bound on a window, on a smooth synthetic history (r_j =
    1e-3 (1 + 0.5 sin(7 t_j)), t on 0..0.65 s). The difference quotient with step 1e-9 of r's
    1e-3 scale has truncation and rounding errors of about 1e-6 relative to the largest
    weight: checked to 1e-4."""
    from flexmbs.problem import constraint_rows, constraint_weights
    p = Problem("robot_2dof", {"constraints": [
        {"response": "deviation_28", "upper": 1.0e-3, "over": "ks", "parameter": 200.0},
        {"response": "deviation_28", "lower": 2.0e-4, "over": "pnorm", "parameter": 8.0,
         "window": [0.1, 0.3]},
        {"response": "deviation_28", "upper": 1.2e-3, "window": [0.6, 0.65]}]})
    t = p.mechanism.t
    r = 1e-3 * (1 + 0.5 * np.sin(7 * t))
    W = constraint_weights(p.description, {"deviation_28": r, "mass": 1.0}, t)
    g0, _, names, _ = constraint_rows(p.description, {"deviation_28": r, "mass": 1.0}, {}, t, 0,
                                      False)
    assert W.shape == (g0.size, t.size) and set(names) == {"deviation_28"}
    eps = 1e-9
    for j in list(range(0, t.size, 97)) + [t.size - 1]:
        up, dn = r.copy(), r.copy()
        up[j] += eps
        dn[j] -= eps
        gu = constraint_rows(p.description, {"deviation_28": up, "mass": 1.0}, {}, t, 0, False)[0]
        gd = constraint_rows(p.description, {"deviation_28": dn, "mass": 1.0}, {}, t, 0, False)[0]
        fd = (gu - gd) / (2 * eps)
        assert np.abs(fd - W[:, j]).max() <= 1e-4 * np.abs(W).max(axis=1).max()


def test_stress_over_beams_of_two_element_orders():
    """One stress response over a beam of 2-node and a beam of 3-node elements, welded, KS
    constrained: its largest station moves between the two beams over time, and the adjoint
    gradient equals direct differentiation (1e-8 relative) in both orders of the beams."""
    def problem(o1, o2):
        return Problem({
            "points": {"O": [0, 0], "A": [0.4, 0], "B": [0.8, 0.0]},
            "materials": {"al": {"E": 7e10, "nu": 0.33, "rho": 2700}},
            "design": [{"name": "d", "lower": 5, "upper": 50, "start": 20, "unit": "mm"},
                       {"name": "e", "lower": 5, "upper": 50, "start": 15, "unit": "mm"}],
            "bodies": [{"name": "a1", "type": "beam", "from": "O", "to": "A", "elements": 2,
                        "order": o1, "material": "al",
                        "section": {"shape": "circle", "diameter": "d"}},
                       {"name": "a2", "type": "beam", "from": "A", "to": "B", "elements": 2,
                        "order": o2, "material": "al",
                        "section": {"shape": "circle", "diameter": "e"}},
                       {"name": "tip", "type": "mass", "at": "B", "on": "a2", "mass": 0.5}],
            "joints": [{"type": "pin", "body": "a1", "at": "O"},
                       {"type": "weld", "bodies": ["a1", "a2"], "at": "A"}],
            "drives": [{"type": "rotation", "body": "a1", "at": "O",
                        "law": {"type": "smooth_step", "end": 0.2, "t1": 0.05}}],
            "responses": [{"name": "sig", "type": "stress", "bodies": ["a1", "a2"]}],
            "constraints": [{"response": "sig", "upper": 1e7, "over": "ks"}],
            "time": {"t_end": 0.04, "h": 1e-3}})
    for orders in ((1, 2), (2, 1)):
        p = problem(*orders)
        direct = p.evaluate(p.start, gradient=True, method="direct").jacobian
        adjoint = p.evaluate(p.start, gradient=True, method="adjoint").jacobian
        assert np.allclose(adjoint, direct, rtol=1e-8, atol=1e-12 * np.abs(direct).max())
