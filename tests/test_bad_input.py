"""Bad input gives a documented Python exception naming the input (issue 9).

ModelError (a ValueError) for invalid sections, settings, names and laws, raised before any
simulation; SimulationError (with .time, .residual, .iterations, .code) when the core finds no
solution: a mechanism not held or not connected, a singular system, a Newton failure after the
step cuts. Nothing may reach a Fortran STOP, a segfault or a silent wrong answer.
"""
from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import flexmbs as fx

ALU = fx.Material(E=72e9, nu=0.3, rho=2700)
NAN, INF = float("nan"), float("inf")


def ramp_law(name="ramp"):
    """theta(t) = 0.1 t^2 with analytic derivatives."""
    return fx.TimeLaw(lambda t: 0.1 * t ** 2, lambda t: 0.2 * t, lambda t: 0.2 + 0 * t, name=name)


def driven_arm(elements=2):
    """A pinned, driven aluminium tube under gravity: (model, beam)."""
    m = fx.Model("arm")
    b = m.add_beam("arm", (0.0, 0.0), (1.0, 0.0), elements, material=ALU,
                   section=fx.Tube.with_wall_ratio(0.02, 0.1))
    m.pin(b.first)
    m.drive_rotation(b.first, ramp_law())
    m.set_gravity(0.0, -9.81)
    return m, b


# --------------------------------------------------------------------------- sections
@pytest.mark.parametrize("d", [0.0, -0.05, NAN, INF])
@pytest.mark.parametrize("make", [lambda d: fx.Circle(d), lambda d: fx.Tube(d, 0.002),
                                  lambda d: fx.Tube.with_wall_ratio(d, 0.1)],
                         ids=["Circle", "Tube", "Tube.with_wall_ratio"])
def test_bad_diameter(make, d):
    with pytest.raises(fx.ModelError) as err:
        make(d)
    msg = str(err.value)
    assert "diameter d" in msg and repr(d) in msg and "positive and finite" in msg


def test_wall_thicker_than_radius():
    with pytest.raises(fx.ModelError, match=r"wall thickness t = 0\.03 is larger than the radius 0\.025"):
        fx.Tube(0.05, 0.03)


@pytest.mark.parametrize("t", [0.0, -0.001, NAN])
def test_bad_wall_thickness(t):
    with pytest.raises(fx.ModelError, match="wall thickness t must be positive and finite"):
        fx.Tube(0.05, t)


@pytest.mark.parametrize("ratio", [0.0, 0.6, NAN])
def test_bad_wall_ratio(ratio):
    with pytest.raises(fx.ModelError, match="wall ratio must lie in"):
        fx.Tube.with_wall_ratio(0.05, ratio)


@pytest.mark.parametrize("kw, name", [(dict(E=0.0, nu=0.3, rho=1.0), "E"), (dict(E=1.0, nu=0.5, rho=1.0), "nu"),
                                      (dict(E=1.0, nu=0.3, rho=NAN), "rho")])
def test_bad_material(kw, name):
    with pytest.raises(fx.ModelError, match=rf"Material\.{name}"):
        fx.Material(**kw)


# --------------------------------------------------------------------------- settings
@pytest.mark.parametrize("h", [0.0, -1e-3, NAN, INF, None])
def test_bad_step(h):
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=r"^h must be a positive finite number, got"):
        fx.simulate(m, 0.01, h)


@pytest.mark.parametrize("t_end", [0.0, -0.1, NAN, INF])
def test_bad_end_time(t_end):
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=r"^t_end must be a positive finite number, got"):
        fx.simulate(m, t_end, 1e-3)


def test_end_time_not_whole_steps():
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=r"t_end = 0\.6687 s is not a whole number of steps h = 0\.0005 s"):
        fx.simulate(m, 0.6687, 5e-4)


@pytest.mark.parametrize("rho_inf", [-0.1, 1.0001, 1.5, NAN, "0.5"])
def test_rho_inf_outside_unit_interval(rho_inf):
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=r"rho_inf must lie in \[0, 1\]"):
        fx.simulate(m, 0.01, 1e-3, rho_inf=rho_inf)


