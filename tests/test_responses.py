"""Responses (flexmbs.responses): stress, constraint forces, aggregation, and their gradients.

Each test names the analytic value it checks and where it comes from. Tolerances are set by
what the model neglects (geometric nonlinearity, flexibility, time discretisation) and are at
least 10x above the measured error, quoted in each docstring.
"""
import math

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.checks import taylor_test
from flexmbs.errors import ModelError
from flexmbs.responses import aggregate, beam_stress, joint_reaction, ks, motor_torque, pnorm
from flexmbs.analysis.settings import DesignDerivatives, SimulationSettings

STEEL = fx.Material(E=210e9, nu=0.3, rho=7800)
G = 9.81


def cantilever(section, elements, order=2, L=1.0, material=STEEL):
    """A beam along x, clamped at x = 0."""
    m = fx.Model()
    b = m.add_beam("beam", (0.0, 0.0), (L, 0.0), elements, material=material, section=section,
                   order=order)
    m.clamp(b.first)
    return m, b


# ---------------------------------------------------------------------------- stress
@pytest.mark.parametrize("order", [2, 1], ids=["quadratic", "linear"])
@pytest.mark.parametrize("section", [fx.Circle(0.05), fx.Rectangle(0.05, 0.1), fx.Tube(0.06, 0.005)],
                         ids=["circle", "rectangle", "tube"])
def test_cantilever_bending_stress_at_the_gauss_stations(section, order):
    """Cantilever (L = 1 m, 4 elements) under a vertical tip load P, static: at the station s
    the larger fibre stress is P (L - s) c / I (Euler-Bernoulli / Navier; the Timoshenko beam
    has the same moment M = P (L - s)) plus the axial stress P sin(theta(s)) / A of the load
    seen in the rotated section, theta(s) = P (L s - s^2 / 2) / EI (a 6e-6 relative effect
    near the tip). Quadratic elements represent the linear curvature exactly; the 2-node
    element's one Gauss point is its midpoint, where its constant curvature is exact (see
    test_simulator's linear-element test). What is left is the geometric nonlinearity
    (P L^2 / EI = 1e-4): measured 6e-9 .. 2e-7 relative; tolerance 2e-6. The mean shear stress
    is P / (k A) (Q = P, Cowper's k): measured 1e-9; tolerance 1e-6."""
    m, b = cantilever(section, 4, order)
    EA, kGA, EI, _, _ = section.properties(STEEL)
    A, I = EA / STEEL.E, EI / STEEL.E
    P = 1e-4 * EI
    m.add_load(b.last, fy=-P)
    r = fx.simulate(m, 2e-3, 1e-3, settings=SimulationSettings(start="static"))
    st = beam_stress(m, r, b, shear=True)
    c = st.half_depth
    assert c == pytest.approx(0.5 * (section.h if isinstance(section, fx.Rectangle) else section.d))
    s = st.s[None]
    theta = P * (s - s * s / 2) / EI
    expected = P * (1.0 - s) * c[None, :, None] / I + P * np.sin(theta) / A
    assert np.abs(st.normal / expected - 1).max() < 2e-6
    root = P * 1.0 * c[0] / I             # P L c / I, the root value
    assert st.normal[:, 0, 0].max() < root                      # the first station is inside
    assert np.abs(st.shear / (P * STEEL.G / kGA) - 1).max() < 1e-6
    assert np.allclose(st.von_mises, np.sqrt(st.normal ** 2 + 3 * st.shear ** 2), rtol=1e-14)



