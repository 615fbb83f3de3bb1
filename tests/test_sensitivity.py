"""Design sensitivities of a Problem (flexmbs.problem.Problem.evaluate(x, gradient=True)):
Taylor tests of the direct derivatives and central finite differences written here.

A finite-difference comparison at one step and one tolerance measures the truncation and
rounding of the finite differences, not the derivative (it failed at 1.17e-5 against 1e-5 on
another machine). The main tests here use the Taylor test instead (flexmbs.analysis.checks.taylor_test):
along a direction d, the remainder e(s) = max_n |r_n(p + s d) - r_n(p) - s (J d)_n| of a
response history r with claimed derivative J falls 4x per halving of s when J is right and 2x
when it is wrong. Each test asserts an observed order > 1.8 for the library's derivative AND
an order < 1.3 for the same derivative with a 1e-3 error in one component
(J[:, i] += 1e-3 |J[n, :]|), on the same simulations: this proves that every step range used
here can fail.

The responses are the squared deviation histories dl_n^2 of the cases' deviation responses,
(28) and (30) of the robot (cases/robot_2dof.toml, robot_2dof_tracking.toml) and (33) of the
four-bar (cases/fourbar.toml, "deviation_A") (the deviation itself has a kink where dl_n = 0,
the square is smooth; d(dl^2) = 2 dl d(dl) checks d(dl) at every step where dl != 0), the KS
aggregate of the case's deviation constraint (Evaluation.constraints / jacobian, the constraint
set to over = "ks", parameter 100), the mass and the objective.

Step ranges (measured on the old per-mechanism cases, whose responses the general cases give
to 1e-9, modified and full Newton, Newton tolerance 1e-10): the remainder of the right
derivative is exactly second order (order 2.00 +- 0.02) down to a plateau, the noise of the
simulated deviation: about 1e-15 m on dl (a few ulps of q ~ 0.5 m), i.e. dl^2 noise
5e-20 .. 7e-18 m^2. The 1e-3 gradient error dominates the remainder below s ~ 2e-3 mm
(robots), 5e-4 mm (four-bar over its full horizon). The steps below (STEP) go from about that
crossover down five halvings; there the smallest remainder stays well above the floor
2 max(dl) NOISE_DL (NOISE_DL = 2e-15 m, twice the measured noise).
"""
import json
import subprocess
import sys

import numpy as np
import pytest

from flexmbs.analysis.checks import taylor_test
from flexmbs.analysis.simulate import simulate
from flexmbs.errors import ModelError
from flexmbs.methods.fully import ScaledProblem
from flexmbs.model.casefile import read_description
import flexmbs.problem
from flexmbs.problem import Problem
from flexmbs.analysis.settings import DesignDerivatives

# (case, design in mm): published optima of Tables 1, 2 and 3, where the deviation is active
DESIGNS = {
    "robot_2dof": [39.29, 28.33, 34.94, 25.19],            # Table 1 weakly, formulation (28)
    "robot_2dof_tracking": [47.87, 34.51, 42.11, 30.08],   # Table 2 weakly, formulation (30)
    "fourbar": [69.85, 87.61, 37.22],                      # Table 3 weakly, formulation (33)
}
#: the constrained deviation response of each case (its [[constraints]] item 0)
DEVIATION = {"robot_2dof": "deviation_28", "robot_2dof_tracking": "deviation_30",
             "fourbar": "deviation_A"}
MODES = {"full Newton": {"time.newton": "full"}, "modified Newton": {"time.newton": "reuse"}}
NOISE_DL = 2e-15          # m, noise of a simulated deviation (measured ~1e-15, see above)
HALVINGS = 5
PERTURBATION = 1e-3       # relative error put into one gradient component
# largest step (mm) per (case, horizon in steps; None = the case's full horizon)
STEP = {("robot_2dof", 100): 2.0 ** -7, ("robot_2dof", 500): 2.0 ** -7,
        ("robot_2dof", None): 2.0 ** -7,
        ("robot_2dof_tracking", 100): 2.0 ** -7, ("robot_2dof_tracking", 500): 2.0 ** -7,
        ("robot_2dof_tracking", None): 2.0 ** -7,
        ("fourbar", 100): 2.0 ** -5, ("fourbar", 500): 2.0 ** -7, ("fourbar", None): 2.0 ** -10}


