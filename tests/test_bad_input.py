"""Bad input gives a documented Python exception naming the input.

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
from flexmbs.optimize import optimize_fully, optimize_weakly
from flexmbs.problem import Problem
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings

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
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(rho_inf=rho_inf))


def _new_spelling(kw):
    """simulate's arguments for the former keywords in kw: settings=, initial=, derivatives=
    (reuse_jacobian, itself deprecated, as it is)."""
    settings = {k: v for k, v in kw.items() if k in SimulationSettings.__dataclass_fields__}
    initial = {k: v for k, v in kw.items() if k in ("q0", "qd0")}
    out = {k: v for k, v in kw.items() if k not in settings and k not in initial
           and k != "design_derivatives"}
    out["settings"] = SimulationSettings(**settings)
    if initial:
        out["initial"] = InitialConditions(**initial)
    if "design_derivatives" in kw:
        out["derivatives"] = DesignDerivatives(properties=kw["design_derivatives"])
    return out


@pytest.mark.parametrize("kw, text", [(dict(solver="lu"), "solver must be"), (dict(start="still"), "start must be"),
                                      (dict(tol=0.0), "tol must be > 0"), (dict(max_iter=0), "max_iter must be an integer >= 1, got 0"),
                                      (dict(max_cuts=-1), "max_cuts must be an integer >= 0, got -1"), (dict(store="tip"), "store must be"),
                                      (dict(q0=np.zeros(3)), "q0 must be a finite array of 15"),
                                      (dict(qd0=np.full(15, NAN)), "qd0 must be a finite array")])
def test_bad_settings(kw, text):
    m, _ = driven_arm()
    with pytest.raises(fx.ModelError, match=text):
        fx.simulate(m, 0.01, 1e-3, **_new_spelling(kw))


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
    (lambda m, b: fx.simulate(m, 0.01, 1e-3, SimulationSettings(store=[99])),
     "store: unknown node 99"),
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
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(store=[other]))


# --------------------------------------------------------------------------- not held, singular
def test_not_held_static_start():
    """A free beam has no static equilibrium: singular stiffness at the first iteration."""
    m = fx.Model()
    m.add_beam("free", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held") as err:
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(start="static"))
    assert err.value.time == 0.0 and err.value.iterations == 1


def test_free_rotation_static_start():
    """A pinned beam without a drive can swing freely about the pin: no static equilibrium."""
    m = fx.Model()
    b = m.add_beam("arm", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.pin(b.first)
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held"):
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(start="static"))


def test_not_connected_static_start():
    """Two beams, the second not hinged to the first: the loose one is not held."""
    m = fx.Model()
    a = m.add_beam("a", (0, 0), (1, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.add_beam("b", (1, 0), (2, 0), 2, material=ALU, section=fx.Circle(0.02))
    m.clamp(a.first)
    m.set_gravity(0, -9.81)
    with pytest.raises(fx.SimulationError, match="not held"):
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(start="static"))


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_massless_free_node_singular(solver):
    """A node with neither mass nor constraint makes [M Phi_q'; Phi_q 0] singular at t = 0."""
    m, _ = driven_arm()
    m.add_node(3.0, 3.0)
    with pytest.raises(fx.SimulationError, match="singular") as err:
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(solver=solver))
    assert err.value.code == 4 and err.value.time == 0.0


@pytest.mark.parametrize("solver", ["dense", "klu"])
def test_redundant_constraints_singular(solver):
    m, b = driven_arm()
    m.pin(b.first)               # the same pin twice
    with pytest.raises(fx.SimulationError, match="redundant"):
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(solver=solver))


def test_inconsistent_initial_configuration_names_constraint():
    m, _ = driven_arm()
    with pytest.raises(fx.SimulationError, match="violates constraint 'pin node 0 x' by 0.1"):
        fx.simulate(m, 0.01, 1e-3, initial=InitialConditions(q0=m.reference_coordinates() + 0.1))


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
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(max_iter=1, max_cuts=2))
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
        fx.simulate(m, 0.01, 1e-3, settings=SimulationSettings(start="static"))
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


