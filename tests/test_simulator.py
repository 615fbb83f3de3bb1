"""The simulator against analytic and published values.

1. statics, 2. frequencies, 3. generalized-alpha, 4. rigid limit, 5. constraints,
6. derivatives, 7. statistics, then Jacobian reuse, failures and
bad input. Every test states in its docstring the reference value, its source and why
the tolerance is what it is.
"""
import math
import sys

import numpy as np
import pytest
from scipy.linalg import eigh
from scipy.optimize import brentq

import flexmbs as fx
from flexmbs.analysis.checks import check_iteration_matrix, check_tangent, generalized_alpha_beta_prime
from flexmbs.analysis.simulate import system_matrices
from flexmbs.analysis.validity import ValidityLimits
from flexmbs.errors import ModelError, SimulationError
from robot_kinematics import planar_2r_inverse, robot_joint_laws, robot_tip_path
from flexmbs.analysis.settings import InitialConditions, SimulationSettings

STEEL = fx.Material(E=210e9, nu=0.3, rho=7800)
NEWTON_TOL = 1e-10          # simulate()'s default tolerance on max|dq| / qscale


# ---------------------------------------------------------------------------- helpers
def robot(p_mm, stiffness_factor=1.0):
    """The 2-dof robot of docs/paper-cases.md: arms of 0.6 m from theta1(0) = 120 deg,
    theta2(0) = -150 deg, each of 2 quadratic elements, tube d = p, wall 0.1 p, aluminium,
    2 kg at A, 1 kg at the tip, gravity -y, absolute drives at O and A."""
    mat = fx.Material(E=72e9 * stiffness_factor, nu=0.3, rho=2700)
    th1, _, th12 = robot_joint_laws()
    t1, t2 = math.radians(120), math.radians(-150)
    a = (0.6 * math.cos(t1), 0.6 * math.sin(t1))
    tip = (a[0] + 0.6 * math.cos(t1 + t2), a[1] + 0.6 * math.sin(t1 + t2))
    tubes = [fx.Tube.with_wall_ratio(p * 1e-3, 0.1) for p in p_mm]
    m = fx.Model("robot")
    arm1 = m.add_beam("arm1", (0, 0), a, 2, material=mat, section=tubes[0])
    arm2 = m.add_beam("arm2", a, tip, 2, material=mat, section=tubes[2])
    m.set_element_sections("arm1", tubes[:2])
    m.set_element_sections("arm2", tubes[2:])
    m.pin(arm1.first)
    m.drive_rotation(arm1.first, th1)
    m.hinge(arm1.last, arm2.first)
    m.drive_rotation(arm2.first, th12)
    m.add_point_mass(arm1.last, 2.0)
    m.add_point_mass(arm2.last, 1.0)
    m.set_gravity(0, -9.81)
    return m, arm1, arm2


def simulate_robot(p_mm=(50, 50, 50, 50), **kw):
    m, arm1, arm2 = robot(p_mm, kw.pop("stiffness_factor", 1.0))
    return fx.simulate(m, 0.65, 5e-4, SimulationSettings(start="static", **kw)), m, arm1, arm2


@pytest.fixture(scope="module")
def robot50():
    """The robot at p = [50, 50, 50, 50] mm, paper settings (h = 5e-4 s, rho_inf = 0.5),
    full Newton (the reference of the Newton-strategy tests; simulate's default is 'auto')."""
    return simulate_robot(newton="full")


def cantilever(section, elements, order=2, length=1.0, material=STEEL):
    m = fx.Model("cantilever")
    b = m.add_beam("beam", (0, 0), (length, 0), elements, material=material, section=section,
                   order=order)
    m.clamp(b.first)
    return m, b


def static_solution(m):
    """Static equilibrium under the (constant) loads: the t = 0 state of a static start."""
    return fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))


def linear_k_m(m, fixed_dofs):
    """Tangent stiffness and mass at the reference state, fixed coordinates removed."""
    q = m.reference_coordinates()
    _, k = system_matrices(m, q)
    _, mm = system_matrices(m, q, cm=1.0, ck=0.0)
    free = np.setdiff1d(np.arange(m.ndof), fixed_dofs)
    return k[np.ix_(free, free)], mm[np.ix_(free, free)], free


def timoshenko_cantilever_frequencies(EI, kGA, rhoA, rhoI, L, count=3):
    """First circular frequencies of a clamped-free Timoshenko beam (shear and rotary
    inertia), from the exact solution of
        kGA (w'' - psi') + rhoA w^2 w = 0,   EI psi'' + kGA (w' - psi) + rhoI w^2 psi = 0
    with w = psi = 0 at x = 0 and EI psi' = kGA (w' - psi) = 0 at x = L (below the cut-off
    frequency sqrt(kGA / rhoI)): the roots of the 4 x 4 boundary determinant in the basis
    cosh, sinh (wave number alpha) and cos, sin (beta) (Timoshenko 1921; Huang 1961)."""
    def det(w):
        w2 = w * w
        a, b, c = kGA * EI, w2 * (kGA * rhoI + rhoA * EI), rhoA * w2 * (rhoI * w2 - kGA)
        disc = math.sqrt(b * b - 4 * a * c)
        al, be = math.sqrt((-b + disc) / (2 * a)), math.sqrt((b + disc) / (2 * a))
        ka, kb = (al * al + rhoA * w2 / kGA) / al, (rhoA * w2 / kGA - be * be) / be
        # al - ka and be + kb in closed form (no cancellation when kGA is large)
        sa, sb = -rhoA * w2 / (kGA * al), rhoA * w2 / (kGA * be)
        ch, sh, co, si = math.cosh(al * L), math.sinh(al * L), math.cos(be * L), math.sin(be * L)
        d = np.array([[1, 0, 1, 0],
                      [0, ka, 0, -kb],
                      [ka * al * ch, ka * al * sh, kb * be * co, kb * be * si],
                      [sa * sh, sa * ch, -sb * si, sb * co]])
        return np.linalg.det(d) / ch
    w1 = 1.875 ** 2 * math.sqrt(EI / (rhoA * L ** 4))
    grid = np.linspace(0.05 * w1, 80 * w1, 16000)
    grid = grid[grid < math.sqrt(kGA / rhoI)]
    vals = np.array([det(w) for w in grid])
    roots = []
    for i in np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0][:count]:
        roots.append(brentq(det, grid[i], grid[i + 1], xtol=1e-13 * grid[i]))
    return np.array(roots)


