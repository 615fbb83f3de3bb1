"""Newton strategies of simulate: newton='auto' (the default), 'full', 'reuse'.

'auto' keeps the factorization of the iteration matrix across iterations and steps and must
give the responses and design derivatives of full Newton within a bound that follows from the
Newton tolerance (derivation in test_auto_gives_the_responses_of_full_newton).
"""
from __future__ import annotations

import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.simulate import NEWTON_MODES
from flexmbs.errors import ModelError
from flexmbs.problem import Problem
from flexmbs.analysis.settings import InitialConditions, SimulationSettings

CASES = Path(__file__).resolve().parents[1] / "cases"
TOL = 1e-10                       # simulate's default Newton tolerance
ACCEPT = 1e-16                    # auto's acceptance level of the remaining error (relative)


def _problem(case, newton):
    raw = tomllib.loads((CASES / f"{case}.toml").read_text())
    raw["time"]["newton"] = newton
    return Problem(raw)


def _qscale(cm):
    """The length scale of the Newton test (model_data.f90: max(1, max|q_ref|, element length))."""
    return max(1.0, float(np.abs(cm.qref).max()), float(cm.el_len[:cm.nel].max()))


def _propagation_bound(prob, result, e):
    """2 N e (1 + (gamma' + h beta') T / 2): per-step errors e of both runs, each carried by
    the velocities and accelerations it comes with (gamma' e, beta' e) over the rest of the run."""
    ts = prob.description.time
    rho = ts.rho_inf
    am, af = (2 * rho - 1) / (rho + 1), rho / (rho + 1)
    gamma = 0.5 - am + af
    beta = 0.25 * (gamma + 0.5) ** 2
    h, n = ts.h, result.stats["steps"]
    gammap = gamma / (beta * h)
    hbetap = (1 - am) / (beta * h * (1 - af))
    return 2 * n * e * (1 + (gammap + hbetap) * n * h / 2), (1 - am) / (beta * h * h * (1 - af))


@pytest.mark.parametrize("case", ["robot_2dof", "fourbar", "slider_crank_press"])
def test_auto_gives_the_responses_and_sensitivities_of_full_newton(case):
    """'auto' and 'full' Newton on three cases of cases/, at the start design, give the
    same coordinates, deviation responses and design derivatives within a bound derived from
    the Newton tolerance.

    Derivation. A step's equations have one solution; full Newton stops at an increment
    <= tol qscale and, converging quadratically, leaves an error of order tol^2 qscale;
    'auto' accepts an increment <= tol qscale only when its estimated remaining error
    (rate/(1 - rate) x increment, rate^2 x increment after a fresh matrix) is below
    max(tol^2, 1e-16) qscale. With the rounding of the coordinates, each accepted state is
    within e = (1e-16 + 4 eps) qscale of the solution of its step in both runs. Through the
    Newmark relations (eqs. 4-5) an error e of q_n comes with gamma' e in the velocities and
    beta' e in the accelerations (gamma' = gamma/(beta h), beta' = (1-alpha_m)/(beta h^2
    (1-alpha_f))); the later steps carry them (generalized-alpha is stable, numerically damped
    here: no growth) and the velocities integrate: over the remaining time t_N - t_n the
    coordinates move by at most e (1 + (gamma' + h beta') (t_N - t_n)). Summed over the N
    steps of both runs: |dq| <= B = 2 N e (1 + (gamma' + h beta') T / 2) (robot: 1.8e-8 m;
    measured 7.5e-12; accepting at rate x increment <= tol instead gave 5e-8: this fails). A deviation, sqrt of the sum of at most two squared components of
    differences of two positions, moves by at most 4 B.

    Sensitivities (gradient=True, where 'auto' takes full Newton steps from the second
    iteration): the derivative solve of a step uses the tangent at an iterate within the last
    increment (<= tol qscale) of the converged state, in both runs, and the accelerations,
    known to beta' e: a relative perturbation per step of at most
    d = tol qscale / l_min + beta' e / a_ref (l_min the shortest element, a_ref = max|qdd|
    of the run), carried like the states: |d(dq/dp)| <= 2 N d (1 + (gamma' + h beta') T / 2)
    max|dq/dp| (robot: 9e-3 relative; measured 1.3e-8). Each bound holds with a margin of
    more than 10 (measured 2400 to 10^7 on the three cases)."""
    full, auto = _problem(case, "full"), _problem(case, "auto")
    cm = full.mechanism.model.compile()
    qs = _qscale(cm)
    e = (ACCEPT + 4 * np.finfo(float).eps) * qs

    # the simulation path (no derivatives): modified Newton with the auto rules
    rf = full.simulate(gradient=False)
    ra = auto.simulate(gradient=False)
    assert rf.stats["newton"] == "full" and ra.stats["newton"] == "auto"
    assert ra.stats["factorizations"] < 0.5 * rf.stats["factorizations"]   # it did reuse
    bound, betap = _propagation_bound(full, rf, e)
    assert np.abs(ra.q - rf.q).max() <= bound
    ef, ea = full.evaluate(gradient=False), auto.evaluate(gradient=False)
    deviations = [n for n, r in full._resp.items() if type(r).__name__ == "Deviation"]
    assert deviations
    for name in deviations:
        assert np.abs(ea.values[name] - ef.values[name]).max() <= 4 * bound, name

    # the sensitivity path
    gf = full.simulate(gradient=True)
    ga = auto.simulate(gradient=True)
    assert np.abs(ga.q - gf.q).max() <= bound
    l_min = float(cm.el_len[:cm.nel].min())
    a_ref = float(np.abs(gf.qdd).max())
    d = TOL * qs / l_min + betap * e / a_ref
    rel = bound / e * d                       # 2 N d (1 + (gamma' + h beta') T / 2)
    scale = np.abs(gf.dq).max(axis=(0, 1))
    assert np.all(np.abs(ga.dq - gf.dq).max(axis=(0, 1)) <= rel * scale)


