"""Builder joints made of linear constraint rows: weld, slider (prismatic joint on the
ground) and drive_translation (Model.weld, Model.slider, Model.drive_translation)."""
import math

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.errors import ModelError
from flexmbs.analysis.settings import SimulationSettings

STEEL = fx.Material(E=210e9, nu=0.3, rho=7800)
G = 9.81


def test_slider_crank_follows_the_analytic_piston_motion():
    """Slider-crank: crank O-A (r = 0.1 m) pinned and driven at O, theta(t) = 2 pi t^2;
    connecting rod A-B (l = 0.3 m) hinged to the crank at A and to a 2 kg slider block at B
    that moves on the x axis (slider). Kinematics of the rigid mechanism (any textbook):
    x_B = r cos(theta) + sqrt(l^2 - r^2 sin^2(theta)). With stiff steel sections (d = 40 mm:
    the rod's axial deflection under the block's inertia force, below 2 kg * 40 m/s^2 /
    (EA = 2.6e8 N) = 3e-7 m), x_B follows it within 2e-6 m over a quarter turn, and the block's
    y and rotation stay 0 (to 1e-12 m)."""
    r_, l_ = 0.1, 0.3
    m = fx.Model()
    sec = fx.Circle(0.04)
    crank = m.add_beam("crank", (0.0, 0.0), (r_, 0.0), 1, material=STEEL, section=sec)
    rod = m.add_beam("rod", (r_, 0.0), (r_ + l_, 0.0), 2, material=STEEL, section=sec)
    block = m.add_node(r_ + l_, 0.0)
    m.add_point_mass(block, 2.0, 0.01)
    m.pin(crank.first)
    m.drive_rotation(crank.first, fx.TimeLaw(lambda t: 2 * np.pi * t ** 2,
                                             lambda t: 4 * np.pi * t,
                                             lambda t: 4 * np.pi + 0 * t))
    m.hinge(crank.last, rod.first)
    m.hinge(rod.last, block)
    m.slider(block, axis=(1.0, 0.0))
    r = fx.simulate(m, 0.5, 1e-3)
    theta = 2 * np.pi * r.t ** 2
    xb = r_ * np.cos(theta) + np.sqrt(l_ ** 2 - (r_ * np.sin(theta)) ** 2)
    pos = r.position(block)
    assert np.max(np.abs(pos[:, 0] - xb)) < 2e-6
    assert np.max(np.abs(pos[:, 1])) < 1e-12
    assert np.max(np.abs(r.rotation(block))) < 1e-12
    assert theta[-1] == pytest.approx(np.pi / 2)


def test_block_slides_down_an_inclined_slider_with_g_sin_alpha():
    """A frictionless block on a slider inclined at alpha = 30 deg (axis through a given
    point), released at rest under gravity: s(t) = g sin(alpha) t^2 / 2 along the line
    (constant acceleration: generalized-alpha with consistent initial accelerations
    integrates it exactly, to 1e-9 m), no motion across the line, rotation fixed; the
    normal reaction is m g cos(alpha) (to 1e-7 relative; measured 3e-9, the Newton
    tolerance)."""
    alpha = math.radians(30.0)
    axis = np.array([math.cos(alpha), -math.sin(alpha)])   # pointing downhill
    m = fx.Model()
    p0 = np.array([1.0, 2.0])
    block = m.add_node(*(p0 + 0.5 * axis))
    m.add_point_mass(block, 3.0, 0.2)
    m.slider(block, axis=10 * axis, point=p0)
    m.set_gravity(0.0, -G)
    r = fx.simulate(m, 0.4, 1e-3)
    d = r.position(block) - p0
    s = d @ axis
    np.testing.assert_allclose(s, 0.5 + 0.5 * G * math.sin(alpha) * r.t ** 2, atol=1e-9)
    assert np.max(np.abs(d @ np.array([-axis[1], axis[0]]))) < 1e-12
    assert np.max(np.abs(r.rotation(block))) < 1e-12
    np.testing.assert_allclose(np.abs(r.mu[:, 0]), 3.0 * G * math.cos(alpha), rtol=1e-7)