@pytest.mark.parametrize("order", [2, 1], ids=["quadratic", "linear"])
def test_normal_stress_partials_at_chosen_stations(order):
    """normal_partials (the adjoint's seeds of a largest stress: one station per step) on a
    cantilever under a tip load with an axial part (eps 1e-3 and kappa nonzero, far from the
    kinks of |eps| and |kappa| at 0 for the step used): at chosen (step, element, station)
    triples its partials with respect to the element's coordinates equal central
    differences of beam_stress's normal stress in those coordinates (step 1e-7 m or rad:
    truncation and rounding about 1e-9 relative; tolerance 1e-6), and equal
    beam_stress(local=True)'s partials of every station, and its d/dc E |kappa|, to rounding
    (1e-12 relative)."""
    from dataclasses import replace
    from flexmbs.responses.stress import normal_partials
    section = fx.Tube(0.06, 0.005)
    m, b = cantilever(section, 4, order)
    EA, _, EI, _, _ = section.properties(STEEL)
    m.add_load(b.last, fx=1e-3 * EA, fy=-1e-3 * EI)        # eps 1e-3, kappa up to 1e-3 / m
    r = fx.simulate(m, 2e-3, 1e-3, settings=SimulationSettings(start="static", store="all"))
    st = beam_stress(m, r, b, local=True)
    nt, nel, nst = st.normal.shape
    steps = np.array([0, nt - 1, nt - 1, 1])
    elems = np.array([0, 3, 1, 2])
    stats = np.array([0, nst - 1, 0, nst - 1])
    dofs, d, d_dc = normal_partials(m, r, b, st, steps, elems, stats)
    local = st.d_normal_local[steps, elems, stats]
    assert np.array_equal(dofs, st.dofs[elems])
    assert np.abs(d - local).max() < 1e-12 * np.abs(local).max()
    ref = st.d_normal_dc[steps, elems, stats]
    assert np.abs(d_dc - ref).max() < 1e-12 * np.abs(ref).max()
    h = 1e-7
    fd = np.zeros_like(d)
    for i in range(steps.size):
        for a in range(dofs.shape[1]):
            col = int(np.searchsorted(r.dofs, dofs[i, a]))
            plus, minus = r.q.copy(), r.q.copy()
            plus[steps[i], col] += h
            minus[steps[i], col] -= h
            up = beam_stress(m, replace(r, q=plus), b).normal[steps[i], elems[i], stats[i]]
            dn = beam_stress(m, replace(r, q=minus), b).normal[steps[i], elems[i], stats[i]]
            fd[i, a] = (up - dn) / (2 * h)
    assert np.abs(d - fd).max() < 1e-6 * np.abs(fd).max()


def test_cantilever_root_stress_at_the_nodes():
    """Stations at the nodes: the root stress P L c / I (Euler-Bernoulli), exactly represented
    by the quadratic element's linear curvature, and P (L - h / 2) c / I for 2-node elements,
    whose curvature is constant, equal to its value at the element's midpoint. Measured 1.6e-5
    (quadratic) and 2.7e-5 (linear) relative, the geometric nonlinearity P L^2 / EI = 1e-4
    seen at the element's end; tolerance 5e-4."""
    section = fx.Circle(0.05)
    EA, _, EI, _, _ = section.properties(STEEL)
    P = 1e-4 * EI
    c, I, L = 0.025, EI / STEEL.E, 1.0
    for order, elements, tol in ((2, 4, 5e-4), (1, 4, 5e-4)):
        m, b = cantilever(section, elements, order)
        m.add_load(b.last, fy=-P)
        st = beam_stress(m, fx.simulate(m, 2e-3, 1e-3, SimulationSettings(start="static")), b,
                         stations="nodes")
        arm = L if order == 2 else L - 0.5 * L / elements
        assert st.xi[0] == -1.0 and st.s[0, 0] == 0.0
        assert abs(st.normal[-1, 0, 0] / (P * arm * c / I) - 1) < tol


def test_axial_bar_stress_is_n_over_a():
    """A clamped bar under an axial tip force N: sigma = N / A at every station (measured
    1e-11 relative; tolerance 1e-8), no bending."""
    section = fx.Circle(0.05)
    m, b = cantilever(section, 3)
    EA = section.properties(STEEL)[0]
    N = 1e-4 * EA
    m.add_load(b.last, fx=N)
    st = beam_stress(m, fx.simulate(m, 2e-3, 1e-3, settings=SimulationSettings(start="static")), b)
    A = math.pi / 4 * 0.05 ** 2
    assert np.abs(st.normal / (N / A) - 1).max() < 1e-8
    assert np.abs(st.axial / (N / A) - 1).max() < 1e-8