def strain_energy(m, q):
    """Discrete strain energy of the model's beams, same strains and reduced Gauss rule as
    fortran/beam2d.f90 (so that f_int = dU/dq, checked in the energy test)."""
    c = m.compile()
    props = m.element_properties()
    total = 0.0
    for e in range(c.nel):
        nen = int(c.el_nen[e])
        d = c.el_dofs[:3 * nen, e] - 1
        length = c.el_len[e]
        rule = [(0.0, 2.0)] if nen == 2 else [(-1 / math.sqrt(3), 1.0), (1 / math.sqrt(3), 1.0)]
        for xi, w in rule:
            if nen == 2:
                n, dn = np.array([(1 - xi) / 2, (1 + xi) / 2]), np.array([-0.5, 0.5])
            else:
                n = np.array([xi * (xi - 1) / 2, 1 - xi * xi, xi * (xi + 1) / 2])
                dn = np.array([xi - 0.5, -2 * xi, xi + 0.5])
            dns = dn * 2 / length

            def strains(qq):
                x, y, p = qq[d][0::3], qq[d][1::3], qq[d][2::3]
                dx, dy, phi = dns @ x, dns @ y, n @ p
                return np.array([math.cos(phi) * dx + math.sin(phi) * dy,
                                 -math.sin(phi) * dx + math.cos(phi) * dy, dns @ p])
            g = strains(q) - strains(c.qref)
            total += 0.5 * w * length / 2 * float(props[:3, e] @ (g * g))
    return total


def generalized_alpha_sdof(omega, h, rho_inf, x0, v0, steps):
    """Positions of x'' + omega^2 x = 0 integrated by generalized-alpha in the form of
    eqs. (3)-(6) (Arnold & Bruls 2007), coefficients of Chung & Hulbert (1993), a_0 = x''(0).
    An independent scalar implementation of the scheme."""
    am = (2 * rho_inf - 1) / (rho_inf + 1)
    af = rho_inf / (rho_inf + 1)
    gamma = 0.5 - am + af
    beta = 0.25 * (gamma + 0.5) ** 2
    w2 = omega * omega
    x, v = x0, v0
    acc = -w2 * x
    a = acc
    out = [x]
    for _ in range(steps):
        c = (af * acc - am * a) / (1 - am)
        d = (1 - af) / (1 - am)
        acc1 = (-w2 * (x + h * v + h * h * ((0.5 - beta) * a + beta * c))
                / (1 + w2 * h * h * beta * d))
        a1 = c + d * acc1
        x = x + h * v + h * h * ((0.5 - beta) * a + beta * a1)
        v = v + h * ((1 - gamma) * a + gamma * a1)
        a, acc = a1, acc1
        out.append(x)
    return np.array(out)


def soft_pendulum():
    """A flexible pendulum: 1 m beam of 2 quadratic elements, pinned at O, released from
    the horizontal under gravity; soft enough (EA = kGA = 100 N, EI = 2 N m^2, rhoA = 1 kg/m,
    rhoI = 0.05 kg m) that it stretches by ~10 % and bends visibly while swinging, and that
    every discrete mode (13.9 to 147 rad/s) is resolved by the steps of the order test."""
    m = fx.Model("pendulum")
    b = m.add_beam("pendulum", (0, 0), (1, 0), 2,
                   section=fx.GivenSection(EA=100.0, kGA=100.0, EI=2.0, rhoA=1.0, rhoI=0.05))
    m.pin(b.first)
    m.set_gravity(0, -9.81)
    return m, b


# ---------------------------------------------------------------------------- 1. statics
@pytest.mark.parametrize("section", [fx.Rectangle(0.05, 0.2), fx.Circle(0.15)],
                         ids=["rectangle L/h=5", "circle L/d=6.7"])
def test_cantilever_tip_load_quadratic_elements(section):
    """Tip deflection of a cantilever under a small tip load, 4 quadratic elements.

    Reference: Timoshenko beam theory, delta = P L^3 / (3 EI) + P L / (kGA). The beams are
    stubby (shear is 2.9 % and 1.2 % of delta), so Euler-Bernoulli would miss the required
    0.5 %. The load gives P L^2 / EI = 1e-4: the geometrically nonlinear correction is of
    order (P L^2 / EI)^2 = 1e-8. The quadratic element with reduced (2-point) integration
    reproduces the cubic deflection of this load case at the nodes, so the bound is set by
    the nonlinearity: 1e-6 relative (0.5 % is required).
    """
    m, b = cantilever(section, 4)
    EA, kGA, EI, _, _ = section.properties(STEEL)
    L = 1.0
    P = 1e-4 * EI / L ** 2
    m.add_load(b.last, fy=-P)
    delta = -static_solution(m).position(b.last)[0, 1]
    exact = P * L ** 3 / (3 * EI) + P * L / kGA
    assert (P * L / kGA) / exact > 0.01      # shear matters: an EB answer would fail
    assert abs(delta / exact - 1) < 1e-6