@pytest.mark.parametrize("kw, text", [(dict(solver="lu"), "solver must be"), (dict(start="still"), "start must be"),
                                      (dict(tol=0.0), "tol must be > 0"), (dict(max_iter=0), "max_iter must be an integer >= 1, got 0"),
                                      (dict(max_cuts=-1), "max_cuts must be an integer >= 0, got -1"), (dict(store="tip"), "store must be"),
                                      (dict(q0=np.zeros(3)), "q0 must be a finite array of 15"),
                                      (dict(qd0=np.full(15, NAN)), "qd0 must be a finite array")])
def test_bad_settings(kw, text):
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=text):
        fx.simulate(m, 0.01, 1e-3, **kw)


# --------------------------------------------------------------------------- names
@pytest.mark.parametrize("call, text", [
    (lambda m, b: m.pin(99), "pin: unknown node 99"),
    (lambda m, b: m.hinge(b.last, 99), "hinge: unknown node 99"),
    (lambda m, b: m.drive_rotation(-1, 0.0), "drive_rotation: unknown node -1"),
    (lambda m, b: m.add_point_mass(99, 1.0), "unknown node 99"),
    (lambda m, b: m.add_load(99, fx=1.0), "add_load: unknown node 99"),
    (lambda m, b: m.pin("tip"), "expected a node id"),
    (lambda m, b: m.body("arm3"), "unknown body 'arm3'"),
    (lambda m, b: m.set_section("arm3", fx.Circle(0.01)), "unknown body 'arm3'"),
    (lambda m, b: m.set_element_sections("arm3", [fx.Circle(0.01)]), "unknown body 'arm3'"),
    (lambda m, b: m.add_beam("arm", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.01)), "'arm' already exists"),
    (lambda m, b: fx.simulate(m, 0.01, 1e-3, store=[99]), "store: unknown node 99"),
])
def test_unknown_names(call, text):
    m, b = driven_arm()
    with pytest.raises(fx.ModelError, match=text):
        call(m, b)


def test_store_body_of_another_model():
    m, _ = driven_arm()
    big = fx.Model("other")
    other = big.add_beam("other", (0, 0), (1, 0), 20, material=ALU, section=fx.Circle(0.02))
    with pytest.raises(fx.ModelError, match="store"):
        fx.simulate(m, 0.01, 1e-3, store=[other])