def problem(name, nsteps=None, **overrides):
    """The shipped case `name` over nsteps time steps (None: its own horizon), with overrides."""
    if nsteps is not None:
        overrides["time.t_end"] = nsteps * read_description(name).time.h
    return Problem(name, overrides=overrides)


def _direction(nv, seed=7):
    d = np.random.default_rng(seed).standard_normal(nv)
    return d / np.linalg.norm(d)


def _perturbed(J, i):
    """J with a 1e-3 relative error in component i (1e-3 of the gradient's norm at each step)."""
    Jw = J.copy()
    Jw[..., i] += PERTURBATION * np.linalg.norm(J, axis=-1)
    return Jw


def _history_taylor(name, nsteps, overrides, step, direction=None):
    """Taylor test of dl^2 of the case's constrained deviation response, and of the KS aggregate
    (rho = 100) of its deviation constraint, with the library's derivatives and with a 1e-3
    error in one component (of the constrained deviation's dl^2)."""
    prob = problem(name, nsteps, **{"constraints.0.over": "ks", "constraints.0.parameter": 100.0},
                   **overrides)
    lim = prob.description.constraints[0].upper
    dev = DEVIATION[name]
    p = np.asarray(DESIGNS[name], float)
    d = _direction(p.size) if direction is None else np.asarray(direction, float)
    i = int(np.argmax(np.abs(d)))
    names = [dev]

    def values(ev):
        out = {k: ev.values[k] ** 2 for k in names}
        out[dev + " perturbed"] = out[dev]
        out["ks"] = ev.constraints
        return out

    ev = prob.evaluate(p, gradient=True)
    jac = {k: 2 * ev.values[k][:, None] * ev.gradients[k] for k in names}
    jac[dev + " perturbed"] = _perturbed(jac[dev], i)
    jac["ks"] = ev.jacobian
    noise = {k: 2 * ev.values[k].max() * NOISE_DL for k in names}
    noise[dev + " perturbed"] = noise[dev]
    noise["ks"] = NOISE_DL / lim                     # g = KS(dl / lim) - 1; weights sum to 1
    # gradient=True at every point: with modified Newton (time.newton = "reuse") a run with
    # gradients factorizes at every step for the sensitivity solve and so takes other Newton
    # iterates than one without (measured: deviation_28 differs by 2.6e-9 m, 1307 against 29
    # factorizations), a constant offset that would hide the remainder
    chk = taylor_test(lambda q: values(prob.evaluate(q, gradient=True)), p, jac, d,
                      step=step, halvings=HALVINGS, value=values(ev), noise=noise)
    return chk, names, dev


def _assert_taylor(result):
    checks, names, dev = result
    for k in names:
        assert checks[k].ok, f"d({k}^2)/dp fails the Taylor test:\n{checks[k].table()}"
    assert checks["ks"].ok, f"d(KS)/dp fails the Taylor test:\n{checks['ks'].table()}"
    wrong = checks[dev + " perturbed"]
    assert not wrong.ok and wrong.order < 1.3, \
        f"a 1e-3 gradient error is not detected with these steps:\n{wrong.table()}"


@pytest.mark.parametrize("mode", list(MODES))
@pytest.mark.parametrize("name", list(DESIGNS))
@pytest.mark.parametrize("nsteps", [100, 500, None], ids=["100 steps", "500 steps", "full"])
def test_deviation_history_derivatives_pass_the_taylor_test(name, nsteps, mode):
    """Taylor test (second order, > 1.8) of d(dl_n^2)/dp at every step for the case's
    constrained deviation response (Evaluation.gradients), and of the KS-aggregated constraint
    (Evaluation.jacobian), formulations (28), (30), (33), along a random direction; the same
    steps give order < 1.3 for a gradient with a 1e-3 error (module docstring)."""
    _assert_taylor(_history_taylor(name, nsteps, MODES[mode], STEP[(name, nsteps)]))