@pytest.mark.parametrize("elements", [2, 4, 8])
def test_cantilever_tip_load_linear_elements_follow_their_exact_error(elements):
    """2-node elements, one-point integration: tip deflection of n elements is
    P L^3 / (3 EI) (1 - 1 / (4 n^2)) + P L / (kGA).

    Derivation: one-point integration makes the curvature of each element constant, equal
    to the exact curvature at its midpoint, so the nodal rotations are exact; the deflection
    is then the trapezoidal rule of the (quadratic) rotation plus the exact shear, and the
    trapezoidal error is -L h^2 theta'' / 12 = -P L^3 / (12 EI n^2). Tolerance 1e-6 as in the
    quadratic test (geometric nonlinearity ~1e-8 at P L^2 / EI = 1e-4).
    """
    section = fx.Circle(0.05)
    m, b = cantilever(section, elements, order=1)
    _, kGA, EI, _, _ = section.properties(STEEL)
    P = 1e-4 * EI
    m.add_load(b.last, fy=-P)
    delta = -static_solution(m).position(b.last)[0, 1]
    expected = P / (3 * EI) * (1 - 1 / (4 * elements ** 2)) + P / kGA
    assert abs(delta / expected - 1) < 1e-6


def test_cantilever_rolls_into_full_circle_under_tip_moment():
    """Tip moment M = 2 pi EI / L on a cantilever (static start, load stepping in the core).

    Exact solution of the geometrically exact beam: N = Q = 0, constant curvature M / EI =
    2 pi / L, so the beam closes into a circle of radius R = L / (2 pi), the tip is back at
    the root with rotation 2 pi, and node s lies at (R sin(2 pi s / L), R (1 - cos(2 pi s / L))).
    The tip must be within 1e-3 L; we also ask every node on the circle within 1e-3 L with
    8 quadratic elements (positions converge as h^4 here: 6.9e-4 L with 4 elements, 5.0e-5 L
    with 8) and the nodal rotations to 1e-9 (phi is linear in s, represented exactly).
    The bending strain kappa h / 2 = pi h / L = 3.1 % is far beyond steel's elastic range (a
    benchmark of the kinematics, not of the material): the validity check must report exactly
    that value (phi' is exact, 1e-8), and the warning limit is raised above it for this test.
    """
    section = fx.Rectangle(0.05, 0.01)
    L = 1.0
    m, b = cantilever(section, 8, length=L)
    EI = section.properties(STEEL)[2]
    m.add_load(b.last, moment=2 * math.pi * EI / L)
    r = fx.simulate(m, 1e-3, 1e-3,
                    settings=SimulationSettings(start="static",
                                                validity=ValidityLimits(strain_warn=0.05)))
    assert abs(r.validity["bending strain"].value / (math.pi * 0.01 / L) - 1) < 1e-8
    tip = r.position(b.last)[0]
    assert np.hypot(*tip) < 1e-3 * L
    s = np.linspace(0, L, len(b.nodes))
    R = L / (2 * math.pi)
    nodes = np.array([r.position(n)[0] for n in b.nodes])
    exact = np.column_stack([R * np.sin(2 * np.pi * s / L), R * (1 - np.cos(2 * np.pi * s / L))])
    assert np.abs(nodes - exact).max() < 1e-3 * L
    rotations = np.array([r.rotation(n)[0] for n in b.nodes])
    assert np.abs(rotations - 2 * np.pi * s / L).max() < 1e-9


# ---------------------------------------------------------------------------- 2. frequencies
def bending_frequencies(m, b, count=3):
    """Lowest `count` bending circular frequencies of a cantilever along x from the
    linearized K and M (clamped node eliminated); bending modes are those whose largest
    component is transverse (y) rather than axial (x)."""
    k, mm, free = linear_k_m(m, b.dofs[:3])
    w2, vecs = eigh(k, mm)
    ydof = np.isin(free, np.arange(1, m.ndof, 3))
    xdof = np.isin(free, np.arange(0, m.ndof, 3))
    bending = [i for i in range(len(w2))
               if np.abs(vecs[ydof, i]).max() > np.abs(vecs[xdof, i]).max()]
    return np.sqrt(w2[bending[:count]])


def test_slender_cantilever_frequencies_match_euler_bernoulli():
    """Slender steel cantilever (L/d = 100), 20 quadratic elements.

    Reference: Euler-Bernoulli, omega_i = (beta_i L)^2 sqrt(EI / (rhoA L^4)) with
    beta_i L = 1.875104, 4.694091, 7.854757 (e.g. Blevins, Formulas for Natural Frequency and
    Mode Shape, table 8-1). Tolerance 2e-3: shear and rotary inertia, which the element has,
    lower the third frequency by (beta_3 L)^2 (r/L)^2 (1 + E/(kG)) / 2 ~ 1e-3 at L/d = 100;
    1 % is required.
    """
    section = fx.Circle(0.01)
    m, b = cantilever(section, 20)
    _, _, EI, rhoA, _ = section.properties(STEEL)
    beta_l = np.array([1.875104068711961, 4.694091132974175, 7.854757438237613])
    expected = beta_l ** 2 * np.sqrt(EI / rhoA)
    np.testing.assert_allclose(bending_frequencies(m, b), expected, rtol=2e-3)


def test_thick_cantilever_frequencies_match_timoshenko():
    """Stubby steel cantilever (rectangle, L/h = 10), 20 quadratic elements.

    Reference: the exact Timoshenko frequencies (roots of the clamped-free boundary
    determinant, timoshenko_cantilever_frequencies), 0.8 %, 5.0 % and 10.7 % below the
    Euler-Bernoulli values here, so the comparison tests shear and rotary inertia. Tolerance
    1e-4: the discretisation error of 20 quadratic elements is 4.2e-5 for the third mode
    (2.6e-6 with 40 elements: h^4 convergence to the reference); 1 % is required.
    """
    section = fx.Rectangle(0.05, 0.1)
    m, b = cantilever(section, 20)
    _, kGA, EI, rhoA, rhoI = section.properties(STEEL)
    expected = timoshenko_cantilever_frequencies(EI, kGA, rhoA, rhoI, 1.0)
    beta_l = np.array([1.875104068711961, 4.694091132974175, 7.854757438237613])
    assert expected[2] < 0.95 * beta_l[2] ** 2 * np.sqrt(EI / rhoA)   # far from EB
    np.testing.assert_allclose(bending_frequencies(m, b), expected, rtol=1e-4)


