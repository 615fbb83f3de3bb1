"""Point-to-point spring-dampers (Model.add_spring_damper, fortran/force_elements.f90).

A point mass m hangs from a clamped node on a vertical spring-damper (stiffness k, damping c)
and moves on a vertical slider; gravity g. Analytic solution (any textbook on the damped
oscillator): static deflection delta = m g / k; released at rest from the unstretched length,
y(t) = -delta (1 - exp(-zeta w t) (cos(w_d t) + zeta / sqrt(1 - zeta^2) sin(w_d t))),
w = sqrt(k / m), zeta = c / (2 m w), w_d = w sqrt(1 - zeta^2). Generalized-alpha is second
order accurate (Chung & Hulbert 1993), so the error must fall 4x per halving of h.
"""
import math
import sys

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.checks import check_iteration_matrix, taylor_test
from flexmbs.errors import ModelError
from flexmbs.analysis.settings import DesignDerivatives, SimulationSettings

MASS, K, G, L = 2.0, 800.0, 9.81, 1.0
STEEL = fx.Material(E=210e9, nu=0.3, rho=7800)


def hanging_mass(c=0.0):
    m = fx.Model()
    top = m.add_node(0.0, 0.0)
    bob = m.add_node(0.0, -L)
    m.clamp(top)
    m.add_point_mass(bob, MASS, 0.1)
    m.slider(bob, axis=(0.0, 1.0))
    m.add_spring_damper(top, bob, K, damping=c)
    m.set_gravity(0.0, -G)
    return m, bob


def analytic_drop(t, c):
    w = math.sqrt(K / MASS)
    z = c / (2 * MASS * w)
    wd = w * math.sqrt(1 - z * z)
    delta = MASS * G / K
    return -delta * (1 - np.exp(-z * w * t) * (np.cos(wd * t) + z / math.sqrt(1 - z * z)
                                               * np.sin(wd * t)))


def test_static_deflection_is_m_g_over_k():
    """start='static': the mass hangs m g / k = 2 * 9.81 / 800 = 0.0245 m below the free
    length (exact: the spring is linear along its line), to 1e-9 relative; no motion after."""
    m, bob = hanging_mass(c=3.0)
    r = fx.simulate(m, 0.05, 1e-3, settings=SimulationSettings(start="static"))
    y = r.position(bob)[:, 1]
    np.testing.assert_allclose(y, -L - MASS * G / K, rtol=1e-9)


def test_preload_and_free_length_shift_the_equilibrium():
    """Tension N = k (l - l0) + f0: with free length 0.9 m and preload 4 N the static length
    is l0 + (m g - f0) / k (analytic), to 1e-9 relative."""
    m = fx.Model()
    top, bob = m.add_node(0.0, 0.0), m.add_node(0.0, -L)
    m.clamp(top)
    m.add_point_mass(bob, MASS)
    m.slider(bob, axis=(0.0, 1.0))
    m.add_spring_damper(top, bob, K, free_length=0.9, preload=4.0)
    m.set_gravity(0.0, -G)
    r = fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(start="static"))
    np.testing.assert_allclose(r.position(bob)[0, 1], -(0.9 + (MASS * G - 4.0) / K), rtol=1e-9)


@pytest.mark.parametrize("c", [0.0, 5.0], ids=["undamped", "damped zeta=0.0625"])
def test_free_vibration_matches_the_analytic_oscillator_to_second_order(c):
    """Released at rest from the free length: y(t) of the (damped) oscillator, frequency
    sqrt(k/m) = 20 rad/s and decay exp(-zeta w t) (module docstring), over 0.5 s (1.6
    periods). The largest error relative to delta falls 4x per halving of h (observed order
    within 0.1 of 2 for h = 2, 1, 0.5 ms; measured 2.00) and is below 1e-3 at h = 0.5 ms
    (measured 6e-5)."""
    errs = []
    hs = [2e-3, 1e-3, 5e-4]
    for h in hs:
        m, bob = hanging_mass(c)
        r = fx.simulate(m, 0.5, h, settings=SimulationSettings(rho_inf=0.5))
        y = r.position(bob)[:, 1] + L
        errs.append(np.max(np.abs(y - analytic_drop(r.t, c))) / (MASS * G / K))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(orders - 2) < 0.1), (errs, orders)
    assert errs[-1] < 1e-3, errs


def spring_beam_model(d=(0.03, 0.025), c=40.0):
    """A beam (2 elements, root pinned and driven) with a tip mass, held by a spring-damper
    from its tip to a clamped ground node; gravity."""
    m = fx.Model()
    arm = m.add_beam("arm", (0.0, 0.0), (0.6, 0.0), 2, material=STEEL, section=fx.Circle(d[0]))
    m.set_element_sections(arm, [fx.Circle(d[0]), fx.Circle(d[1])])
    m.pin(arm.first)
    m.drive_rotation(arm.first, fx.TimeLaw(lambda t: 2.0 * t ** 2, lambda t: 4.0 * t,
                                           lambda t: 4.0 + 0.0 * t))
    m.add_point_mass(arm.last, 1.5, 0.01)
    ground = m.add_node(0.6, 0.4)
    m.clamp(ground)
    m.add_spring_damper(ground, arm.last, 2.0e4, damping=c, free_length=0.35)
    m.set_gravity(0.0, -9.81)
    return m, arm