def _spin_law(omega, T):
    """Spin-up to omega in T s with a smooth (1 - cos) angular acceleration (Simo & Vu-Quoc
    1986 law), then constant speed."""
    a = 2 * math.pi / T

    def f(t):
        t = np.asarray(t, float)
        return np.where(t < T, omega / T * (t * t / 2 + (np.cos(a * t) - 1) / a ** 2),
                        omega * (t - T / 2))

    def df(t):
        t = np.asarray(t, float)
        return np.where(t < T, omega / T * (t - np.sin(a * t) / a), omega + 0 * t)

    def ddf(t):
        t = np.asarray(t, float)
        return np.where(t < T, omega / T * (1 - np.cos(a * t)), 0 * t)
    return fx.TimeLaw(f, df, ddf, name="spin-up")


def test_rotating_beam_centrifugal_stress():
    """A beam (L = 1 m, steel, d = 50 mm) pinned and driven at its root, spun up to
    omega = 30 rad/s in 1 s, then at constant speed. The centrifugal axial stress of a uniform
    bar in rigid rotation is sigma(s) = rho omega^2 (L^2 - s^2) / 2 (equilibrium of the outer
    part: N(s) = int_s^L rho A omega^2 x dx; e.g. Timoshenko & Goodier, Theory of Elasticity,
    rotating disc/bar), rho omega^2 L^2 / 2 at the root. Elastic stretching changes it by
    rho omega^2 L^2 / E = 3e-5. Over t in [1.2, 1.5] s: the axial stress E eps matches at every
    Gauss station within 2.4e-4 (measured; time discretisation, 9e-4 at h = 2e-3, 8e-5 at
    h = 5e-4; tolerance 5e-3); the response (the larger fibre stress, which includes the
    residual bending vibration left by the spin-up) averaged over that window matches the root
    value within 5e-4 (measured; tolerance 1e-2)."""
    L, omega = 1.0, 30.0
    m = fx.Model()
    b = m.add_beam("blade", (0, 0), (L, 0), 4, material=STEEL, section=fx.Circle(0.05))
    m.pin(b.first)
    m.drive_rotation(b.first, _spin_law(omega, 1.0))
    r = fx.simulate(m, 1.5, 1e-3)
    st = beam_stress(m, r, b)
    late = r.t >= 1.2
    exact = STEEL.rho * omega ** 2 * (L ** 2 - st.s ** 2) / 2
    assert np.abs(st.axial[late] / exact[None] - 1).max() < 5e-3
    assert abs(st.normal[late, 0, 0].mean() / exact[0, 0] - 1) < 1e-2


# ---------------------------------------------------------------------------- forces
def test_motor_torque_of_a_stiff_arm_under_gravity():
    """Rigid-body dynamics of a uniform arm about its pinned end O, driven by a motor with
    theta(t) = theta0 + a t^3 / 6 (alpha = a t) under gravity -y: the motor torque is
    I_O alpha + m g (L/2) cos(theta), I_O = rhoA L^3 / 3 + rhoI L (the centrifugal forces pass
    through O). The arm is steel with E x 100 (very stiff: the flexible lag of a steel arm
    changes the torque by 1e-3, that of this one by 1e-5). Static start. Measured after the
    first 50 steps: 4e-6 of the largest torque; tolerance 1e-4. The sign is the module's
    convention: positive counter-clockwise on the driven body, so lifting needs a positive
    torque."""
    stiff = fx.Material(E=100 * STEEL.E, nu=0.3, rho=STEEL.rho)
    L, a, th0 = 1.0, 4.0, 0.3
    section = fx.Circle(0.05)
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (L * math.cos(th0), L * math.sin(th0)), 4, material=stiff,
                   section=section)
    m.pin(b.first)
    m.drive_rotation(b.first, fx.TimeLaw(lambda t: th0 + a * np.asarray(t) ** 3 / 6,
                                         lambda t: a * np.asarray(t) ** 2 / 2,
                                         lambda t: a * np.asarray(t)))
    m.set_gravity(0, -G)
    r = fx.simulate(m, 1.0, 1e-3, settings=SimulationSettings(start="static"))
    torque, grad = motor_torque(m, r, b.first)
    assert grad is None
    _, _, _, rhoA, rhoI = section.properties(stiff)
    theta, alpha = th0 + a * r.t ** 3 / 6, a * r.t
    expected = (rhoA * L ** 3 / 3 + rhoI * L) * alpha + rhoA * L * G * L / 2 * np.cos(theta)
    after = r.t >= 0.05
    assert np.abs(torque - expected)[after].max() < 1e-4 * np.abs(expected).max()
    # the same row by its label
    assert np.array_equal(motor_torque(m, r, f"motor node {b.first}")[0], torque)