def test_dense_solver_derivatives_pass_the_taylor_test(monkeypatch):
    """The dense LAPACK path (solver='dense') of the direct derivatives, robot (28), 500
    steps: Taylor order > 1.8 (and < 1.3 with a 1e-3 gradient error). The case's
    solver.linear_solver = "dense" reaches every run of the problem (the runs' settings are
    recorded)."""
    solvers = []

    def recorded(*args, **kw):
        r = simulate(*args, **kw)
        solvers.append(r.settings.solver)
        return r

    monkeypatch.setattr(flexmbs.problem, "simulate", recorded)
    _assert_taylor(_history_taylor("robot_2dof", 500, {"solver.linear_solver": "dense"},
                                   STEP[("robot_2dof", 500)]))
    assert solvers and set(solvers) == {"dense"}


@pytest.mark.parametrize("var", range(4))
def test_each_design_variable_passes_the_taylor_test(var):
    """Each column of d(dl^2)/dp (direction e_i), robot (28), full 0.65 s, modified Newton:
    Taylor order > 1.8, and < 1.3 with a 1e-3 error in that column."""
    _assert_taylor(_history_taylor("robot_2dof", None, MODES["modified Newton"], 2.0 ** -8,
                                   direction=np.eye(4)[var]))


def test_mass_gradient_is_analytic_and_passes_the_taylor_test():
    """Beam mass m = rho A L, A = 0.36 pi/4 p^2 (docs/paper-cases.md), robot: the mass response's
    gradient and the objective's (the case minimizes the mass) are 2 * 229.02 p_i * 1e-6 kg/mm
    (to rounding); the mass is quadratic in p, so the Taylor remainder is exactly second
    order (order 2 to rounding)."""
    prob = problem("robot_2dof", 10)
    p = np.array([39.29, 28.33, 34.94, 25.19])
    ev = prob.evaluate(p, gradient=True)
    rho_a_per_p2 = 2700 * 0.36 * np.pi / 4 * 0.3            # kg / m^2 per element of 0.3 m
    exact = 2 * rho_a_per_p2 * p * 1e-6
    np.testing.assert_allclose(ev.gradients["mass"], exact, rtol=1e-12)
    np.testing.assert_allclose(ev.d_objective, exact, rtol=1e-12)
    # steps 1 .. 2^-5 mm: remainders 2e-4 .. 2e-7 kg, 1e6x above the rounding floor 1e3 eps m
    # (the analytic value above is the sharper check: a 1e-3 error would show as order 1 only
    # below s ~ 2e-5 mm, where the remainder reaches rounding)
    chk = taylor_test(prob.design_mass, p, ev.gradients["mass"], _direction(4), step=1.0,
                      halvings=5)
    assert chk.ok and abs(chk.order - 2) < 0.01, chk.table()


