"""Vibration modes of a mechanism at a state (flexmbs.analysis.modes) and the modes a time step
cannot resolve: beam frequencies against closed forms, a pendulum under gravity, the
generalized-alpha scheme's spectral properties, and the warning in error estimates."""
import json
import math
import os
import warnings

import numpy as np
import pytest
from scipy.optimize import brentq

from flexmbs import Circle, Material, Model
from flexmbs.analysis.modes import (SCHEME_TOL, amplification_matrix, modes, resolved_limit,
                                    scheme_errors)
from flexmbs.analysis.settings import SimulationSettings
from flexmbs.analysis.simulate import simulate
from flexmbs.cli.main import main
from flexmbs.errors import ModelError
from flexmbs.model.constraints import constraint_jacobian
from flexmbs.problem import Problem

E, NU, RHO, L, D = 210e9, 0.3, 7850.0, 1.0, 0.02
A, I = math.pi * D ** 2 / 4, math.pi * D ** 4 / 64
#: shear correction of a solid circle (Cowper 1966): 6 (1 + nu) / (7 + 6 nu)
KAPPA = 6 * (1 + NU) / (7 + 6 * NU)
CRANK_ROCKER = os.path.join(os.path.dirname(__file__), "data", "crank_rocker_coarse_step.toml")


def _cantilever(nel=16):
    m = Model()
    b = m.add_beam("b", (0, 0), (L, 0), nel, material=Material(E, NU, RHO), section=Circle(D))
    m.clamp(b.first)
    return m


def test_cantilever_bending_and_axial_frequencies():
    """First three bending frequencies of a clamped-free steel rod (L = 1 m, d = 20 mm, 16
    quadratic elements) against Euler-Bernoulli, beta_n L = 1.8751, 4.6941, 7.8548 (Geradin &
    Rixen, "Mechanical Vibrations", 3rd ed., sec. 4.2), lowered by the first-order Timoshenko
    correction of shear and rotary inertia, 1/2 (beta_n r)^2 (1 + E / (kappa G)) with r the
    radius of gyration (Han, Benaroya & Wei, J. Sound Vib. 225, 1999: 0.02 %, 0.1 %, 0.3 %
    here): within 0.1 %, the discretisation error of 16 elements (5+ elements per half-wave
    of the third mode); the first axial frequency sqrt(E / rho) / (4 L) within 0.1 %. The
    model is undamped: every damping ratio is 0."""
    md = modes(_cantilever(), count=10)
    r = math.sqrt(I / A)
    g = E / (2 * (1 + NU))
    for k, bl in enumerate((1.8751040687, 4.6940911330, 7.8547574382)):
        f_eb = bl ** 2 * math.sqrt(E * I / (RHO * A)) / (2 * math.pi)
        f_t = f_eb * (1 - 0.5 * bl ** 2 * r ** 2 * (1 + E / (KAPPA * g)))
        assert abs(md.frequency[k] / f_t - 1) < 1e-3, (k, md.frequency[k], f_t)
    f_ax = math.sqrt(E / RHO) / (4 * L)
    assert np.min(np.abs(md.frequency / f_ax - 1)) < 1e-3, (md.frequency, f_ax)
    assert np.all(md.damping == 0.0)
    # the shapes are nodal fields scaled to a largest translation of 1; the first bends the
    # tip most (its tip translation is the largest)
    assert md.shapes.shape == (10, 33, 3)
    tr = np.hypot(md.shapes[0, :, 0], md.shapes[0, :, 1])
    assert tr.max() == pytest.approx(1.0) and np.argmax(tr) == 32


def test_pendulum_frequency_under_gravity_and_rigid_mode_without():
    """A stiff steel rod (1 m, 8 elements) pinned at its top end: without gravity its swing is
    a 0 Hz mode (exactly one, the pin leaves one rigid motion), its shape respecting the pin
    (Phi_q shape = 0); hanging under g = 9.81 m/s^2 in static equilibrium (the rod's tension
    gives the geometric stiffness) its lowest mode is the compound pendulum's,
    sqrt(3 g / (2 L)) / (2 pi) = 0.6105 Hz, within 0.1 % (the rod's thickness adds r^2 / (4
    L^2) ~ 2.5e-5 to its inertia)."""
    m = Model()
    b = m.add_beam("b", (0, 0), (0, -L), 8, material=Material(E, NU, RHO), section=Circle(D))
    m.pin(b.first)
    free = modes(m, count=3)
    assert free.frequency[0] == 0.0 and free.frequency[1] > 10.0
    jac = constraint_jacobian(m.compile(), m.reference_coordinates())
    for s in free.shapes:
        assert np.abs(jac @ s.ravel()).max() < 1e-9
    m.set_gravity(0.0, -9.81)
    r = simulate(m, 1e-3, 1e-3, SimulationSettings(start="static", store="all"))
    hanging = modes(m, r.q[0], r.qd[0], r.qdd[0], r.mu[0], count=3)
    f = math.sqrt(1.5 * 9.81 / L) / (2 * math.pi)
    assert abs(hanging.frequency[0] / f - 1) < 1e-3, (hanging.frequency[0], f)
    assert hanging.frequency[1] == pytest.approx(free.frequency[1], rel=1e-2)


def test_modes_reject_inputs_of_the_wrong_size():
    """modes() names the input of the wrong shape and the count allowed."""
    m = _cantilever(2)
    with pytest.raises(ModelError, match="q needs 15 entries"):
        modes(m, np.zeros(3))
    with pytest.raises(ModelError, match="count must be a positive integer"):
        modes(m, count=0)