def hanging_chain():
    """Two rods (1 m, steel, d = 20 mm) hanging from a pin at the origin, joined by a hinge,
    3 kg at the bottom, gravity -y."""
    m = fx.Model()
    sec = fx.Circle(0.02)
    b1 = m.add_beam("rod1", (0, 0), (0, -1), 2, material=STEEL, section=sec)
    b2 = m.add_beam("rod2", (0, -1), (0, -2), 2, material=STEEL, section=sec)
    m.pin(b1.first)
    m.hinge(b1.last, b2.first)
    m.add_point_mass(b2.last, 3.0)
    m.set_gravity(0, -G)
    return m, b1, b2, sec


def test_pin_and_hinge_reactions_of_a_hanging_chain_at_rest():
    """Two rods (1 m, steel, d = 20 mm) hanging from a pin and joined by a hinge, 3 kg at the
    bottom, gravity -y, released from the reference configuration: once the axial transient
    of the release has died out (numerical damping, rho_inf = 0.5), statics gives the pin's
    force on the upper rod (0, m g + 2 w) and the hinge's force on the upper rod's end
    (0, -(m g + w)), w the weight of one rod (the lower part hangs on it). Measured over the
    last 50 steps of 0.2 s: 8e-8 relative (what is left of the transient); tolerance 1e-6."""
    m, b1, b2, sec = hanging_chain()
    r = fx.simulate(m, 0.2, 1e-3)
    w = sec.properties(STEEL)[3] * 1.0 * G
    pin = joint_reaction(m, r, f"pin node {b1.first}")
    hinge = joint_reaction(m, r, f"hinge {b1.last}-{b2.first}")
    last = slice(-50, None)
    W = 3.0 * G
    assert np.abs(pin.y[last] / (W + 2 * w) - 1).max() < 1e-6
    assert np.abs(pin.magnitude[last] / (W + 2 * w) - 1).max() < 1e-6
    assert np.abs(hinge.y[last] / (W + w) + 1).max() < 1e-6
    assert np.abs(np.r_[pin.x[last], hinge.x[last]]).max() < 1e-6 * W
    assert pin.dx is None


def test_reaction_gradient_is_minus_dmu():
    """With dmu given, the force gradients follow the convention F = -mu: dF = -dmu, and
    d|F| = (Fx dFx + Fy dFy) / |F| (checked on an arbitrary dmu: algebra, not simulation)."""
    m = hanging_chain()[0]
    r = fx.simulate(m, 0.02, 1e-3)
    dmu = np.random.default_rng(1).standard_normal(r.mu.shape + (3,))
    rc = joint_reaction(m, r, (0, 1), dmu=dmu)
    assert np.array_equal(rc.dx, -dmu[:, 0]) and np.array_equal(rc.dy, -dmu[:, 1])
    fx_, fy_ = -r.mu[:, 0], -r.mu[:, 1]
    expected = (fx_[:, None] * -dmu[:, 0] + fy_[:, None] * -dmu[:, 1]) / np.hypot(fx_, fy_)[:, None]
    assert np.allclose(rc.dmagnitude, expected, rtol=1e-12, atol=0)


def test_force_responses_reject_unknown_rows():
    """Bad rows: a ModelError naming the label given and the rows that exist."""
    m = fx.Model()
    b = m.add_beam("rod", (0, 0), (0, -1), 2, material=STEEL, section=fx.Circle(0.02))
    m.pin(b.first)
    r = fx.simulate(m, 0.002, 1e-3)
    with pytest.raises(ModelError, match="no constraint row labelled 'hinge 1-2'.*pin node 0 x"):
        joint_reaction(m, r, "hinge 1-2")
    with pytest.raises(ModelError, match=r"node 0 has 0 rotation drives"):
        motor_torque(m, r, 0)
    with pytest.raises(ModelError, match=r"row must be a label or a row index in \[0, 2\), got 5"):
        joint_reaction(m, r, (0, 5))