def test_auto_is_the_default_and_reuses_the_factorization():
    """simulate() without `newton` runs 'auto' (Result.stats['newton']); on the robot it
    factors far less often than full Newton (measured 460 against 2604 factorizations for
    1300 steps), and 'reuse' less still (measured 22)."""
    prob = _problem("robot_2dof", "auto")
    model = prob.mechanism.set_design(prob.start)
    q0, _ = prob.mechanism.initial_state()
    settings = SimulationSettings(start="static", store=[0])
    initial = InitialConditions(q0=q0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # the default path warns about nothing
        r = fx.simulate(model, 0.65, 5e-4, settings, initial=initial)
    rf = fx.simulate(model, 0.65, 5e-4, settings.replace(newton="full"), initial=initial)
    rr = fx.simulate(model, 0.65, 5e-4, settings.replace(newton="reuse"), initial=initial)
    assert r.stats["newton"] == "auto" and r.settings.newton == "auto"
    assert rf.stats["factorizations"] >= rf.stats["newton_iterations"]      # one per iteration
    assert r.stats["factorizations"] < 0.25 * rf.stats["factorizations"]
    assert rr.stats["factorizations"] < 0.05 * rf.stats["factorizations"]


@pytest.mark.parametrize("value", ["modified", "Auto", None, True, 1])
def test_bad_newton_value_is_a_model_error_naming_the_argument(value):
    """newton outside 'auto', 'full', 'reuse': ModelError naming the argument, the value and
    the allowed values."""
    m = fx.Model()
    b = m.add_beam("b", (0, 0), (1, 0), 1, material=fx.Material(E=70e9, nu=0.3, rho=2700),
                   section=fx.Circle(0.02))
    m.clamp(b.first)
    with pytest.raises(ModelError) as err:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(newton=value))
    msg = str(err.value)
    assert "newton must be one of 'full', 'reuse', 'auto'" in msg and repr(value) in msg


def test_reuse_jacobian_is_a_deprecated_alias():
    """reuse_jacobian=True runs 'reuse', False 'full', each with a DeprecationWarning naming
    the replacement; together with a contradicting newton=..., ModelError naming both."""
    m = fx.Model()
    b = m.add_beam("b", (0, 0), (1, 0), 1, material=fx.Material(E=70e9, nu=0.3, rho=2700),
                   section=fx.Circle(0.02))
    m.clamp(b.first)
    for flag, mode in ((True, "reuse"), (False, "full")):
        with pytest.warns(DeprecationWarning, match=f"newton={mode!r}"):
            r = fx.simulate(m, 2e-3, 1e-3, reuse_jacobian=flag)
        assert r.stats["newton"] == mode
    with pytest.raises(ModelError, match="reuse_jacobian=True .* contradicts newton='full'"):
        fx.simulate(m, 2e-3, 1e-3, settings=SimulationSettings(newton="full"), reuse_jacobian=True)
    assert set(NEWTON_MODES) == {"auto", "full", "reuse"}


def test_case_file_newton_key_is_validated():
    """[time] newton outside 'auto', 'full', 'reuse', or contradicted by the deprecated
    reuse_jacobian: CaseError naming the key, the value and what is allowed."""
    from flexmbs.errors import CaseError
    raw = tomllib.loads((CASES / "robot_2dof.toml").read_text())
    raw["time"]["newton"] = "fast"
    with pytest.raises(CaseError, match=r"time\.newton.*'auto', 'full' or 'reuse', got 'fast'"):
        Problem(raw)
    raw["time"].update(newton="full", reuse_jacobian=True)
    with pytest.raises(CaseError, match="time.*reuse_jacobian = true .* contradicts newton = 'full'"):
        Problem(raw)