def test_timoshenko_reference_reduces_to_euler_bernoulli_when_slender():
    """The Timoshenko reference itself: with kGA and 1/rhoI very large it must give the
    Euler-Bernoulli roots beta_i L = 1.875104, 4.694091, 7.854757 (to 1e-6)."""
    w = timoshenko_cantilever_frequencies(1.0, 1e12, 1.0, 1e-12, 1.0)
    beta_l = np.array([1.875104068711961, 4.694091132974175, 7.854757438237613])
    np.testing.assert_allclose(w, beta_l ** 2, rtol=1e-6)


# ---------------------------------------------------------------------------- 3. generalized-alpha
@pytest.mark.parametrize("rho_inf", [0.5, 1.0])
def test_generalized_alpha_second_order_on_flexible_pendulum(rho_inf):
    """Observed order of convergence of the positions of a nonlinear flexible pendulum.

    Reference: generalized-alpha is second order in the positions for index-3 constrained
    systems with consistent initial accelerations (Arnold & Bruls 2007, Multibody Syst. Dyn.
    18:185). Error: the largest deviation of the tip position over the coarse grid from a
    reference run with h / 8 of the finest step; steps T/256 ... T/2048 (T = 0.5 s), all in
    the asymptotic range (omega_max h <= 0.3). Each halving must give log2(e_h / e_{h/2}) =
    2 +- 0.2 (the required band); measured 1.99-2.01.
    """
    m, b = soft_pendulum()
    T = 0.5
    levels = [8, 9, 10, 11]
    ref = fx.simulate(m, T, T / 2 ** 14,
                      settings=SimulationSettings(rho_inf=rho_inf, store=[b.last]))
    ref_tip = ref.position(b.last)[::2 ** (14 - levels[0])]
    errors = []
    for k in levels:
        r = fx.simulate(m, T, T / 2 ** k,
                        settings=SimulationSettings(rho_inf=rho_inf, store=[b.last]))
        errors.append(np.abs(r.position(b.last)[::2 ** (k - levels[0])] - ref_tip).max())
    assert np.abs(ref_tip).max() > 1.05          # the pendulum stretches: nonlinear, flexible
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(orders - 2) <= 0.2), orders


def test_energy_of_free_flexible_pendulum_conserved_with_rho_inf_1():
    """rho_inf = 1 (no numerical dissipation): total energy T + U + V of the swinging flexible
    pendulum over 1000 steps of 1 ms stays within 0.1 % of the largest kinetic energy
    (the required bound; measured 8e-6).

    T = qd^T M qd / 2 with the model's consistent mass, U the discrete strain energy (checked
    here: its central-difference gradient equals the core's f_int within 1e-6), V = -f_g . q
    for gravity. The pin does no work.
    """
    m, b = soft_pendulum()
    rng = np.random.default_rng(11)
    q = m.reference_coordinates() + 0.1 * rng.standard_normal(m.ndof)
    r_static, _ = system_matrices(m, q)
    fgrav = -system_matrices(m, m.reference_coordinates())[0][:m.ndof]   # f_int(qref) = 0
    fint = r_static[:m.ndof] + fgrav
    e = 1e-6
    grad = np.array([(strain_energy(m, q + e * d) - strain_energy(m, q - e * d)) / (2 * e)
                     for d in np.eye(m.ndof)])
    assert np.abs(grad - fint).max() <= 1e-6 * np.abs(fint).max()

    res = fx.simulate(m, 1.0, 1e-3, settings=SimulationSettings(rho_inf=1.0))
    _, mass = system_matrices(m, res.q[0], cm=1.0, ck=0.0)
    mass = mass[:m.ndof, :m.ndof]
    kinetic = 0.5 * np.einsum("ti,ij,tj->t", res.qd, mass, res.qd)
    energy = kinetic + np.array([strain_energy(m, qq) for qq in res.q]) - (res.q - res.q[0]) @ fgrav
    assert res.t.size == 1001
    assert np.abs(energy - energy[0]).max() <= 1e-3 * kinetic.max()


@pytest.mark.parametrize("rho_inf", [0.0, 0.5, 1.0])
def test_modal_response_of_cantilever_matches_scalar_generalized_alpha(rho_inf):
    """Small free vibration of a cantilever in its lowest and its highest mode
    (omega h = 0.09 and 612 with h = 1 ms), 20 steps.

    Reference: at small amplitude the beam is linear and generalized-alpha decouples by
    modes, so each modal coordinate must follow the scalar recursion of the scheme
    (generalized_alpha_sdof, written independently from eqs. 3-6) to within the Newton
    tolerance relative to the modal amplitude (1e-6; measured < 1e-9), above the round-off
    floor of the coordinates themselves (50 ulps of 1 m). Consequences checked
    on the modal energies: with rho_inf < 1 the high mode loses more than 6 decades of energy
    in 20 steps (its spectral radius tends to rho_inf), the low mode keeps more than 99 % (the
    0.7 % lost with rho_inf = 0 is the O(h) starting transient of the velocities that
    Arnold & Bruls describe); with rho_inf = 1 both keep their energy within 1e-6.
    """
    m, b = cantilever(fx.Circle(0.02), 4)
    h, steps = 1e-3, 20
    k, mm, free = linear_k_m(m, b.dofs[:3])
    w2, vecs = eigh(k, mm)
    omega = np.sqrt(w2)
    energies = {}
    for mode in (0, len(omega) - 1):
        amp = 1e-5 / np.abs(vecs[:, mode]).max()       # largest coordinate moves 1e-5
        qd0 = np.zeros(m.ndof)
        qd0[free] = amp * omega[mode] * vecs[:, mode]
        r = fx.simulate(m, steps * h, h, settings=SimulationSettings(rho_inf=rho_inf),
                        initial=InitialConditions(qd0=qd0))
        eta = (r.q[:, free] - m.reference_coordinates()[free]) @ mm @ vecs[:, mode]
        etad = r.qd[:, free] @ mm @ vecs[:, mode]
        expected = generalized_alpha_sdof(omega[mode], h, rho_inf, 0.0, amp * omega[mode], steps)
        # absolute floor: the coordinates are ~1 m, so q itself is resolved to ~2e-16 m
        # (one ulp); the high mode's amplitude, 1e-10, is only ~1e6 ulps of q
        assert np.abs(eta - expected).max() <= 1e-6 * np.abs(expected).max() + 50 * np.spacing(1.0)
        energy = 0.5 * etad ** 2 + 0.5 * w2[mode] * eta ** 2
        energies[mode] = energy[-1] / energy[0]
    low, high = energies[0], energies[len(omega) - 1]
    assert omega[-1] * h > 100 and omega[0] * h < 0.1
    if rho_inf < 1:
        assert high < 1e-6
        assert low > 0.99
    else:
        assert abs(high - 1) < 1e-6 and abs(low - 1) < 1e-6