# ---------------------------------------------------------------------------- aggregation
def _history(nt=401, nv=3, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0, nt)
    base = 1.0 + 0.3 * np.sin(3 * t) + 0.05 * rng.standard_normal(nt)
    modes = np.stack([np.cos((k + 1) * t) for k in range(nv)], axis=1)
    return t, base, modes


@pytest.mark.parametrize("rho", [20.0, 100.0, 1000.0])
def test_ks_and_pnorm_bounds(rho):
    """Kreisselmeier-Steinhauser bounds: max r <= KS <= max r + ln(N) / rho over the N samples;
    p-norm: max |r| <= PN <= N^(1/P) max |r| (P = rho / 10 > 1), on a history of 401 steps,
    for the whole history and for a window."""
    t, r, _ = _history()
    for window in (None, (0.5, 1.2)):
        sel = r if window is None else r[(t >= 0.5) & (t <= 1.2)]
        val, _ = aggregate(r, how="ks", parameter=rho, t=t, window=window)
        assert sel.max() <= val <= sel.max() + math.log(sel.size) / rho
        p = rho / 10
        val, _ = aggregate(r, how="pnorm", parameter=p, t=t, window=window)
        assert sel.max() <= val <= sel.size ** (1 / p) * sel.max()
        assert aggregate(r, how="max", t=t, window=window)[0] == sel.max()


def test_windows_select_their_samples():
    """A window [t0, t1] keeps exactly the steps with t0 <= t <= t1, ends included (grid
    points 0.5 and 1.2 of a 0.005 s grid): 141 steps; 'every_step' returns them in order, and
    'max' sees a spike outside the window only when the window holds it."""
    t, r, modes = _history()
    spike = r.copy()
    spike[10] = 50.0                                    # t = 0.05, outside [0.5, 1.2]
    vals, grads = aggregate(spike, modes, "every_step", t=t, window=(0.5, 1.2))
    inside = np.arange(100, 241)
    assert vals.shape == (141,) and np.array_equal(vals, spike[inside])
    assert np.array_equal(grads, modes[inside])
    assert aggregate(spike, how="max", t=t, window=(0.5, 1.2))[0] < 50.0
    assert aggregate(spike, how="max", t=t, window=(0.0, 0.05))[0] == 50.0
    # several samples per step: a window selects whole steps
    two = np.stack([r, 2 * r], axis=1)
    assert aggregate(two, how="max", t=t, window=(0.5, 1.2))[0] == 2 * r[inside].max()


@pytest.mark.parametrize("how", ["max", "ks", "pnorm", "every_step"])
def test_aggregate_gradients_pass_the_taylor_test(how):
    """Taylor test (flexmbs.analysis.checks.taylor_test) of every aggregate of the analytic history
    r(v) = base + sin(modes v) (nt = 401, nv = 3, window [0.3, 1.7] s), whose derivative is
    cos(modes v) modes: order > 1.8 for the gradient returned, < 1.3 with a 1e-3 relative
    error in one component. 'max' is smooth where its argmax does not change: one sample
    stands 0.5 above the others, far more than the steps (2^-8 .. 2^-13) move it."""
    t, base, modes = _history()

    def history(v):
        return base + np.sin(modes @ v), np.cos(modes @ v)[:, None] * modes

    base = base.copy()
    base[200] += 0.5                 # t = 1: an isolated largest sample, so 'max' is smooth
    v0 = np.array([0.1, -0.2, 0.05])
    r0, dr0 = history(v0)
    par = {"ks": 50.0, "pnorm": 8.0}.get(how)
    val, grad = aggregate(r0, dr0, how, parameter=par, t=t, window=(0.3, 1.7))
    wrong = np.array(grad, float).copy()
    wrong[..., 0] += 1e-3 * np.linalg.norm(grad, axis=-1)

    def fun(v):
        out = np.asarray(aggregate(history(v)[0], None, how, parameter=par, t=t,
                                   window=(0.3, 1.7))[0])
        return {"right": out, "perturbed": out}

    chk = taylor_test(fun, v0, {"right": np.asarray(grad), "perturbed": wrong},
                      np.array([0.6, 0.3, -0.74]), step=2.0 ** -8, halvings=5)
    assert chk["right"].ok, chk["right"].table()
    assert not chk["perturbed"].ok and chk["perturbed"].order < 1.3, chk["perturbed"].table()