def test_generalized_alpha_spectral_properties():
    """The amplification matrix of one generalized-alpha step: spectral radius rho_inf as
    omega h -> infinity (Chung & Hulbert, J. Appl. Mech. 60, 1993, eq. 25), a period error of
    second order (it falls 4x when omega h halves, to 5 %), no numerical damping at rho_inf =
    1 (the trapezoidal rule), whose period error is omega h / (2 atan(omega h / 2)) - 1 in
    closed form: resolved_limit(1.0) is where that reaches SCHEME_TOL, to 1e-5."""
    for rho in (0.0, 0.5, 0.9):
        lam = np.abs(np.linalg.eigvals(amplification_matrix(1e6, rho)))
        assert lam.max() == pytest.approx(rho, abs=1e-3)
        _, p1 = scheme_errors(0.1, rho)
        _, p2 = scheme_errors(0.05, rho)
        assert p1 / p2 == pytest.approx(4.0, rel=0.05)
    xi, _ = scheme_errors(1.0, 1.0)
    assert abs(xi) < 1e-12
    exact = brentq(lambda w: w / (2 * math.atan(w / 2)) - 1 - SCHEME_TOL, 0.01, 2.0)
    assert resolved_limit(1.0) == pytest.approx(exact, abs=1e-5)
    # more numerical damping, less accuracy at a given omega h
    assert resolved_limit(0.0) < resolved_limit(0.5) < resolved_limit(1.0)


def _problem(**sets):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Problem(CRANK_ROCKER, overrides=sets or None)


def test_unresolved_undamped_mode_is_named_in_the_error_estimate():
    """The undamped crank-rocker of tests/data (h = 2 ms, ladder h, h/2, h/4): the coupler
    stress sees a mode near 140 Hz (omega h/4 = 0.44, beyond resolved_limit(0.5) = 0.285):
    its estimate is not reliable and says so, naming the response, the mode's frequency
    (within 3 % of an eigenfrequency of the linearized model at the start, computed here
    from its static state) and a step that resolves it (omega h <= resolved_limit)."""
    prob = _problem()
    ev = prob.evaluate(gradient=False, error=True)
    e = ev.errors["coupler_stress"]
    assert e.unresolved and not e.reliable
    u = e.unresolved[0]
    assert u.response == "coupler_stress" and u.damping == 0.0
    r = prob.simulate(store="all")
    md = modes(r.design_model, r.q[0], r.qd[0], r.qdd[0], r.mu[0], count=8)
    assert np.min(np.abs(md.frequency / u.frequency - 1)) < 0.03, (u.frequency, md.frequency)
    assert 2 * math.pi * u.frequency * u.h_resolved == pytest.approx(resolved_limit(0.5))
    text = e.describe()
    assert "NOT reliable" in text and "coupler_stress" in text and "undamped" in text
    assert f"{u.frequency:.4g} Hz" in text
    assert ev.to_json()["responses"]["coupler_stress"]["error"]["unresolved_modes"]


def test_damped_case_reports_no_unresolved_mode():
    """The same crank-rocker with Kelvin-Voigt damping 0.2 ms in every material (damping ratio
    eta omega / 2 = 9 % at 140 Hz, above LIGHT_DAMPING = 5 %): no estimate names a mode."""
    prob = _problem(**{"materials.aluminium.damping_time": 2e-4,
                       "materials.steel.damping_time": 2e-4})
    ev = prob.evaluate(gradient=False, error=True)
    assert all(not e.unresolved for e in ev.errors.values())


def test_modes_command(tmp_path, capsys):
    """`flexmbs modes CASE --json --at 0,0.1 --count 4`: 4 modes at each of the two times,
    lowest first, the unresolved mode of the coupler stress listed; --plot writes a PNG and
    --animate a GIF of 40 frames (one period); a time outside the motion is one line naming
    it (exit status 2)."""
    from PIL import Image

    png, gif = tmp_path / "modes.png", tmp_path / "mode.gif"
    assert main(["modes", CRANK_ROCKER, "--json", "--at", "0,0.1", "--count", "4",
                 "--plot", str(png), "--animate", str(gif), "--mode", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [m["t"] for m in out["modes"]] == pytest.approx([0.0, 0.1])
    f = out["modes"][0]["frequency"]
    assert len(f) == 4 and f == sorted(f)
    assert out["unresolved"]["coupler_stress"][0]["frequency"] > 0
    assert png.stat().st_size > 0
    with Image.open(gif) as im:
        assert im.n_frames == 40
    assert main(["modes", CRANK_ROCKER, "--at", "5"]) == 2
    assert "time 5 s is outside the motion" in capsys.readouterr().err


def test_verification_refuses_a_constraint_seeing_an_unresolved_mode(tmp_path):
    """verify() of the crank-rocker with its coupler stress limited far above its value (1 GPa,
    a margin that alone would verify it) stopped at h/4 (max_level=2): the 140 Hz mode is
    unresolved at that finest step (omega h = 0.44 > 0.285), so the design is not verified
    and the constraint's estimate names the mode."""
    from flexmbs.analysis.accuracy import verify

    case = tmp_path / "limited.toml"
    case.write_text(open(CRANK_ROCKER).read() + '\n[[constraints]]\nresponse = "coupler_stress"'
                    '\nupper = 1.0e9\nover = "every_step"\n')
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = Problem(str(case))
    v = verify(prob, None, max_level=2)
    e = v.constraints["coupler_stress"]
    assert e.value < 0 and e.unresolved and not v.verified
    assert e.unresolved[0].h == pytest.approx(2e-3 / 4)