def test_translation_drive_prescribes_the_position_and_its_force():
    """drive_translation along an inclined slider, s(t) = 0.05 sin(2 pi t) from the node's
    reference position: the node is at point + s(t) a to 1e-12 m (index-3 constraints hold
    at every step); the drive force along the axis balances inertia and gravity,
    |mu| = m |s''(t) - g . a| (Newton's law along the axis), within the generalized-alpha
    error of the accelerations at h = 1 ms (2e-3 relative to m g)."""
    alpha = math.radians(20.0)
    axis = np.array([math.cos(alpha), math.sin(alpha)])
    m = fx.Model()
    node = m.add_node(0.3, 0.1)
    m.add_point_mass(node, 1.5, 0.1)
    m.slider(node, axis)
    m.drive_translation(node, fx.TimeLaw(lambda t: 0.05 * np.sin(2 * np.pi * t),
                                         lambda t: 0.1 * np.pi * np.cos(2 * np.pi * t),
                                         lambda t: -0.2 * np.pi ** 2 * np.sin(2 * np.pi * t)),
                        axis)
    m.set_gravity(0.0, -G)
    r = fx.simulate(m, 1.0, 1e-3)
    s = 0.05 * np.sin(2 * np.pi * r.t)
    np.testing.assert_allclose(r.position(node), np.array([0.3, 0.1]) + s[:, None] * axis,
                               atol=1e-12)
    sdd = -0.2 * np.pi ** 2 * np.sin(2 * np.pi * r.t)
    force = 1.5 * (sdd - np.array([0.0, -G]) @ axis)
    drive = m.compile().row_labels.index(f"translation drive node {node}")
    assert np.max(np.abs(np.abs(r.mu[:, drive]) - np.abs(force))) < 2e-3 * 1.5 * G


def test_welded_beams_bend_as_one_cantilever():
    """Two beams welded end to end (weld: same position and relative rotation), clamped at
    the root, a small tip load P: the tip deflection of a Timoshenko cantilever,
    P L^3 / (3 EI) + P L / (kGA) (analytic), within 1e-3 relative (quadratic elements,
    geometric nonlinearity of order (deflection / L)^2 = 1e-8). Without the weld's angle
    row the joint is a hinge and the structure a mechanism (static start fails)."""
    sec = fx.Rectangle(0.02, 0.03)
    ea, kga, ei, _, _ = sec.properties(STEEL)
    P, L = 10.0, 1.0

    def build(weld=True):
        m = fx.Model()
        a = m.add_beam("a", (0.0, 0.0), (0.4, 0.0), 2, material=STEEL, section=sec)
        b = m.add_beam("b", (0.4, 0.0), (1.0, 0.0), 2, material=STEEL, section=sec)
        m.clamp(a.first)
        if weld:
            m.weld(a.last, b.first)
        else:
            m.hinge(a.last, b.first)
        m.add_load(b.last, fy=-P)
        return m, b

    m, b = build()
    r = fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    expected = P * L ** 3 / (3 * ei) + P * L / kga
    np.testing.assert_allclose(-r.position(b.last)[0, 1], expected, rtol=1e-3)
    m2, _ = build(weld=False)
    with pytest.raises(fx.SimulationError):
        fx.simulate(m2, 1e-3, 1e-3, settings=SimulationSettings(start="static"))


def test_joint_builders_bad_input():
    """Bad input names the argument, the value and what is allowed."""
    m = fx.Model()
    a, b = m.add_node(0.0, 0.0), m.add_node(1.0, 0.0)
    with pytest.raises(ModelError, match="weld between nodes 0 and 1: they are 1 m apart"):
        m.weld(a, b)
    with pytest.raises(ModelError, match="weld: both nodes are node 0"):
        m.weld(a, a)
    with pytest.raises(ModelError, match=r"slider: axis must be a finite nonzero \(x, y\) pair"):
        m.slider(a, (0.0, 0.0))
    with pytest.raises(ModelError, match=r"slider: node 1 at \(1, 0\) is 0.707 m off the line"):
        m.slider(b, (1.0, 1.0), point=(0.0, 0.0))
    with pytest.raises(ModelError, match=r"drive_translation: point (y )?must be .*finite"):
        m.drive_translation(a, 0.0, (1.0, 0.0), point=(1.0, math.nan))
    with pytest.raises(ModelError, match="drive_translation: unknown node 5"):
        m.drive_translation(5, 0.0, (1.0, 0.0))