def test_ks_and_pnorm_functions_match_their_definitions():
    """ks and pnorm against their textbook forms (1/rho) ln(sum exp(rho r)) and
    (sum |r|^P)^(1/P) on small values where the direct forms do not overflow."""
    r = np.array([0.3, -0.1, 0.25, 0.05])
    assert ks(r, rho=7.0)[0] == pytest.approx(np.log(np.exp(7.0 * r).sum()) / 7.0, rel=1e-13)
    assert pnorm(r, p=3.0)[0] == pytest.approx((np.abs(r) ** 3).sum() ** (1 / 3), rel=1e-13)


def test_aggregate_rejects_bad_input():
    """Unknown aggregation, bad parameter, a window without times or without samples: a
    ModelError naming the argument, the value and what is allowed."""
    t, r, modes = _history()
    with pytest.raises(ModelError, match="how='mean' is unknown; allowed: every_step, max, ks"):
        aggregate(r, how="mean")
    with pytest.raises(ModelError, match="parameter of 'pnorm' must be a finite number > 1, got 0.5"):
        aggregate(r, how="pnorm", parameter=0.5)
    with pytest.raises(ModelError, match="window needs the times t"):
        aggregate(r, how="max", window=(0, 1))
    with pytest.raises(ModelError, match=r"window \(3.0, 4.0\) holds no time step"):
        aggregate(r, how="max", t=t, window=(3.0, 4.0))
    with pytest.raises(ModelError, match=r"dr must have shape \(401,\) \+ \(nv,\)"):
        aggregate(r, modes[:10], how="ks")


# ---------------------------------------------------------------------------- stress gradient
def _stress_run(d, with_gradient, dynamic, elements=3):
    section = fx.Circle(d)
    m, b = cantilever(section, elements)
    P = 1e-3 * fx.Circle(0.05).properties(STEEL)[2]          # fixed load, whatever d
    if dynamic:
        w = 200.0
        law = fx.TimeLaw(lambda t: 1 - np.cos(w * np.asarray(t)),
                         lambda t: w * np.sin(w * np.asarray(t)),
                         lambda t: w * w * np.cos(w * np.asarray(t)))
        m.add_load(b.last, fx=0.3 * P, fy=-P, law=law)
    else:
        m.add_load(b.last, fx=0.3 * P, fy=-P)
    derivatives = None
    if with_gradient:
        dprop = np.repeat(section.property_derivatives(STEEL)[:, None, :], elements, axis=1)
        derivatives = DesignDerivatives(properties=dprop, dofs=b.dofs)
    r = fx.simulate(m, 0.02 if dynamic else 2e-3, 1e-3,
                    SimulationSettings(start="rest" if dynamic else "static"),
                    derivatives=derivatives)
    dc = np.full((elements, 1), 0.5) if with_gradient else None       # c = d / 2
    return beam_stress(m, r, b, shear=True, dc=dc)


@pytest.mark.parametrize("dynamic", [False, True], ids=["static", "dynamic"])
def test_stress_gradient_passes_the_taylor_test(dynamic):
    """Design gradient of the stress histories (normal, shear, von Mises) of a cantilever with
    the diameter d = 50 mm of its Circle section as design variable (dprop from
    Section.property_derivatives, dc/dd = 1/2), tip load (0.3 P, -P), P L^2 / EI = 1e-3: static
    (3 steps at rest) and dynamic (a 1 - cos load from rest, 20 steps). Taylor test along d:
    order > 1.8 for the gradients returned, and not ok (order < 1.3) with a 1e-3 relative
    error. Steps 2^-12 d .. 2^-17 d: measured order 2.00 (right), 0.90-0.99 (perturbed); the
    smallest remainders (1.7e-3 Pa normal, 6.5e-6 Pa shear) are 800-1500x above the rounding
    floor 1e3 eps max|r| that taylor_test applies."""
    d0 = 0.05
    st = _stress_run(d0, True, dynamic)
    names = ("normal", "shear", "von_mises")
    jac = {n: getattr(st, "d_" + n) for n in names}
    jac.update({n + " perturbed": j + 1e-3 * np.abs(j) for n, j in list(jac.items())})

    def fun(x):
        s = _stress_run(float(x[0]), False, dynamic)
        out = {n: getattr(s, n) for n in names}
        out.update({n + " perturbed": v for n, v in list(out.items())})
        return out

    chk = taylor_test(fun, np.array([d0]), jac, np.array([1.0]), step=2.0 ** -12 * d0,
                      halvings=5)
    for n in names:
        assert chk[n].ok, chk[n].table()
        assert not chk[n + " perturbed"].ok and chk[n + " perturbed"].order < 1.3, \
            chk[n + " perturbed"].table()