def test_beta_prime_of_the_trapezoidal_limit():
    """beta' of eq. (7) used by the checker: with rho_inf = 1, Chung-Hulbert gives
    alpha_m = alpha_f = 1/2, gamma = 1/2, beta = 1/4 (the trapezoidal rule), so
    beta' = (1 - alpha_m) / (beta h^2 (1 - alpha_f)) = 4 / h^2; with rho_inf = 0,
    alpha_m = -1, alpha_f = 0, gamma = 3/2, beta = 1, so beta' = 2 / h^2."""
    assert generalized_alpha_beta_prime(1e-3, 1.0) == pytest.approx(4e6, rel=1e-14)
    assert generalized_alpha_beta_prime(1e-3, 0.0) == pytest.approx(2e6, rel=1e-14)


# ---------------------------------------------------------------------------- 4. rigid limit
def test_stiff_robot_follows_ideal_kinematics():
    """Robot with E x 1e6: the tip must follow the ideal path of eq. (26) (docs/paper-cases.md: tip
    from (0.21962, 0.21962) m along the diagonal) within 1e-6 m at every one of the 1301
    time steps. Elastic deflection scales as 1/E: ~1e-9 m remain."""
    r, m, arm1, arm2 = simulate_robot(stiffness_factor=1e6)
    x0 = 0.6 * math.cos(math.radians(120)) + 0.6 * math.cos(math.radians(-30))
    path = robot_tip_path(r.t, x0, x0)
    tip = r.position(arm2.last)
    assert r.t.size == 1301
    assert np.abs(tip - np.column_stack(path[:2])).max() < 1e-6
    # the joint A follows the ideal kinematics too
    th1 = planar_2r_inverse(*path, 0.6, 0.6)[0]
    joint_a = np.column_stack([0.6 * np.cos(th1), 0.6 * np.sin(th1)])
    assert np.abs(r.position(arm1.last) - joint_a).max() < 1e-6


# ---------------------------------------------------------------------------- 5. constraints
def test_robot_constraints_hold_at_every_step(robot50):
    """The pin at O, the hinge at A and both motor laws, evaluated from the stored q at every
    step, hold to the Newton tolerance (1e-10 on max|dq| / qscale, qscale = 1 m here): the
    constraints are linear, so after a converged Newton step they are satisfied up to the
    last increment."""
    r, m, arm1, arm2 = robot50
    th1, _, th12 = robot_joint_laws()
    assert np.abs(r.position(arm1.first)).max() <= NEWTON_TOL
    assert np.abs(r.position(arm1.last) - r.position(arm2.first)).max() <= NEWTON_TOL
    assert np.abs(r.rotation(arm1.first) - th1.value(r.t)).max() <= NEWTON_TOL
    assert np.abs(r.rotation(arm2.first) - th12.value(r.t)).max() <= NEWTON_TOL


def test_rigid_link_constraints_hold_at_every_step():
    """Nonlinear constraints: a driven beam carrying a rigid body (rigid link of eq. 1 in
    constraints.f90, offset held in the frame of the body's centre node). The link's
    position and angle constraints, evaluated from the stored q, hold to the Newton
    tolerance at every step (Newton converges quadratically: the residual after the last
    increment is far below the increment)."""
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.6, 0), 3, material=STEEL,
                   section=fx.Tube.with_wall_ratio(0.04, 0.1))
    m.pin(b.first)
    m.drive_rotation(b.first, fx.TimeLaw(lambda t: 3 * t ** 2, lambda t: 6 * t, lambda t: 6 + 0 * t,
                                         name="swing"))
    body = m.add_rigid_body("payload", [b.last], mass=3.0, inertia=0.05, center=(0.75, 0.1))
    m.set_gravity(0, -9.81)
    r = fx.simulate(m, 0.5, 1e-3, settings=SimulationSettings(start="static"))
    c, j = body.first, b.last
    ref = m.reference_coordinates()
    d = ref[3 * j:3 * j + 2] - ref[3 * c:3 * c + 2]
    dphi = ref[3 * j + 2] - ref[3 * c + 2]
    phi_c = r.rotation(c)
    rot = np.stack([np.cos(phi_c) * d[0] - np.sin(phi_c) * d[1],
                    np.sin(phi_c) * d[0] + np.cos(phi_c) * d[1]], axis=1)
    gap = r.position(j) - r.position(c) - rot
    assert np.abs(r.rotation(b.first)).max() > 0.7          # large rotation of the payload
    assert np.abs(gap).max() <= NEWTON_TOL
    assert np.abs(r.rotation(j) - phi_c - dphi).max() <= NEWTON_TOL


def test_trajectory_does_not_depend_on_the_penalty(robot50):
    """Two penalty values p of eq. (1), 1e2 and 1e10 (k automatic), give the same
    trajectory within 1e-9 relative to max|q|: p changes the Newton path,
    not the solution of the discrete equations, which is fixed to the Newton tolerance."""
    r_low = simulate_robot(penalty=1e2)[0]
    r_high = simulate_robot(penalty=1e10)[0]
    scale = np.abs(robot50[0].q).max()
    assert np.abs(r_low.q - r_high.q).max() <= 1e-9 * scale
    assert np.abs(r_low.q - robot50[0].q).max() <= 1e-9 * scale