def test_iteration_matrix_with_a_spring_damper_matches_finite_differences(monkeypatch):
    """The iteration matrix of eq. (7) with a spring-damper: beta' M + gamma' C_t + K_t
    (the damper's C_t = c g g^T and the velocity-dependent part of K_t) against central
    differences of the residual with dq, dqd = gamma' dq, dqdd = beta' dq, at a deformed,
    moving state with random multipliers: within 1e-6 relative per row; and the same check
    fails (> 1e-3) when the damping term gamma' C_t is left out of the matrix (not of the
    residual), so the check sees it. The static case (beta' = gamma' = 0) as well."""
    m, arm = spring_beam_model(c=4000.0)     # gamma' c = 2e7 N/m, visible beside the beam
    rng = np.random.default_rng(3)
    q = m.reference_coordinates() + 0.02 * rng.standard_normal(m.ndof)
    qd = 2.0 * rng.standard_normal(m.ndof)
    mu = 1e2 * rng.standard_normal(m.compile().nc)
    qdd = rng.standard_normal(m.ndof)
    result = check_iteration_matrix(m, q, qdd, mu, 0.1, qd=qd)
    assert result.max_relative_error < 1e-6, result
    static = check_iteration_matrix(m, q, None, mu, 0.1, qd=qd, beta_prime=0.0, gamma_prime=0.0)
    assert static.max_relative_error < 1e-6, static

    checks_module = sys.modules["flexmbs.analysis.checks"]
    real = checks_module.system_matrices

    def without_damping_in_matrix(*args, cc=0.0, **kw):
        r, _ = real(*args, cc=cc, **kw)
        return r, real(*args, cc=0.0, **kw)[1]

    monkeypatch.setattr(checks_module, "system_matrices", without_damping_in_matrix)
    assert check_iteration_matrix(m, q, qdd, mu, 0.1, qd=qd).max_relative_error > 1e-3


def _element_derivatives(m, arm):
    """dprop (5, nel, 2): element e's properties depend on its diameter p_e (m)."""
    secs = m.element_sections(arm)
    dprop = np.zeros((5, len(secs), len(secs)))
    for e, s in enumerate(secs):
        dprop[:, arm.elements[e], e] = s.property_derivatives(STEEL)[:, 0]
    return dprop


def test_design_derivatives_with_a_spring_damper_pass_the_taylor_test():
    """Direct differentiation through a model with a spring-damper (its stiffness and
    damping enter the iteration matrix and the recursion as C_t (gamma' Qhat - Vhat)): the
    tip position history of the spring-held beam over 300 steps w.r.t. the two element
    diameters, static start: Taylor order > 1.8; < 1.3 with a 1e-3 error in one component.
    Steps 2^-16 .. 2^-21 m of diameter (15 .. 0.5 um: the tip's response is strongly curved,
    e/s^2 = 35 m/m^2, so a 1e-3 gradient error dominates only below ~2e-5 m). Measured: right
    orders 2.000, smallest remainder 8e-12 m (60x above the noise 1e-13 m given; the
    remainder shows no plateau down there); perturbed orders 1.39 .. 1.04, median 1.14."""
    p = np.array([0.03, 0.025])
    h, nsteps = 5e-4, 300

    def run(x):
        m, arm = spring_beam_model(tuple(x))
        r = fx.simulate(m, nsteps * h, h,
                        settings=SimulationSettings(start="static", store=[arm.last]),
                        derivatives=DesignDerivatives(properties=_element_derivatives(m, arm),
                                                      dofs=[3 * arm.last, 3 * arm.last + 1]))
        return r.position(arm.last), r.position_derivative(arm.last)

    v, J = run(p)
    d = np.array([0.6, -0.8])
    Jw = J.copy()
    Jw[..., 1] += 1e-3 * np.linalg.norm(J, axis=-1)
    chk = taylor_test(lambda x: {"tip": run(x)[0], "perturbed": run(x)[0]}, p,
                      {"tip": J, "perturbed": Jw}, d, step=2.0 ** -16, halvings=5,
                      value={"tip": v, "perturbed": v}, noise=1e-13)
    assert chk["tip"].ok, chk["tip"].table()
    assert not chk["perturbed"].ok and chk["perturbed"].order < 1.3, chk["perturbed"].table()


def test_spring_damper_bad_input():
    """Bad input names the argument, the value and what is allowed."""
    m, bob = hanging_mass()
    with pytest.raises(ModelError, match="stiffness must be finite and >= 0, got -1"):
        m.add_spring_damper(0, bob, -1.0)
    with pytest.raises(ModelError, match="damping must be a number"):
        m.add_spring_damper(0, bob, 1.0, damping="x")
    with pytest.raises(ModelError, match="free_length must be finite and >= 0"):
        m.add_spring_damper(0, bob, 1.0, free_length=-0.5)
    with pytest.raises(ModelError, match="node_a and node_b are both node 1"):
        m.add_spring_damper(bob, bob, 1.0)
    with pytest.raises(ModelError, match="unknown node 7"):
        m.add_spring_damper(0, 7, 1.0)