def test_stress_rejects_bad_input():
    """beam_stress: a GivenSection beam (no E, no depth), unstored coordinates, a wrong dc, a
    gradient without design derivatives: ModelError naming what is wrong."""
    m = fx.Model()
    g = m.add_beam("given", (0, 0), (1, 0), 2,
                   section=fx.GivenSection(EA=1e8, kGA=1e7, EI=1e4, rhoA=10.0, rhoI=1e-3))
    m.clamp(g.first)
    b = m.add_beam("steel", (0, 1), (1, 1), 2, material=STEEL, section=fx.Circle(0.05))
    m.clamp(b.first)
    r = fx.simulate(m, 0.002, 1e-3, settings=SimulationSettings(store=[b]))
    with pytest.raises(ModelError, match="beam 'given' has no material"):
        beam_stress(m, r, "given")
    m2, b2 = cantilever(fx.Circle(0.05), 2)
    r2 = fx.simulate(m2, 0.002, 1e-3, settings=SimulationSettings(store=[b2.last]))
    with pytest.raises(ModelError, match="coordinates of beam 'beam' were not stored"):
        beam_stress(m2, r2, b2)
    with pytest.raises(ModelError, match=r"dc must be a finite \(2, nv\) array"):
        beam_stress(m, r, b, dc=np.zeros(3))
    with pytest.raises(ModelError, match="the result has no design derivatives"):
        beam_stress(m, r, b, dc=np.zeros((2, 1)))
    with pytest.raises(ModelError, match="stations='middle' is unknown"):
        beam_stress(m, r, b, stations="middle")


# ---------------------------------------------------------------------------- aggregate weights
def test_aggregate_weights_have_their_closed_forms():
    """aggregate_weights (the adjoint's per-sample weights, W @ dr = aggregate's gradient):
    KS of r = [0, ln 2 / rho] has the softmax weights exp(rho r) / sum = [1/3, 2/3] and the
    value ln(3) / rho; the p-norm (P = 2) of [3, 4] is 5 with weights r / 5 = [0.6, 0.8];
    'max' weighs its largest sample alone; 'every_step' within a window (t0, t1) selects the
    samples inside, one row each; a window's KS weighs only the samples inside it (exact
    arithmetic up to rounding: 1e-14)."""
    from flexmbs.responses.aggregate import aggregate_weights
    rho = 50.0
    v, W = aggregate_weights([0.0, math.log(2.0) / rho], "ks", parameter=rho)
    assert v == pytest.approx(math.log(3.0) / rho, rel=1e-14)
    assert W == pytest.approx(np.array([[1 / 3, 2 / 3]]), abs=1e-14)
    v, W = aggregate_weights([3.0, -4.0], "pnorm", parameter=2.0)
    assert v == pytest.approx(5.0, rel=1e-14)
    assert W == pytest.approx(np.array([[0.6, -0.8]]), abs=1e-14)
    v, W = aggregate_weights([1.0, 7.0, 2.0], "max")
    assert v == 7.0 and W.tolist() == [[0.0, 1.0, 0.0]]
    t = np.array([0.0, 0.1, 0.2, 0.3])
    v, W = aggregate_weights([1.0, 2.0, 3.0, 4.0], "every_step", t=t, window=(0.1, 0.2))
    assert v.tolist() == [2.0, 3.0] and W.tolist() == [[0, 1, 0, 0], [0, 0, 1, 0]]
    v, W = aggregate_weights([9.0, 0.0, math.log(2.0) / rho, 9.0], "ks", parameter=rho, t=t,
                             window=(0.1, 0.2))
    assert W == pytest.approx(np.array([[0.0, 1 / 3, 2 / 3, 0.0]]), abs=1e-14)