@pytest.mark.parametrize("over", ["every_step", "ks", "pnorm", "max"])
def test_fully_coupled_constraints_pass_the_taylor_test(over):
    """The optimizer's scaled constraints g(x) and objective f(x) of the fully coupled method
    (optimize/fully.py ScaledProblem: the deviation constraint per step, KS, p-norm or max
    over time), robot (28), 500 steps, at 0.95 x the Table 1 design (there dl_n >= 3.5e-4 m,
    so the per-step form dl_n / limit - 1 has no kink; the maximum is at one step, away from
    a tie): Taylor order > 1.8; < 1.3 with a 1e-3 error in one gradient component. Measured
    on the old format (same responses): orders 2.00, smallest remainders 1e-9 (g) and 1.5e-11
    (f), > 100x above the noise (dl noise 2e-15 m / limit = 2e-12) and the rounding floor
    1e3 eps |g|."""
    prob = ScaledProblem(problem("robot_2dof", 500, **{"constraints.0.over": over}))
    x = prob.to_x(0.95 * np.asarray(DESIGNS["robot_2dof"]))
    d = _direction(4)
    ev = prob.evaluate(x)
    value = {"g": ev.g, "f": ev.f, "g perturbed": ev.g}
    jac = {"g": ev.dg, "f": ev.df, "g perturbed": _perturbed(ev.dg, int(np.argmax(np.abs(d))))}

    def fun(xx):
        e = prob.evaluate(xx, gradient=False)
        return {"g": e.g, "f": e.f, "g perturbed": e.g}

    # x = p / p_start, p_start = 50 mm: x-steps 2^-12 .. 2^-17 are 1.2e-2 .. 3.8e-4 mm
    chk = taylor_test(fun, x, jac, d, step=2.0 ** -12, halvings=HALVINGS, value=value)
    for key in ("g", "f"):
        assert chk[key].ok, f"{key}:\n{chk[key].table()}"
    assert not chk["g perturbed"].ok and chk["g perturbed"].order < 1.3, chk["g perturbed"].table()


def test_taylor_test_on_an_analytic_function():
    """flexmbs.analysis.checks.taylor_test on r(x) = (sin x0 exp x1, x0^2 x1^3): the exact Jacobian
    gives order 2 (analytic; remainders 1e-3 .. 1e-7, far above rounding), a 1e-3 error in
    one entry gives order ~1 and fails; a linear response (remainder = rounding) is refused;
    bad arguments raise ModelError naming the argument."""
    def r(x):
        return np.array([np.sin(x[0]) * np.exp(x[1]), x[0] ** 2 * x[1] ** 3])

    x = np.array([0.7, -0.4])
    J = np.array([[np.cos(x[0]) * np.exp(x[1]), np.sin(x[0]) * np.exp(x[1])],
                  [2 * x[0] * x[1] ** 3, 3 * x[0] ** 2 * x[1] ** 2]])
    ok = taylor_test(r, x, J, step=1e-1, halvings=6)
    assert ok.ok and abs(ok.order - 2) < 0.1 and abs(ok.slope - 2) < 0.1, ok.table()
    Jw = J.copy()
    Jw[1, 0] += 1e-3 * np.abs(J).max()
    wrong = taylor_test(r, x, Jw, step=1e-4, halvings=6)      # below the crossover ~1e-3
    assert not wrong.ok and wrong.order < 1.3, wrong.table()
    assert "order (median)" in ok.table()
    # a linear response has a rounding-level remainder: refused (the floor), not passed
    A = np.array([[1.0, 2.0], [3.0, -1.0]])
    lin = taylor_test(lambda y: A @ y, x, A, step=1e-1)
    assert not lin.above_floor and not lin.ok, lin.table()
    with pytest.raises(ModelError, match=r"jacobian must have shape \(2, 2\), got \(2,\)"):
        taylor_test(r, x, J[0], step=1e-1)
    with pytest.raises(ModelError, match="halvings must be an integer >= 2, got 1"):
        taylor_test(r, x, J, step=1e-1, halvings=1)
    with pytest.raises(ModelError, match="step must be a positive finite number, got -1"):
        taylor_test(r, x, J, step=-1.0)