# --------------------------------------------------------------------------- API argument types
# Each bad argument gives a flexmbs error naming the argument, the value given and what is
# allowed (strings where numbers belong, bools, None, NaN, nested or wrong-length designs).
STR, NONE = "2", None


@pytest.mark.parametrize("call, text", [
    (lambda: fx.Material(E="72e9", nu=0.3, rho=2700), "Material.E must be a positive finite number, got '72e9'"),
    (lambda: fx.Material(E=72e9, nu="0.3", rho=2700), "Material.nu must be a finite number, got '0.3'"),
    (lambda: fx.Material(E=72e9, nu=None, rho=2700), "Material.nu must be a finite number, got None"),
    (lambda: fx.Material(E=True, nu=0.3, rho=2700), "Material.E must be a positive finite number, got True"),
    (lambda: fx.Material(E=72e9, nu=0.3, rho=INF), "Material.rho must be positive and finite, got inf"),
    (lambda: fx.Circle("0.02"), "Circle diameter d must be a positive finite number, got '0.02'"),
    (lambda: fx.Tube(0.05, None), "Tube wall thickness t must be a positive finite number, got None"),
    (lambda: fx.Tube.with_wall_ratio(0.05, "0.1"), "Tube wall ratio must lie in (0, 0.5], got '0.1'"),
    (lambda: fx.Rectangle(0.01, False), "Rectangle height h must be a positive finite number, got False"),
    (lambda: fx.GivenSection(1.0, 1.0, 1.0, 1.0, rhoI="x"), "GivenSection.rhoI must be a finite number >= 0, got 'x'"),
    (lambda: fx.GivenSection(1.0, 1.0, 1.0, 1.0, rhoI=-1.0), "GivenSection.rhoI must be a finite number >= 0, got -1.0"),
    (lambda: fx.TimeLaw(3.0), "value must be a callable of t, got 3.0"),
    (lambda: fx.TimeLaw(np.sin, rate="cos"), "rate must be a callable of t or None, got 'cos'"),
    (lambda: fx.TimeLaw.constant("1.0"), "c must be a finite number, got '1.0'"),
    (lambda: fx.TimeLaw.samples([0.0, 1.0, 2.0], [0.0, 1.0]), "t and values must have the same length, got 3 and 2"),
    (lambda: fx.TimeLaw.samples([0.0, 2.0, 1.0], [0.0, 1.0, 2.0]), "t must be strictly increasing"),
    (lambda: fx.Model(None), "Model name must be a string, got None"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_numbers_of_sections_materials_laws(call, text):
    """Sections, materials and laws refuse strings, bools, None and non-finite values, by name."""
    with pytest.raises(fx.ModelError) as err:
        call()
    assert text in str(err.value)


@pytest.mark.parametrize("call, text", [
    (lambda m, b: m.drive_rotation(b.first, "1.0"), "motor at node 0: law must be a TimeLaw, a finite number or a callable of t, got '1.0'"),
    (lambda m, b: m.drive_rotation(b.first, True), "law must be a TimeLaw, a finite number or a callable of t, got True"),
    (lambda m, b: m.drive_rotation(b.first, NAN), "motor at node 0: law must be a finite number, got nan"),
    (lambda m, b: m.drive_rotation(b.first, [0.0, 1.0]), "got [0.0, 1.0] (list)"),
    (lambda m, b: m.drive_rotation(1.0, 0.0), "drive_rotation: expected a node id (int), got 1.0"),
    (lambda m, b: m.drive_rotation(b.last, 0.0, relative_to=b.last), "relative_to is the driven node 4 itself"),
    (lambda m, b: m.drive_rotation(b.last, 0.0, relative_to="arm"), "drive_rotation relative_to: expected a node id (int), got 'arm'"),
    (lambda m, b: m.prescribe_position(b.last, x="0.5"), "position x of node 4: law must be"),
    (lambda m, b: m.prescribe_position(b.last), "give x, y or both"),
    (lambda m, b: m.add_point_mass(b.last, mass=STR), "mass must be a finite number >= 0, got '2'"),
    (lambda m, b: m.add_point_mass(b.last, mass=NONE), "mass must be a finite number >= 0, got None"),
    (lambda m, b: m.add_point_mass(b.last, mass=True), "mass must be a finite number >= 0, got True"),
    (lambda m, b: m.add_point_mass(b.last, mass=-1.0), "mass must be a finite number >= 0, got -1.0"),
    (lambda m, b: m.add_point_mass(b.last, 1.0, inertia=NAN), "inertia must be a finite number >= 0, got nan"),
    (lambda m, b: m.add_node("1", 0.0), "add_node: x must be a finite number, got '1'"),
    (lambda m, b: m.add_node(0.0, 0.0, phi=INF), "add_node: phi must be a finite number, got inf"),
    (lambda m, b: m.set_gravity("0", -9.81), "set_gravity: gx must be a finite number, got '0'"),
    (lambda m, b: m.set_gravity(0.0, None), "set_gravity: gy must be a finite number, got None"),
    (lambda m, b: m.add_load(b.last, fy="-10"), "load at node 4: fy must be a finite number, got '-10'"),
    (lambda m, b: m.add_load(b.last, moment=NAN), "load at node 4: moment must be a finite number, got nan"),
    (lambda m, b: m.add_load(b.last, fx=1.0, law="ramp"), "load at node 4: law must be a TimeLaw"),
    (lambda m, b: m.add_beam("b", ("0", "0"), (1, 1), material=ALU, section=fx.Circle(0.01)), "beam 'b': start x must be a finite number, got '0'"),
    (lambda m, b: m.add_beam("b", "ab", (1, 1), material=ALU, section=fx.Circle(0.01)), "beam 'b': start must be an (x, y) pair"),
    (lambda m, b: m.add_beam("b", (0, 0), (1, 1, 0), material=ALU, section=fx.Circle(0.01)), "beam 'b': end must be an (x, y) pair"),
    (lambda m, b: m.add_beam("b", (0, 0), (1, 1), True, material=ALU, section=fx.Circle(0.01)), "elements must be a positive integer, got True"),
    (lambda m, b: m.add_beam("b", (0, 0), (1, 1), 2.0, material=ALU, section=fx.Circle(0.01)), "elements must be a positive integer, got 2.0"),
    (lambda m, b: m.add_beam("b", (0, 0), (1, 1), 2, order=True, material=ALU, section=fx.Circle(0.01)), "order must be 1 or 2, got True"),
    (lambda m, b: m.add_beam("b", (0, 0), (1, 1), material="alu", section=fx.Circle(0.01)), "material must be a flexmbs Material, got 'alu'"),
    (lambda m, b: m.set_section("arm", 0.01), "section must be a flexmbs Section (Circle, Tube, Rectangle, GivenSection), got 0.01"),
    (lambda m, b: m.set_section(None, fx.Circle(0.01)), "expected a body name (str), got None"),
    (lambda m, b: m.set_element_sections("arm", None), "sections must be a list of 2 Sections"),
    (lambda m, b: m.add_rigid_body("r", [b.last], "1", 0.0), "rigid body 'r': mass must be a finite number >= 0, got '1'"),
    (lambda m, b: m.add_rigid_body("r", 3, 1.0, 0.0), "rigid body 'r': nodes must be a list of node ids, got 3"),
    (lambda m, b: m.add_rigid_body("arm", [b.last], 1.0, 0.0), "a body called 'arm' already exists"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_builder_arguments(call, text):
    """Every numeric argument of the Model builders is checked: strings, bools, None, NaN/inf
    and negative masses give a ModelError naming the argument and the value."""
    m, b = driven_arm()
    nodes = m.nnodes
    with pytest.raises(fx.ModelError) as err:
        call(m, b)
    assert text in str(err.value)
    assert m.nnodes == nodes, "a refused call must not leave half a body behind"


def test_numpy_scalars_are_numbers():
    """numpy scalars are accepted where numbers belong (and stored as floats)."""
    mat = fx.Material(E=np.float32(72e9), nu=np.float64(0.3), rho=np.int64(2700))
    assert type(mat.E) is float and mat.rho == 2700.0
    m, b = driven_arm()
    m.add_point_mass(b.last, mass=np.float32(2.0), inertia=np.int32(0))
    assert m.compile().lumped[3 * b.last] == 2.0


@pytest.mark.parametrize("kw, text", [
    (dict(max_iter="5"), "max_iter must be an integer >= 1, got '5'"),
    (dict(max_iter=2.5), "max_iter must be an integer >= 1, got 2.5"),
    (dict(max_iter=True), "max_iter must be an integer >= 1, got True"),
    (dict(max_cuts=None), "max_cuts must be an integer >= 0, got None"),
    (dict(tol="1e-8"), "tol must be > 0 and finite, got '1e-8'"),
    (dict(tol=NAN), "tol must be > 0 and finite, got nan"),
    (dict(rho_inf=True), "rho_inf must lie in [0, 1], got True"),
    (dict(h=True), "h must be a positive finite number, got True"),
    (dict(solver=["klu"]), "solver must be 'auto', 'dense' or 'klu', got ['klu']"),
    (dict(store=None), "store must be 'all' or a list of nodes/bodies, got None"),
    (dict(start=None), "start must be 'rest' or 'static', got None"),
    (dict(q0="a"), "q0 must be an array of numbers, got 'a'"),
    (dict(reuse_jacobian="no"), "reuse_jacobian must be True or False, got 'no'"),
    (dict(design_derivatives="a"),
     "DesignDerivatives.properties must be an array of numbers, got 'a'"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_simulate_setting_types(kw, text):
    """simulate's own settings: integers are integers, numbers are numbers, by name."""
    m, _ = driven_arm()
    kw = dict(kw)
    h = kw.pop("h", 1e-3)
    with pytest.raises(fx.ModelError) as err:
        fx.simulate(m, 0.01, h, **_new_spelling(kw))
    assert text in str(err.value)


# --------------------------------------------------------------------------- problems, optimizers
@pytest.fixture(scope="module")
def robot():
    """The paper's robot (cases/robot_2dof.toml) over 20 steps: bad input is refused before
    any simulation, the horizon only bounds the cost of a test that would run."""
    return Problem("robot_2dof", overrides={"time.t_end": 0.01})


@pytest.mark.parametrize("arg", [None, 3, True, ["robot_2dof"]], ids=repr)
def test_problem_of_a_non_case(arg):
    """Problem(None) and other non-cases: CaseError naming what is allowed and the type given."""
    with pytest.raises(fx.CaseError) as err:
        Problem(arg)
    msg = str(err.value)
    assert "a case file path, a case name, a dict or a Description" in msg
    assert f"got {type(arg).__name__}" in msg


def test_problem_of_an_unknown_case_name_lists_the_shipped_cases():
    """Problem('nosuchcase'): CaseError naming the name and listing the shipped cases."""
    with pytest.raises(fx.CaseError) as err:
        Problem("nosuchcase")
    msg = str(err.value)
    assert "case 'nosuchcase' not found" in msg and "a path to a .toml file" in msg
    assert "robot_2dof" in msg and "fourbar" in msg


@pytest.mark.parametrize("overrides, text", [
    (["time.t_end", 1], "overrides must be a dict {dotted key: value}, got list"),
    ("time.t_end=1", "overrides must be a dict {dotted key: value}, got str"),
    ({"bodies.arm9.elements": 4},
     "override 'bodies.arm9.elements': no single item 'arm9' in 'bodies' (names: arm1, arm2, actuator, payload; or an index 0..3)"),
    ({"time..h": 1}, "override keys are dotted paths such as 'time.t_end', got 'time..h'"),
    ({"time.t_endd": 1}, "key 'time.t_endd' is not a known key (see docs/case-format.md), got 1"),
    ({"bodies.arm1.elementz": 4}, "key 'bodies[0].elementz' is not a known key"),
    ({"bodies.arm1.elements": 2.5}, "key 'bodies[0].elements' Input should be a valid integer, got a number with a fractional part, got 2.5"),
    ({"bodies.arm1.elements": 100_000}, "key 'bodies[0].elements' Input should be less than or equal to 20000, got 100000"),
    ({"time.t_end": -1}, "key 'time.t_end' Input should be greater than 0, got -1"),
    ({"time.h": "a"}, "key 'time.h' Input should be a valid number, unable to parse string as a number, got 'a'"),
    ({"design.p1.start": 10.0}, "design variable 'p1': start = 10.0 must lie within [20.0, 60.0]"),
    ({"design.p1.lower": 70.0}, "design variable 'p1': lower = 70.0 must be below upper = 60.0"),
], ids=repr)
def test_override_messages_name_file_key_and_value(overrides, text):
    """Problem(name, overrides=...): a non-dict, an item name that is not there, an unknown key
    or a bad value is a CaseError naming the case file, the key and the value."""
    with pytest.raises(fx.CaseError) as err:
        Problem("robot_2dof", overrides=overrides)
    msg = str(err.value)
    assert text in msg and "robot_2dof.toml" in msg


def test_unknown_override_key_lists_allowed_keys():
    """An unknown override key names itself and lists the keys allowed in its table."""
    with pytest.raises(fx.CaseError) as err:
        Problem("robot_2dof", overrides={"time.t_endd": 1})
    msg = str(err.value)
    assert "t_endd" in msg and "t_end," in msg and "rho_inf" in msg


@pytest.mark.parametrize("design, text", [
    ("40,30,35,25", "design must be 4 numbers (p1, p2, p3, p4), got '40,30,35,25'"),
    ([[40, 30], [35, 25]], "design must be 4 finite numbers (p1, p2, p3, p4), got [[40, 30], [35, 25]]"),
    ([[40, 30, 35, 25]], "design must be 4 finite numbers (p1, p2, p3, p4), got [[40, 30, 35, 25]]"),
    ([40, [30], 35, 25], "design must be 4 numbers (p1, p2, p3, p4), got [40, [30], 35, 25]"),
    (40.0, "design must be 4 finite numbers (p1, p2, p3, p4), got 40.0"),
    ([40, 30, 35], "design must be 4 finite numbers (p1, p2, p3, p4), got [40, 30, 35]"),
    ([40, 30, NAN, 25], "design must be 4 finite numbers (p1, p2, p3, p4), got [40, 30, nan, 25]"),
    ([-40, 30, 35, 25], "design values must be positive (section sizes), got [-40, 30, 35, 25]"),
    ([40, "a", 35, 25], "design must be 4 numbers (p1, p2, p3, p4), got [40, 'a', 35, 25]"),
], ids=repr)
def test_problem_design_must_be_flat(robot, design, text):
    """Problem.evaluate / simulate / design_mass: a design is a flat sequence of nv finite
    positive numbers; a string, a nested list, a wrong length or NaN is a ModelError naming the
    variables and the value."""
    for call in (robot.evaluate, robot.simulate, robot.design_mass):
        with pytest.raises(fx.ModelError) as err:
            call(design)
        assert text in str(err.value)


@pytest.mark.parametrize("design", [[True, 30, 35, 25], [40, "30", 35, 25]], ids=repr)
def test_problem_design_refuses_bools_and_strings(robot, design):
    """A bool or a numeric string in a design is refused, as the old case API did."""
    with pytest.raises(fx.ModelError, match="design"):
        robot.design_mass(design)


def _tube_mass(design_mm):
    """Beam mass of the robot (2 arms of 0.6 m, 2 elements each, 0.3 m per design variable):
    rho pi/4 (p^2 - (0.8 p)^2) * 0.3 m summed, aluminium rho = 2700 kg/m^3 (case file)."""
    p = np.asarray(design_mm) * 1e-3
    return float(np.sum(2700.0 * math.pi / 4 * 0.36 * p ** 2 * 0.3))


def test_optimizers_accept_a_case_name_and_progress_false():
    """optimize_fully("robot_2dof") and optimize_weakly("robot_2dof", progress=False) load the
    case by name and run; progress=False used to fail after the first cycle (False was called).
    The first history record is the robot's start design [50]*4 mm with its analytic mass."""
    w = optimize_weakly("robot_2dof", progress=False, options=dict(max_cycles=1))
    assert w.case == "robot_2dof" and w.iterations == 1
    assert w.history[0]["design"] == [50.0] * 4
    assert w.history[0]["mass_kg"] == pytest.approx(_tube_mass([50.0] * 4), rel=1e-12)
    f = optimize_fully("robot_2dof", progress=False, options=dict(max_iterations=1))
    assert f.case == "robot_2dof" and f.iterations == 1
    assert f.history[0]["design"] == [50.0] * 4
    assert f.history[0]["mass_kg"] == pytest.approx(_tube_mass([50.0] * 4), rel=1e-12)


@pytest.mark.parametrize("kw, text", [
    (dict(options=dict(max_iterations="5")), "options: option max_iterations = '5': Input should be a valid integer"),
    (dict(options=dict(max_iterations=2.5)), "options: option max_iterations = 2.5: Input should be a valid integer"),
    (dict(options=dict(max_simulations=0)), "options: option max_simulations = 0: Input should be greater than or equal to 1"),
    (dict(options=dict(kkt_tol="small")), "options: option kkt_tol = 'small': Input should be a valid number"),
    (dict(options=dict(trust_radius=-1)), "options: option sqp.trust_radius = -1: Input should be greater than 0"),
    (dict(options=dict(design_rel_change="a")), "options: option design_rel_change = 'a'"),
    (dict(optimizer="bfgs"), "optimizer must be 'auto' or one of mma, sqp, slsqp, nlopt-mma, nlopt-ccsaq, nlopt-slsqp, got 'bfgs'"),
    (dict(progress=3), "progress must be a callable taking one history record, or None/False, got 3"),
    (dict(options=dict(mma=3)), "options: option mma = 3"),
    (dict(options=3), "options must be a FullyOptions or a dict of its options, got 3"),
    (dict(x0="40,30,35,25"), "design must be 4 numbers (p1, p2, p3, p4), got '40,30,35,25'"),
    (dict(x0=[[40, 30], [35, 25]]), "design must be 4 finite numbers (p1, p2, p3, p4), got [[40, 30], [35, 25]]"),
    (dict(x0=[10, 30, 35, 25]), "x0: p1 = 10.0 lies outside its bounds [20, 60]"),
    (dict(problem=None), "a problem needs a case file path, a case name, a dict or a Description, got NoneType"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_optimize_fully_arguments(robot, kw, text):
    """optimize_fully's arguments and options (flexmbs.model.options.FullyOptions): typed
    errors (ModelError, CaseError for the problem) naming the argument or option and the
    value, before the first simulation."""
    kw = dict(kw)
    problem = kw.pop("problem", robot)
    with pytest.raises(fx.ModelError) as err:
        optimize_fully(problem, **kw)
    assert text in str(err.value)


def test_optimize_fully_history_must_be_a_path(robot):
    """history= is a path, a HistoryWriter or None: anything else is a ModelError naming it."""
    with pytest.raises(fx.ModelError, match="history"):
        optimize_fully(robot, history=3)


@pytest.mark.parametrize("kw, text", [
    (dict(options=dict(max_cycles="5")), "options: option max_cycles = '5': Input should be a valid integer"),
    (dict(options=dict(max_cycles=2.5)), "options: option max_cycles = 2.5: Input should be a valid integer"),
    (dict(options=dict(confirm_cycles=-1)), "options: option confirm_cycles = -1: Input should be greater than or equal to 0"),
    (dict(options=dict(eps="0.01")), "options: option eps = '0.01': Input should be a valid number"),
    (dict(options=dict(screen=None)), "options: option screen = None: Input should be a valid number"),
    (dict(options=dict(screen=2)), "options: option screen = 2: Input should be less than or equal to 1"),
    (dict(options=dict(move_limit=-1)), "options: option move_limit = -1: Input should be greater than 0"),
    (dict(options=dict(max_inner=0)), "options: option max_inner = 0: Input should be greater than or equal to 1"),
    (dict(options=dict(frame_kind="polar")), "options: option frame_kind = 'polar': Input should be 'auto', 'tangent' or 'chord'"),
    (dict(options=dict(frames=3)), "options: option frames = 3: Input should be a valid dictionary"),
    (dict(options=dict(frames={"arm9": "A"})), "frames: 'arm9' is not a beam (beams: arm1, arm2)"),
    (dict(options=dict(frames={"arm1": "Z"})), "frames: beam 'arm1' has no end point 'Z' (its ends: O, A)"),
    (dict(progress="yes"), "progress must be a callable taking one history record, or None/False, got 'yes'"),
    (dict(x0=[-40, 30, 35, 25]), "design values must be positive (section sizes), got [-40, 30, 35, 25]"),
    (dict(x0=[100, 30, 35, 25]), "x0 = [100.0, 30.0, 35.0, 25.0] lies outside the bounds"),
    (dict(problem=42), "a problem needs a case file path, a case name, a dict or a Description, got int"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_optimize_weakly_arguments(robot, kw, text):
    """optimize_weakly's arguments and options (flexmbs.model.options.WeaklyOptions): typed
    errors naming the argument or option and the value, before the first simulation."""
    kw = dict(kw)
    problem = kw.pop("problem", robot)
    with pytest.raises(fx.ModelError) as err:
        optimize_weakly(problem, **kw)
    assert text in str(err.value)


def test_result_and_model_accessors():
    """Result accessors, Model.pattern/row_label and simulate(store=...) refuse non-ids with a
    ModelError naming the argument, not a bare TypeError/ValueError."""
    m, b = driven_arm()
    r = fx.simulate(m, 0.003, 1e-3)
    for call in (r.position, r.rotation, r.velocity):
        for bad in (None, "2", 1.5, np.zeros(3)):
            with pytest.raises(fx.ModelError, match="expected a node id"):
                call(bad)
    with pytest.raises(fx.ModelError, match=r"coordinates: expected a list of coordinate indices \(int\), got 3"):
        r.coordinates(3)
    assert r.coordinates([]).shape == (r.t.size, 0)
    with pytest.raises(fx.ModelError, match=r"unknown matrix storage \['klu'\]: use 'dense' or 'klu'"):
        m.pattern(["klu"])
    with pytest.raises(fx.ModelError, match=r"row_label: expected a constraint row index \(int\), got None"):
        m.row_label(None)
    with pytest.raises(fx.ModelError, match=r"DesignDerivatives.dofs must be an array of numbers, got \[1\.5\]"):
        fx.simulate(m, 0.003, 1e-3,
                    derivatives=DesignDerivatives(properties=np.zeros((5, 2, 1)), dofs=[1.5]))
    with pytest.raises(fx.ModelError, match=r"store must be 'all' or a list of nodes/bodies, got None"):
        fx.simulate(m, 0.002, 1e-3, settings=SimulationSettings(store=None))