def test_dense_and_klu_give_the_same_trajectory(robot50):
    """The same robot with dense LU and with KLU: identical discrete equations, so the
    trajectories agree within 1e-10 relative (both reach roundoff, measured
    5e-15)."""
    r_dense = simulate_robot(solver="dense")[0]
    r_klu = simulate_robot(solver="klu")[0]
    assert r_klu.stats["solver"] == "klu" and r_dense.stats["solver"] == "dense"
    scale = np.abs(r_dense.q).max()
    assert np.abs(r_dense.q - r_klu.q).max() <= 1e-10 * scale
    # multipliers are forces: they carry the roundoff of f_int, EA u / l_e ~ 2e-8 N here,
    # i.e. 1.3e-10 of the largest joint force (151 N)
    assert np.abs(r_dense.mu - r_klu.mu).max() <= 1e-9 * np.abs(r_dense.mu).max()


# ---------------------------------------------------------------------------- 6. derivatives
@pytest.mark.parametrize("nen", [2, 3])
def test_element_tangent_matches_finite_differences(nen):
    """Exact tangent of the 2- and 3-node geometrically exact element against central
    differences of its internal forces at 8 random deformed states (rigid rotations up to
    pi, strains up to 20 %), each stiffness part separately: within 1e-6 relative per row
    (central differences with step 1e-6 are accurate to ~1e-10)."""
    result = check_tangent(nen, states=8, seed=nen)
    assert result.max_relative_error < 1e-6, result


@pytest.mark.parametrize("wrong,eta", [(1, 0.0), (2, 1e-3)], ids=["tangent", "damping matrix"])
def test_tangent_checker_detects_a_wrong_tangent(monkeypatch, wrong, eta):
    """The checker must fail on a wrong tangent: the geometric stiffness of the element is
    ~1e-3 of its material part at these strains, so a tangent with one entry off by 1e-4 of
    its row must be reported above 1e-6; likewise the damping matrix d fe/d qd of a damped
    element (Kelvin-Voigt time eta = 1e-3 s, checked when eta > 0)."""
    import flexmbs.core as core
    real = core._core

    class Perturbed:
        @staticmethod
        def beam_element(length, stiff, qref, qe, eta, qde):
            out = [a.copy() for a in real.beam_element(length, stiff, qref, qe, eta, qde)]
            out[wrong][2, 5] += 1e-4 * np.abs(out[wrong][2]).max()
            return tuple(out)

    monkeypatch.setattr(core, "_core", Perturbed)
    assert check_tangent(3, states=2, damping_time=eta).max_relative_error > 1e-5


def test_robot_iteration_matrix_matches_finite_differences(robot50):
    """The whole iteration matrix of eq. (7) (beta' M + K_t + constraint terms, k-scaled
    multiplier columns) against central differences of the residual, at a converged state of
    the robot run (t = 0.4 s, its multipliers) and at a perturbed state with random
    multipliers, for the dynamic beta' (h = 5e-4, rho_inf = 0.5) and the static case
    beta' = 0 where K_t dominates: within 1e-6 relative per row."""
    r, m, _, _ = robot50
    j = 800
    rng = np.random.default_rng(5)
    states = [(r.q[j], r.qdd[j], r.mu[j], r.t[j]),
              (r.q[j] + 1e-2 * rng.standard_normal(m.ndof), rng.standard_normal(m.ndof),
               100 * rng.standard_normal(r.mu.shape[1]), 0.1)]
    for q, qdd, mu, t in states:
        for beta_prime in (None, 0.0):
            result = check_iteration_matrix(m, q, qdd, mu, t, beta_prime=beta_prime)
            assert result.max_relative_error < 1e-6, result


def test_iteration_matrix_with_rigid_links_and_loads():
    """Iteration matrix of a model with nonlinear constraints (rigid body: Hessian terms
    (mu + p Phi) Phi_qq), nodal loads and gravity, clamped beam of 2-node and 3-node
    elements, at a deformed state with random multipliers: within 1e-6 relative per row,
    for beta' of the paper's settings and beta' = 0."""
    m = fx.Model()
    a = m.add_beam("a", (0, 0), (1, 0.5), 3, material=STEEL, section=fx.Rectangle(0.02, 0.03))
    c = m.add_beam("c", (1, 0.5), (1.5, 1.5), 2, material=STEEL, section=fx.Circle(0.02), order=1)
    m.clamp(a.first)
    m.add_rigid_body("joint", [a.last, c.first], mass=2.0, inertia=0.1)
    m.add_load(c.last, fx=10, fy=-5, moment=3)
    m.set_gravity(1, -9.81)
    rng = np.random.default_rng(9)
    q = m.reference_coordinates() + 0.05 * rng.standard_normal(m.ndof)
    mu = 1e3 * rng.standard_normal(m.compile().nc)
    for beta_prime in (None, 0.0):
        result = check_iteration_matrix(m, q, None, mu, beta_prime=beta_prime)
        assert result.max_relative_error < 1e-6, result


def test_iteration_matrix_checker_detects_a_missing_penalty_term(monkeypatch):
    """The checker must fail when the matrix lacks the penalty terms p Phi_q^T Phi_q and
    p Phi Phi_qq (the residual keeps them)."""
    checks_module = sys.modules["flexmbs.analysis.checks"]
    real = checks_module.system_matrices

    def without_penalty_in_matrix(model, q, qdd=None, mu=None, t=0.0, *, cm=0.0, ck=1.0,
                                  kscale=0.0, penalty=0.0, props=None, qd=None, cc=0.0):
        r, _ = real(model, q, qdd, mu, t, cm=cm, ck=ck, kscale=kscale, penalty=penalty, qd=qd,
                    cc=cc)
        _, s = real(model, q, qdd, mu, t, cm=cm, ck=ck, kscale=kscale, penalty=0.0, qd=qd, cc=cc)
        return r, s

    m, _, _ = robot((50, 50, 50, 50))
    q = m.reference_coordinates()
    monkeypatch.setattr(checks_module, "system_matrices", without_penalty_in_matrix)
    result = check_iteration_matrix(m, q, t=0.1, beta_prime=0.0, penalty=1e9)
    assert result.max_relative_error > 1e-3