@pytest.mark.parametrize("name", list(DESIGNS))
def test_central_differences_converge_to_the_direct_gradients(name):
    """Central differences (written here) of every response, the objective and the
    constraints (every step) converge to Evaluation's direct gradients like s^2: over 300
    steps at the Table 1/2/3 design, the error of the histories' differences (relative to the
    gradient's largest entry) falls more than 30-fold for a tenfold smaller step (textbook:
    100; measured 99 (four-bar), 61-117 (robots)) and is below 2e-3 at s = 1e-3 mm (measured
    1.5e-4 four-bar, 2e-8 robots). The mass is quadratic in p: its central difference is
    exact up to rounding (measured <= 1e-11, asserted 1e-9)."""
    prob = problem(name, 300)
    p = np.asarray(DESIGNS[name], float)
    ev = prob.evaluate(p, gradient=True)
    hist = [k for k, v in ev.values.items() if np.ndim(v)]
    grads = dict(ev.gradients, objective=ev.d_objective, constraints=ev.jacobian)
    errs = {}
    for s in (1e-2, 1e-3):
        fd = {k: np.zeros_like(g) for k, g in grads.items()}
        for i in range(p.size):
            e = np.zeros(p.size)
            e[i] = s
            up, dn = prob.evaluate(p + e, gradient=False), prob.evaluate(p - e, gradient=False)
            for k in ev.values:
                fd[k][..., i] = (up.values[k] - dn.values[k]) / (2 * s)
            fd["objective"][i] = (up.objective - dn.objective) / (2 * s)
            fd["constraints"][:, i] = (up.constraints - dn.constraints) / (2 * s)
        errs[s] = {k: np.abs(fd[k] - grads[k]).max() / np.abs(grads[k]).max() for k in grads}
    for k in hist + ["constraints"]:
        assert errs[1e-3][k] < errs[1e-2][k] / 30, (k, errs)
        assert errs[1e-3][k] < 2e-3, (k, errs)
    for k in ("mass", "objective"):
        assert errs[1e-3][k] < 1e-9 and errs[1e-2][k] < 1e-9, (k, errs)


def test_design_derivative_at_the_maximum_is_consistent():
    """A constraint over the maximum of the deviation ("max") has the gradient of the
    history at the step of the maximum, over the limit (the maximum of a history is attained
    at one step: its derivative is that step's); the robot (28) at the Table 1 design: thicker
    arms deflect less, so every derivative of the active deviation is negative."""
    prob = problem("robot_2dof", None, **{"constraints.0.over": "max"})
    ev = prob.evaluate(DESIGNS["robot_2dof"], gradient=True)
    lim = prob.description.constraints[0].upper
    k = int(np.argmax(ev.values["deviation_28"]))
    assert ev.constraints.shape == (1,)
    assert ev.constraints[0] == pytest.approx(ev.values["deviation_28"][k] / lim - 1, rel=1e-14)
    np.testing.assert_allclose(ev.jacobian[0], ev.gradients["deviation_28"][k] / lim, rtol=1e-14)
    assert np.all(ev.gradients["deviation_28"][k] < 0)


def test_cli_gradient_json_reports_the_library_derivatives():
    """`flexmbs evaluate CASE --design ... --gradient --json` reports the direct
    derivatives of Problem.evaluate (Taylor-tested above): the gradient of each history at its
    maximum and the mass's gradient, equal to rounding of the JSON output (1e-12)."""
    p = DESIGNS["robot_2dof"]
    ev = Problem("robot_2dof").evaluate(p, gradient=True)
    proc = subprocess.run([sys.executable, "-m", "flexmbs", "evaluate", "robot_2dof", "--design",
                           ",".join(map(str, p)), "--gradient", "--json"],
                          capture_output=True, text=True, check=True)
    out = json.loads(proc.stdout)["responses"]
    k = int(np.argmax(ev.values["deviation_28"]))
    np.testing.assert_allclose(out["deviation_28"]["gradient_of_max"],
                               ev.gradients["deviation_28"][k], rtol=1e-12)
    np.testing.assert_allclose(out["mass"]["gradient"], ev.gradients["mass"], rtol=1e-12)