# --------------------------------------------------------------------------- not held, singular
def test_not_held_static_start():
    """A free beam has no static equilibrium: singular stiffness at the first iteration."""
    m = fx.Model()
    m.add_beam("free", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held") as err:
        fx.simulate(m, 0.01, 1e-3, start="static")
    assert err.value.time == 0.0 and err.value.iterations == 1


def test_free_rotation_static_start():
    """A pinned beam without a drive can swing freely about the pin: no static equilibrium."""
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.pin(b.first)
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held"):
        fx.simulate(m, 0.01, 1e-3, start="static")


def test_not_connected_static_start():
    """Two beams, the second not hinged to the first: the loose one is not held."""
    m = fx.Model()
    a = m.add_beam("a", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.add_beam("b", (1, 0), (2, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.clamp(a.first)
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held"):
        fx.simulate(m, 0.01, 1e-3, start="static")


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_massless_free_node_singular(solver):
    """A node with neither mass nor constraint makes [M Phi_q'; Phi_q 0] singular at t = 0."""
    m, _ = driven_arm()
    m.add_node(3.0, 3.0)
    with pytest.raises(fx.SimulationError, match="singular") as err:
        fx.simulate(m, 0.01, 1e-3, solver=solver)
    assert err.value.code == 4 and err.value.time == 0.0


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_redundant_constraints_singular(solver):
    m, b = driven_arm()
    m.pin(b.first)               # the same pin twice
    with pytest.raises(fx.SimulationError, match="redundant"):
        fx.simulate(m, 0.01, 1e-3, solver=solver)


def test_inconsistent_initial_configuration_names_constraint():
    m, _ = driven_arm()
    with pytest.raises(fx.SimulationError, match="violates constraint 'pin node 0 x' by 0.1"):
        fx.simulate(m, 0.01, 1e-3, q0=m.reference_coordinates() + 0.1)


# --------------------------------------------------------------------------- laws
def _arm_with_law(law):
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.pin(b.first)
    m.drive_rotation(b.first, law)
    return m


def test_motor_law_nan_value_names_law_and_time():
    law = fx.TimeLaw(lambda t: np.where(t > 0.005, np.nan, 0.0), lambda t: 0 * t, lambda t: 0 * t,
                     name="bad motor")
    with pytest.raises(fx.ModelError, match=r"time law 'bad motor': value is not finite at t = 0\.006 s"):
        fx.simulate(_arm_with_law(law), 0.01, 1e-3)


def test_motor_callable_nan_names_motor():
    with np.errstate(invalid="ignore"):
        with pytest.raises(fx.ModelError, match=r"time law 'motor at node 0': value is not finite at t = 0 s"):
            fx.simulate(_arm_with_law(lambda t: np.sqrt(t - 0.005)), 0.01, 1e-3)


def test_motor_law_infinite_rate_names_law():
    law = fx.TimeLaw(lambda t: 0.0 * t, lambda t: np.where(t > 0.003, np.inf, 0.0 * t),
                     lambda t: 0.0 * t, name="jerky")
    with pytest.raises(fx.ModelError, match=r"time law 'jerky': rate is not finite at t = 0\.004 s"):
        fx.simulate(_arm_with_law(law), 0.01, 1e-3)


def test_motor_law_nan_acceleration_names_law():
    """The acceleration is used at t = 0 (consistent initial accelerations)."""
    law = fx.TimeLaw(lambda t: 0.0 * t, lambda t: 0.0 * t, lambda t: np.nan + 0.0 * t, name="jerky")
    with pytest.raises(fx.ModelError, match=r"time law 'jerky': acceleration is not finite at t = 0 s"):
        fx.simulate(_arm_with_law(law), 0.01, 1e-3)


# --------------------------------------------------------------------------- Newton failure
def test_newton_failure_after_cuts_reports_time_residual_iterations():
    """One Newton iteration per step cannot reach tol = 1e-10: after 2 halvings the first
    sub-step (h / 4) fails and the error carries time, residual and iteration count."""
    m, _ = driven_arm()
    with pytest.raises(fx.SimulationError) as err:
        fx.simulate(m, 0.01, 1e-3, max_iter=1, max_cuts=2)
    e = err.value
    assert e.code == 1
    assert math.isclose(e.time, 2.5e-4, rel_tol=1e-12)
    assert e.iterations == 1 and e.residual > 1e-10
    msg = str(e)
    assert "t = 0.00025 s" in msg and "2 times" in msg and f"{e.residual:.3g}" in msg and "1 iterations" in msg


def test_static_equilibrium_failure_reports():
    """A load far beyond what the arm carries: the static start gives up with a SimulationError."""
    m, b = driven_arm()
    m.add_load(b.last, fy=-1e9)
    with pytest.raises(fx.SimulationError, match="static equilibrium at t = 0") as err:
        fx.simulate(m, 0.01, 1e-3, start="static")
    assert err.value.time == 0.0 and err.value.residual > 0


# --------------------------------------------------------------------------- no crash
def test_core_failures_do_not_crash_the_interpreter():
    """Every path into the Fortran core that fails is run in a child interpreter: it must end
    normally (no segfault, no Fortran STOP) with the expected exception each time."""
    code = textwrap.dedent('''
        import numpy as np, flexmbs as fx
        alu = fx.Material(E=72e9, nu=0.3, rho=2700)
        def arm(pin=True, drive=True):
            m = fx.Model(); b = m.add_beam("arm", (0, 0), (1, 0), 2, material=alu, section=fx.Circle(0.02))
            if pin: m.pin(b.first)
            if drive: m.drive_rotation(b.first, fx.TimeLaw(lambda t: 0.1*t**2, lambda t: 0.2*t, lambda t: 0.2+0*t))
            m.set_gravity(0, -9.81); return m, b
        cases = []
        for solver in ("dense", "klu"):
            m, b = arm(pin=False, drive=False); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, start="static", solver=s))
            m, b = arm(); m.add_node(3, 3); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, solver=s))
            m, b = arm(); m.pin(b.first); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, solver=s))
            m, b = arm(); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, max_iter=1, max_cuts=3, solver=s))
            m, b = arm(); m.add_load(b.last, fy=-1e12); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, start="static", solver=s))
            m, b = arm(); cases.append(lambda m=m, s=solver: fx.simulate(m, 0.01, 1e-3, q0=m.reference_coordinates() + 1.0, solver=s))
        n = 0
        for c in cases:
            try:
                c()
            except fx.SimulationError:
                n += 1
        print("simulation errors", n, "of", len(cases))
    ''')
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "STOP" not in proc.stdout + proc.stderr
    assert "simulation errors 12 of 12" in proc.stdout