def test_system_matrices_at_t0_of_the_robot():
    """The tangent stiffness and residual of the robot at its initial state (t = 0, laws
    evaluated at t = 0 only), as the weakly coupled method needs them, against exact
    properties of the undeformed, unstressed state:
    - K_t is symmetric (hyperelastic beams, no stress: no load-stiffness term) and annihilates
      the three rigid motions of the plane (translations along x, y and the infinitesimal
      rotation about O: dx = -y, dy = x, dphi = 1 at every node), to round-off of K;
    - f_int = 0, so r = -f_ext: the residual sums to (0, +W) with W = (beam mass + 2 kg + 1 kg)
      g, the beam mass 229.02 sum p^2 = 2.2902 kg (docs/paper-cases.md), its moment about O to that of
      the point masses and of each arm's weight at its midpoint (uniform tubes at p = 50 mm);
    - the constraint rows vanish: the reference posture is the drives' position at t = 0."""
    m, _, _ = robot((50, 50, 50, 50))
    q = m.reference_coordinates()
    n = m.ndof
    r, s = system_matrices(m, q, t=0.0, kscale=1.0)
    k = s[:n, :n]
    scale = np.abs(k).max()
    np.testing.assert_allclose(k, k.T, rtol=0, atol=1e-12 * scale)
    xyz = q.reshape(-1, 3)
    modes = np.zeros((3, n))
    modes[0, 0::3] = 1.0
    modes[1, 1::3] = 1.0
    modes[2, 0::3], modes[2, 1::3], modes[2, 2::3] = -xyz[:, 1], xyz[:, 0], 1.0
    for v in modes:
        assert np.abs(k @ v).max() <= 1e-12 * scale * np.abs(v).max()
    g = 9.81
    beam_mass = 2700.0 * 0.36 * np.pi / 4 * 0.05 ** 2 * 1.2          # 2 arms of 0.6 m
    assert beam_mass == pytest.approx(229.02 * 4 * 0.05 ** 2, rel=1e-5)
    f = r[:n].reshape(-1, 3)
    assert f[:, 0].sum() == pytest.approx(0.0, abs=1e-12)
    assert f[:, 1].sum() == pytest.approx((beam_mass + 3.0) * g, rel=1e-12)
    # moment about O of -f_ext (r = +m g in y): sum x_i r_y,i - y_i r_x,i + r_phi,i
    a = np.array([0.6 * math.cos(math.radians(120)), 0.6 * math.sin(math.radians(120))])
    tip = a + 0.6 * np.array([math.cos(math.radians(-30)), math.sin(math.radians(-30))])
    moment = g * (beam_mass / 2 * (a[0] / 2 + (a[0] + tip[0]) / 2) + 2.0 * a[0] + 1.0 * tip[0])
    got = np.sum(xyz[:, 0] * f[:, 1] - xyz[:, 1] * f[:, 0] + f[:, 2])
    assert got == pytest.approx(moment, rel=1e-12, abs=1e-12 * (beam_mass + 3) * g)
    assert np.abs(r[n:]).max() <= 1e-12


# ---------------------------------------------------------------------------- 7. statistics
def test_robot_runs_1301_steps_with_few_newton_iterations(robot50):
    """The robot at p = [50, 50, 50, 50] mm (docs/paper-cases.md), h = 5e-4 s, 0.65 s: 1301 time steps
    (grid points) with on average at most 3 Newton iterations per step (measured
    2.0), no step cut, and the result carries the solver statistics."""
    r = robot50[0]
    st = r.stats
    assert r.t.size == 1301 and st["steps"] == 1300
    for key in ("newton_iterations", "factorizations", "residual_evaluations", "step_cuts",
                "static_iterations", "solver", "unknowns"):
        assert key in st
    assert st["newton_iterations"] / st["steps"] <= 3.0
    assert r.mean_newton_iterations == st["newton_iterations"] / st["steps"]
    assert st["step_cuts"] == 0 and st["static_iterations"] >= 1
    assert st["factorizations"] >= st["newton_iterations"]          # full Newton
    assert st["residual_evaluations"] >= st["newton_iterations"]
    assert st["unknowns"] == r.q.shape[1] + r.mu.shape[1]


# ---------------------------------------------------------------------------- Jacobian reuse
def test_jacobian_reuse_gives_the_same_trajectory_with_fewer_factorizations(robot50):
    """Modified Newton (newton="reuse") converges to the same discrete solution up to
    the Newton tolerance at each step: a per-step difference <= tol qscale, carried by the
    (stable) dynamics over 1300 steps, bounds the trajectory difference by 1300 tol qscale
    = 1.3e-7 m (measured 5.3e-8). It must factor far less often (measured 22 vs 2604)."""
    r_full = robot50[0]
    r_reuse = simulate_robot(newton="reuse")[0]
    assert np.abs(r_reuse.q - r_full.q).max() <= r_full.stats["steps"] * NEWTON_TOL
    assert r_reuse.stats["factorizations"] < 0.1 * r_full.stats["factorizations"]


# ---------------------------------------------------------------------------- failures
def test_newton_failure_reports_time_residual_and_iterations():
    """A time step as long as the whole run (h = 0.65 s) with step cutting disabled: Newton
    cannot converge; SimulationError carries the time of the failed step, the last scaled
    increment and the iteration count (= max_iter)."""
    m, _, _ = robot((50, 50, 50, 50))
    with pytest.raises(SimulationError) as err:
        fx.simulate(m, 0.65, 0.65,
                    settings=SimulationSettings(start="static", max_cuts=0, max_iter=20))
    e = err.value
    assert e.time == pytest.approx(0.65)
    assert e.iterations == 20
    assert np.isfinite(e.residual) and e.residual > NEWTON_TOL
    assert "t = 0.65" in str(e)