def _robot_with_torques(nsteps=200):
    """The robot (28) over nsteps with the two motor torques as responses (docs/case-format.md:
    type "torque", drive = NAME)."""
    import tomllib
    from flexmbs.model.casefile import case_path
    with open(case_path("robot_2dof"), "rb") as f:
        data = tomllib.load(f)
    data["responses"] += [{"name": "torque_shoulder", "type": "torque", "drive": "shoulder"},
                          {"name": "torque_elbow", "type": "torque", "drive": "elbow"}]
    data["time"]["t_end"] = nsteps * data["time"]["h"]
    return Problem(data)


@pytest.mark.parametrize("mode", list(MODES))
def test_constraint_force_derivatives_pass_the_taylor_test(mode):
    """d(mu)/dp of every constraint row (Result.dmu, asked by Problem.simulate when a torque
    response is evaluated) and the torque responses' gradients (Evaluation.gradients): the
    motor torques and the pin and hinge reactions of the robot (28) over 200 steps, along a
    random direction: Taylor order > 1.8, and < 1.3 with a 1e-3 error in one component.
    Measured on the old format (both modes): torques up to 38 N m, noise plateau of the
    remainder 2e-10 (Newton tolerance), right remainders 5e-6 .. 2e-8 at steps 2^-6 .. 2^-10
    mm (100x above the noise 4e-10 given), orders 2.00; perturbed orders 0.89-1.07."""
    prob = _robot_with_torques()
    if mode == "modified Newton":
        data = prob.description.model_dump(by_alias=True, exclude_unset=True)
        data["time"]["newton"] = "reuse"
        prob = Problem(data)
    torques = ["torque_shoulder", "torque_elbow"]
    p = np.asarray(DESIGNS["robot_2dof"], float)
    labels = prob.mechanism.model.compile().row_labels
    motors = [k for k, lab in enumerate(labels) if lab.startswith("motor")]
    assert len(motors) == 2
    r = prob.simulate(p, gradient=True, responses=torques)
    mu, dmu = r.mu, r.dmu
    assert dmu.shape == mu.shape + (4,)
    ev = prob.evaluate(p, gradient=True)
    d = _direction(4)
    i = int(np.argmax(np.abs(d)))

    def fun(x):
        v = prob.simulate(x, gradient=True, responses=torques).mu   # as in _history_taylor
        e = prob.evaluate(x, gradient=True)
        out = {"all": v, "torque": v[:, motors], "torque perturbed": v[:, motors]}
        out.update({k: e.values[k] for k in torques})
        return out

    value = {"all": mu, "torque": mu[:, motors], "torque perturbed": mu[:, motors]}
    value.update({k: ev.values[k] for k in torques})
    jac = {"all": dmu, "torque": dmu[:, motors], "torque perturbed": _perturbed(dmu[:, motors], i)}
    jac.update({k: ev.gradients[k] for k in torques})
    chk = taylor_test(fun, p, jac, d, step=2.0 ** -6, halvings=4, value=value, noise=4e-10)
    for k in ["all", "torque"] + torques:
        assert chk[k].ok, (k, chk[k].table())
    wrong = chk["torque perturbed"]
    assert not wrong.ok and wrong.order < 1.3, wrong.table()


def test_constraint_force_derivatives_are_only_computed_when_asked():
    """Problem.simulate with gradient=True differentiates the multipliers only when a torque
    or reaction response is asked (Result.dmu None for the deviations alone), and asking
    simulate for them without design derivatives is a ModelError naming the argument."""
    prob = _robot_with_torques(10)
    p = np.asarray(DESIGNS["robot_2dof"], float)
    r = prob.simulate(p, gradient=True, responses=["deviation_28"])
    assert r.dmu is None and r.dq is not None
    assert prob.simulate(p, gradient=True, responses=["torque_elbow"]).dmu is not None
    with pytest.raises(ModelError, match="DesignDerivatives.constraint_forces=True needs "
                                         "DesignDerivatives.properties"):
        simulate(prob.mechanism.model, 10 * prob.mechanism.h,
                 derivatives=DesignDerivatives(constraint_forces=True), h=prob.mechanism.h)
