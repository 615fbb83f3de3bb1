"""Validity checks of a converged result (no nonsense reported as converged):
strains against the linear-elastic range, constraint drift, energy of a free system."""
import dataclasses
import warnings

import numpy as np
import pytest

import flexmbs as fx
from flexmbs.analysis.validity import ValidityLimits, check_result
from flexmbs.errors import InvalidResultError, ModelError, ValidityWarning
from flexmbs.analysis.settings import InitialConditions, SimulationSettings

ALU = fx.Material(E=72e9, nu=0.3, rho=2700)
TUBE = fx.Tube.with_wall_ratio(0.05, 0.1)
L = 0.6


def cantilever(load, elements=2, order=2):
    m = fx.Model("cantilever")
    b = m.add_beam("tube", (0.0, 0.0), (L, 0.0), elements, material=ALU, section=TUBE, order=order)
    m.clamp(b.first)
    m.add_load(b.last, fy=-load)
    return m, b


def test_1e9_newton_cantilever_fails_naming_strain_and_element():
    """A clamped 0.6 m tube (d = 50 mm) under 1e9 N "converges" statically
    to elements ~14 m long. EA = 5.1e7 N, so any equilibrium carries strains of order
    F / EA ~ 20, three orders beyond the 10 % failure limit: InvalidResultError naming the
    axial strain, the element and its beam; the stretched chord of element 0 (node 0 to its
    end node) confirms the magnitude independently of the check."""
    m, b = cantilever(1e9)
    with pytest.raises(InvalidResultError) as e:
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    msg = str(e.value)
    assert "axial strain" in msg and "element 0 (element 0 of beam 'tube')" in msg
    res = e.value.result
    chord = np.linalg.norm(res.position(b.nodes[2])[0] - res.position(b.nodes[0])[0])
    assert chord / (L / 2) - 1 > 10.0
    assert e.value.validity["axial strain"].value > 10.0


@pytest.mark.parametrize("elements,order", [(2, 2), (4, 2), (4, 1), (8, 1)])
def test_small_tip_load_bending_strain_matches_beam_theory(elements, order):
    """1 N at the tip: no warning, and the bending-strain check equals beam theory.

    Euler-Bernoulli and Timoshenko theory alike give the curvature M / EI with
    M(s) = P (L - s) (Timoshenko, Strength of Materials I, ch. 5; shear does not change the
    curvature), so the root fibre strain is P L c / EI, c = d / 2. The quadratic element
    reproduces the nodal rotations and the quadratic rotation field exactly, so its end
    curvature is P L / EI: tolerance 1e-6 (geometric nonlinearity (P L^2 / EI)^2 ~ 1e-9).
    The 2-node element with one-point integration has exact nodal rotations and a constant
    curvature per element, the mean over the root element: P (L - h / 2) c / EI, h = L / n
    (same tolerance)."""
    m, b = cantilever(1.0, elements, order)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    EI = TUBE.properties(ALU)[2]
    arm = L - (L / elements / 2 if order == 1 else 0.0)
    expected = 1.0 * arm * (TUBE.d / 2) / EI
    assert abs(res.validity["bending strain"].value / expected - 1) < 1e-6
    assert res.validity.ok


def test_constraint_drift_of_a_normal_run_is_tiny_and_a_violation_is_named():
    """A motor-driven pendulum arm (pin + rotation drive, 0.1 s): all rows are linear, so a
    converged Newton step (tol 1e-10 on the scaled increment) satisfies them to rounding;
    the drift must be below 1e-11 m (10x under tol). Moving the stored pin coordinate by
    10 mm (10x the 1e-3 qscale failure limit) must be reported as a failure naming the pin row."""
    m = fx.Model()
    b = m.add_beam("arm", (0.0, 0.0), (L, 0.0), 2, material=ALU, section=TUBE)
    m.pin(b.first)
    m.drive_rotation(b.first, fx.TimeLaw(lambda t: t ** 2, lambda t: 2 * t, lambda t: 2 + 0 * t))
    m.set_gravity(0.0, -9.81)
    res = fx.simulate(m, 0.1, 1e-3)
    drift = res.validity["constraint drift"]
    assert drift.status == "ok" and drift.value < 1e-11
    bad = dataclasses.replace(res, q=res.q.copy())
    bad.q[50, 0] += 1e-2
    check = check_result(m, bad)["constraint drift"]
    assert check.status == "fail" and "pin node 0 x" in check.where
    assert abs(check.value - 1e-2) < 1e-9


def _free_beam():
    m = fx.Model("free beam")
    m.add_beam("beam", (0.0, 0.0), (1.0, 0.0), 4, material=ALU,
                   section=fx.Tube.with_wall_ratio(0.02, 0.1))
    x = m.reference_coordinates()[0::3]
    qd0 = np.zeros(m.ndof)
    qd0[1::3] = 2.0 * np.sin(np.pi * x)
    return m, qd0


def test_energy_of_a_free_beam_does_not_grow_and_injected_energy_is_caught():
    """Free-free bending beam, no loads, rho_inf = 1: generalized-alpha conserves energy up to
    the Newton tolerance and O(h^2) (test_robustness measured 5e-4 on a harder case); the
    check must be below 1e-3 (10x under its 1 % warning limit). Doubling the velocities in
    the second half of the stored history quadruples the kinetic energy there: the check
    must fail."""
    m, qd0 = _free_beam()
    res = fx.simulate(m, 0.05, 5e-4, settings=SimulationSettings(rho_inf=1.0),
                      initial=InitialConditions(qd0=qd0))
    energy = res.validity["energy"]
    assert energy.status == "ok" and energy.value < 1e-3
    bad = dataclasses.replace(res, qd=res.qd.copy())
    bad.qd[len(res.t) // 2:] *= 2.0
    assert check_result(m, bad)["energy"].status == "fail"


def test_checks_of_unstored_coordinates_are_skipped_and_say_so():
    """With store= a subset, elements whose nodes are not stored are not checked and the
    check's note says so; a driven system has no energy check (the drive does work)."""
    m, b = cantilever(1.0)
    res = fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static", store=[b.last]))
    assert res.validity["axial strain"].status == "skipped"
    assert "not stored" in res.validity["axial strain"].note
    assert res.validity["energy"].status == "skipped"


def test_validity_settings_warn_error_off_and_bad_value():
    """A tip load giving a root bending strain of 2 % (between the 1 % warning and 10 %
    failure limits; P = 0.02 EI / (L c)): a ValidityWarning by default, InvalidResultError
    with validity='error', nothing with 'off'; a bad setting is a ModelError naming it."""
    EI = TUBE.properties(ALU)[2]
    m, b = cantilever(0.02 * EI / (L * TUBE.d / 2))
    with pytest.warns(ValidityWarning, match="bending strain"):
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static"))
    with pytest.raises(InvalidResultError, match="bending strain"):
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(start="static", validity="error"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fx.simulate(m, 1e-3, 1e-3,
                          settings=SimulationSettings(start="static", validity="off"))
        fx.simulate(m, 1e-3, 1e-3,
                    settings=SimulationSettings(start="static",
                                                validity=ValidityLimits(strain_warn=0.05)))
    assert res.validity.checks == []
    with pytest.raises(ModelError, match="validity must be"):
        fx.simulate(m, 1e-3, 1e-3, settings=SimulationSettings(validity="loud"))
    with pytest.raises(ModelError, match="strain_warn"):
        ValidityLimits(strain_warn=0.2, strain_fail=0.1)