def test_jumping_motor_law_fails_after_step_cuts():
    """A motor law that jumps by 30 rad at t = 0.1 s (with zero rate): no step cut can make
    Newton follow it; SimulationError names a time within the step of the jump."""
    jump = fx.TimeLaw(lambda t: np.where(t < 0.1 - 1e-9, 0.0, 30.0), lambda t: 0 * t,
                      lambda t: 0 * t, name="jumping motor")
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.6, 0), 2, material=STEEL,
                   section=fx.Tube.with_wall_ratio(0.05, 0.1))
    m.pin(b.first)
    m.drive_rotation(b.first, jump)
    m.add_point_mass(b.last, 1.0)
    with pytest.raises(SimulationError) as err:
        fx.simulate(m, 0.2, 5e-4)
    e = err.value
    assert 0.1 - 5e-4 < e.time <= 0.1 + 1e-12
    assert e.iterations >= 1 and e.residual > NEWTON_TOL


def test_motor_law_returning_nan_raises_model_error_naming_the_law():
    """A motor law that returns NaN from t = 0.1 s is caught when the laws are tabulated,
    before the Fortran loop: ModelError naming the law and the time."""
    law = fx.TimeLaw(lambda t: np.where(t < 0.1, 0.0, np.nan), lambda t: 0 * t, lambda t: 0 * t,
                     name="broken motor")
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.6, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.pin(b.first)
    m.drive_rotation(b.first, law)
    with pytest.raises(ModelError, match="broken motor.*t = 0.1"):
        fx.simulate(m, 0.2, 5e-4)


@pytest.mark.parametrize("bad, match", [
    (lambda m: fx.simulate(m, 0.1, 0.0), "h must be"),
    (lambda m: fx.simulate(m, 0.1, -1e-3), "h must be"),
    (lambda m: fx.simulate(m, 0.1, 3e-2), "whole number of steps"),
    (lambda m: fx.simulate(m, 0.1, 1e-3, settings=SimulationSettings(rho_inf=1.5)), "rho_inf"),
    (lambda m: fx.simulate(m, 0.1, 1e-3, settings=SimulationSettings(rho_inf=-0.1)), "rho_inf"),
    (lambda m: fx.Circle(-0.01), "diameter"),
    (lambda m: fx.Tube(0.02, 0.015), "thickness"),
    (lambda m: m.set_section("no such arm", fx.Circle(0.02)), "no such arm"),
    (lambda m: m.body("no such arm"), "no such arm"),
], ids=["h=0", "h<0", "t_end not multiple of h", "rho_inf>1", "rho_inf<0",
        "negative diameter", "wall thicker than radius", "unknown body (set_section)",
        "unknown body"])
def test_bad_input_raises_model_error(bad, match):
    """Invalid settings and inputs raise ModelError (a ValueError) naming the input."""
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.6, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.clamp(b.first)
    with pytest.raises(ModelError, match=match):
        bad(m)


# ---------------------------------------------------------------------------- laws on a grid
def _driven_arm(law):
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (0.6, 0), 2, material=STEEL, section=fx.Circle(0.02))
    m.add_point_mass(b.last, 1.0)
    m.pin(b.first)
    m.drive_rotation(b.first, law)
    m.set_gravity(0, -9.81)
    return m, b


def test_motor_law_given_as_samples_on_the_grid_matches_the_callable():
    """A law given as samples (TimeLaw.samples: a not-a-knot cubic spline) reproduces a cubic
    polynomial exactly, values and derivatives; so theta(t) = 2 t^3 - t^2 sampled on the time
    grid drives the arm exactly as the analytic law does: same trajectory to round-off
    (1e-12 m against arm motions of ~0.1 m)."""
    h, t_end = 1e-3, 0.2
    t = np.arange(0, t_end + h / 2, h)
    exact = fx.TimeLaw(lambda s: 2 * s**3 - s**2, lambda s: 6 * s**2 - 2 * s, lambda s: 12 * s - 2)
    sampled = fx.TimeLaw.samples(t, 2 * t**3 - t**2)
    m1, b1 = _driven_arm(exact)
    m2, b2 = _driven_arm(sampled)
    r1 = fx.simulate(m1, t_end, h)
    r2 = fx.simulate(m2, t_end, h)
    assert np.abs(r1.position(b1.last)[-1] - r1.position(b1.last)[0]).max() > 1e-3
    np.testing.assert_allclose(r2.q, r1.q, rtol=0, atol=1e-12)


def test_prescribed_position_is_followed_at_every_step():
    """prescribe_position: the node follows x(t) = 0.1 t^2, y(t) = 0.05 sin(10 t) to the Newton
    tolerance (1e-10 m) at every step, while the beam hanging from it swings."""
    m = fx.Model()
    b = m.add_beam("hanger", (0, 0), (0, -0.5), 2, material=STEEL, section=fx.Circle(0.01))
    m.add_point_mass(b.last, 0.5)
    m.prescribe_position(b.first,
                         x=fx.TimeLaw(lambda t: 0.1 * t**2, lambda t: 0.2 * t, lambda t: 0.2 + 0 * t),
                         y=fx.TimeLaw(lambda t: 0.05 * np.sin(10 * t), lambda t: 0.5 * np.cos(10 * t),
                                      lambda t: -5 * np.sin(10 * t)))
    m.set_gravity(0, -9.81)
    r = fx.simulate(m, 0.5, 1e-3)
    p = r.position(b.first)
    np.testing.assert_allclose(p[:, 0], 0.1 * r.t**2, atol=1e-10)
    np.testing.assert_allclose(p[:, 1], 0.05 * np.sin(10 * r.t), atol=1e-10)
    # the hanging mass lags behind the accelerating support: the beam rotates
    assert np.ptp(r.rotation(b.first)) > 1e-3
