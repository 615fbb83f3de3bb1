"""Diagnosis of failed simulations: redundant constraints,
a body not held, and an input that overflows are told apart and named in the message."""
import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.validity import free_directions, redundant_constraints
from flexmbs.errors import SimulationError
from flexmbs.analysis.settings import SimulationSettings

ALU = fx.Material(E=72e9, nu=0.3, rho=2700)


def arm(elements=2):
    m = fx.Model("arm")
    b = m.add_beam("arm", (0.0, 0.0), (0.6, 0.0), elements, material=ALU,
                   section=fx.Tube.with_wall_ratio(0.05, 0.1))
    return m, b


def test_two_identical_pins_are_reported_as_redundant_not_as_unheld():
    """A motor-driven arm pinned twice at the same node (static start): the constraint
    Jacobian has rank 3 for 5 rows (two pins = 4 rows, x and y twice, plus the motor), so the
    message must say over-constrained/redundant and name the repeated pin rows, not "not held"
    (the arm is held: one pin and the motor fix it)."""
    m, b = arm()
    m.pin(b.first)
    m.pin(b.first)
    m.drive_rotation(b.first, 0.0)
    m.set_gravity(0.0, -9.81)
    with pytest.raises(SimulationError) as e:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    msg = str(e.value)
    assert "over-constrained" in msg and "redundant" in msg
    assert "rank 3 for 5 rows" in msg
    assert "row 3 'pin node 0 x' repeats row 1 'pin node 0 x'" in msg
    assert "not held" not in msg


def test_redundant_rigid_link_and_hinge_rows_found_by_rank():
    """Rank test on a nonlinear row: a rigid link between nodes i and j holds their relative
    position (rows x, y) and angle; a hinge between the same two coincident nodes repeats the
    link's x and y rows exactly at the reference state (Phi_q of the link at zero offset is
    [-1, 1, 0]), so both hinge rows and nothing else are redundant."""
    m = fx.Model()
    i = m.add_node(0.0, 0.0)
    j = m.add_node(0.0, 0.0)
    m.rigid_link(i, j)
    m.hinge(i, j)
    red = redundant_constraints(m)
    assert [r for r, _ in red] == [3, 4]
    assert red[0][1] == [0] and red[1][1] == [1]


def test_unheld_body_is_reported_as_not_held_with_its_free_motion():
    """A beam pinned at its root with no motor, under gravity, static start: it can turn about
    the pin with no stiffness against it. Exactly one free motion (the rigid rotation about the
    pin: the null space of K_t restricted to the pin's null space is one-dimensional), no
    redundant constraint; the message says not held / under-constrained and names the body."""
    m, b = arm()
    m.pin(b.first)
    m.set_gravity(0.0, -9.81)
    assert redundant_constraints(m) == []
    with pytest.raises(SimulationError) as e:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    msg = str(e.value)
    assert "under-constrained" in msg and "not held" in msg
    assert "1 free motion(s)" in msg and "body 'arm'" in msg
    assert "redundant" not in msg


def test_floating_beam_has_three_rigid_free_motions():
    """A beam with no support at all: the null space of its tangent stiffness is the three
    planar rigid motions (two translations, one rotation)."""
    m, _ = arm(elements=3)
    assert len(free_directions(m)) == 3


def test_huge_load_is_reported_as_overflow_naming_the_load():
    """1e300 N at the tip of a clamped arm: products of this load with displacements
    (~1e300 / k) exceed the largest double (1.8e308) in the residual. The message must say
    overflow and name the load (component and node), not "underconstrained"."""
    m, b = arm()
    m.clamp(b.first)
    m.add_load(b.last, fy=-1e300)
    with pytest.raises(SimulationError) as e:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    msg = str(e.value)
    assert "overflow" in msg
    assert f"load fy at node {b.last} = -1e+300" in msg
    assert "underconstrained" not in msg and "not held" not in msg


def test_held_structure_with_too_large_load_blames_the_load():
    """A clamped arm of 4 elements under 1e9 N transverse (the load of the 1e9 N cantilever of
    test_validity.py): Newton diverges although the constraints are independent and nothing is free; the
    message must say so and name the load rather than "may not be held"."""
    m, b = arm(elements=4)
    m.clamp(b.first)
    m.add_load(b.last, fy=-1e9)
    with pytest.raises(SimulationError) as e:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    msg = str(e.value)
    assert "structure is held" in msg and f"largest load 1e+09 at node {b.last}" in msg
    assert "may not be held" not in msg


def test_redundant_pin_in_a_rest_start_is_named():
    """Rest start (no static solve): the initial system [M Phi_q^T; Phi_q 0] is singular with a
    repeated pin; the message names the repeated rows."""
    m, b = arm()
    m.pin(b.first)
    m.pin(b.first)
    m.drive_rotation(b.first, 0.0)
    with pytest.raises(SimulationError) as e:
        fx.simulate(m, 1e-3, 1e-3)
    assert "redundant" in str(e.value) and "'pin node 0 y'" in str(e.value)
    assert np.isfinite(e.value.time)
