"""Initial elastic deformation and velocity of the case format (docs/case-format.md,
"Initial state `[initial]`"): a static solution under given loads, or given beam deflections
and rates; design gradients exact with given values (Taylor test), refused with a static
solution (which depends on the design).

Analytic reference: the Euler-Bernoulli cantilever of length L under an end load P (e.g.
Timoshenko & Gere, Mechanics of Materials, Appendix G, case 1): w(x) = P x^2 (3L - x)/(6 EI),
tip deflection P L^3/(3 EI). A beam started in that shape with that load applied stays in it;
started straight it vibrates between 0 and about twice the static deflection. A clamped-free
bar of axial wave speed c started in its first axial mode u0 sin(pi x / 2L) oscillates as
u0 cos(omega_1 t), omega_1 = (pi/2) c / L.
"""
import numpy as np
import pytest

from flexmbs.analysis.checks import taylor_test
from flexmbs.errors import ModelError
from flexmbs.problem import Problem

L, EI, P = 1.0, 100.0, 0.3          # tip deflection 1 mm: small rotations
TIP = P * L ** 3 / (3 * EI)


def _w(x):
    return -P * x * x * (3 * L - x) / (6 * EI)


def _case(initial=None, load=True, start="rest", design=False, t_end=0.1):
    """A 1 m clamped cantilever of 4 quadratic elements (9 nodes), end load fy = -P."""
    section = {"shape": "given", "EA": 1e9, "EI": EI, "GA": 1e12, "rhoA": 1.0, "rhoI": 1e-4}
    d = {"points": {"O": [0, 0], "B": [L, 0]},
         "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B", "elements": 4,
                     "section": section}],
         "joints": [{"type": "clamp", "body": "rod", "at": "O"}],
         "loads": [{"body": "rod", "at": "B", "fy": -P}] if load else [],
         "responses": [{"name": "tip", "type": "deviation",
                        "terms": [{"body": "rod", "at": "B", "component": "y"}]}],
         "time": {"t_end": t_end, "h": 1e-3, "start": start}}
    if design:      # a circle of steel instead (d = 10.3 mm: EI about 113 N m^2)
        d["materials"] = {"steel": {"E": 2e11, "nu": 0.3, "rho": 7800}}
        d["design"] = [{"name": "d", "lower": 5, "upper": 20, "start": 10.3, "unit": "mm"}]
        d["bodies"][0].update(material="steel", section={"shape": "circle", "diameter": "d"})
        d["constraints"] = [{"response": "tip", "upper": 1e-3}]
    if initial is not None:
        d["initial"] = initial
    return Problem(d)


def test_static_loads_start_is_the_static_solution():
    """[initial] static_loads = the end load, no load in the run: the tip at t = 0 is the
    static deflection P L^3/(3 EI) to 2e-5 (shear P L/GA = 3e-13 m, second order (w/L)^2 =
    1e-6), the same state as time.start = 'static' under the load to 1e-12 m; released, the
    beam swings back: a quarter period of its first mode after release (0.045 s, from
    omega_1 = 1.875^2 sqrt(EI/(rhoA L^4))) the tip passes zero, so the deviation |y| of the
    tip falls below 0.1 TIP within the 0.1 s run."""
    tip0 = _case({"static_loads": [{"body": "rod", "at": "B", "fy": -P}]}, load=False)
    v = tip0.evaluate(gradient=False).values["tip"]
    ref = _case(start="static").evaluate(gradient=False).values["tip"]
    assert abs(v[0] - TIP) < 2e-5 * TIP
    assert abs(v[0] - ref[0]) < 1e-12
    assert v.min() < 0.1 * TIP


def test_given_static_shape_stays_at_rest():
    """[[initial.beams]] deflection = w(x) at the 9 nodes, with the load applied: the beam
    starts in equilibrium (the nodal values of the discrete solution are those of w to 1e-5,
    the spline of 9 samples is exact for the cubic w), so the tip stays within 1e-4 of TIP of
    its static value over 0.1 s, where the straight start swings by about 2 TIP (200 %)."""
    x = np.linspace(0, L, 9)
    v = _case({"beams": [{"body": "rod", "deflection": _w(x).tolist()}]}) \
        .evaluate(gradient=False).values["tip"]
    assert np.max(np.abs(v - TIP)) < 1e-4 * TIP
    straight = _case().evaluate(gradient=False).values["tip"]
    assert straight.max() > 1.9 * TIP


def test_given_rate_sets_the_velocity():
    """deflection_rate = v0 s^2 given at s = 0, 0.5, 1 (the spline through 3 samples is that
    parabola; zero slope at the clamped root, so the joints' velocity constraints hold): the
    simulation's velocities at t = 0 (after the core's projection onto those constraints) are
    v0 (x/L)^2 normal to the beam and rotation rates 2 v0 x/L^2 at the 9 nodes, to 1e-12."""
    v0 = 0.01
    p = _case({"beams": [{"body": "rod", "s": [0, 0.5, 1],
                          "deflection_rate": [0, v0 / 4, v0]}]}, load=False, t_end=0.002)
    r = p.simulate(store="all")
    nodes = p.mechanism.model.body("rod").nodes
    x = np.linspace(0, 1, 9)
    qd = r.qd[0]
    assert np.allclose(qd[[3 * n + 1 for n in nodes]], v0 * x ** 2, atol=1e-12, rtol=0)
    assert np.allclose(qd[[3 * n + 2 for n in nodes]], 2 * v0 * x / L, atol=1e-12, rtol=0)
    assert np.allclose(qd[[3 * n for n in nodes]], 0.0, atol=1e-12)


def test_given_values_keep_exact_gradients():
    """A design run from a given deflection (independent of the design): the constraint rows'
    gradients by direct differentiation and by the adjoint pass the Taylor test (order > 1.8
    over 6 halvings, above the Newton noise)."""
    x = np.linspace(0, L, 9)
    p = _case({"beams": [{"body": "rod", "deflection": (0.5 * _w(x)).tolist()}]}, design=True,
              t_end=0.02)
    x0 = p.start
    for method in ("direct", "adjoint"):
        ev = p.evaluate(x0, gradient=True, method=method)
        c = taylor_test(lambda y: p.evaluate(y, gradient=False).constraints, x0, ev.jacobian,
                        direction=np.array([1.0]), step=0.5, value=ev.constraints,
                        noise=1e-10)
        assert c.ok, (method, c.table())


def test_static_loads_refuse_gradients():
    """With static_loads the initial state depends on the design: a gradient evaluation is a
    ModelError saying so (both methods); without gradients it runs."""
    p = _case({"static_loads": [{"body": "rod", "at": "B", "fy": -P}]}, load=False,
              design=True, t_end=0.02)
    for method in ("direct", "adjoint"):
        with pytest.raises(ModelError, match="static_loads.*depends on the design"):
            p.evaluate(gradient=True, method=method)
    assert np.isfinite(p.evaluate(gradient=False).values["tip"]).all()


@pytest.mark.parametrize("initial, words", [
    ({}, "needs static_loads or beams"),
    ({"beams": [{"body": "rod", "deflection": [0, 1]}]}, "needs one per node \\(9"),
    ({"beams": [{"body": "rod", "s": [0, 1], "deflection": [0, 1, 2]}]},
     "has 3 values for 2 stations"),
    ({"beams": [{"body": "nope", "deflection_rate": [0] * 9}]}, "'nope': not a beam"),
    ({"static_loads": [{"body": "rod", "at": "B"}],
      "beams": [{"body": "rod", "deflection": [0] * 9}]}, "not both"),
])
def test_bad_initial_states_are_named(initial, words):
    """Each malformed [initial] is a case error naming what is wrong."""
    with pytest.raises(Exception, match=words):
        _case(initial)


def test_initial_needs_the_rest_start():
    """[initial] with time.start = 'static' (which would overwrite it) is refused."""
    with pytest.raises(Exception, match="goes with time.start = 'rest'"):
        _case({"static_loads": [{"body": "rod", "at": "B", "fy": -P}]}, start="static")


def test_a_deflection_that_breaks_a_joint_is_named():
    """A deflection 0 -> 10 mm along the clamped rod (a line: slope 0.01 at the clamped root)
    violates the clamp's rotation row by 0.01 rad: a ModelError naming the row and the value
    before any simulation."""
    p = _case({"beams": [{"body": "rod", "s": [0, 1], "deflection": [0.0, 0.01]}]})
    with pytest.raises(ModelError, match="violate constraint 'clamp node 0 phi' by 0.01"):
        p.evaluate(gradient=False)


def test_static_loads_solve_with_the_case_settings(monkeypatch):
    """[initial] static_loads with [solver] tol = 1e-13 and linear_solver = 'dense': the
    static solve that makes the start state runs with the case's settings (the
    SimulationSettings of the problem with start 'static', validity 'off', store 'all'), not
    with the defaults (tol 1e-10, solver 'auto'); the run from it with the case's own."""
    import flexmbs.problem as problem
    seen, run = [], problem.simulate

    def spy(model, t_end, h, settings=None, **kw):
        seen.append(settings)
        return run(model, t_end, h, settings, **kw)

    monkeypatch.setattr(problem, "simulate", spy)
    p0 = _case({"static_loads": [{"body": "rod", "at": "B", "fy": -P}]}, load=False)
    d = p0.description.model_dump(mode="json", by_alias=True, exclude_defaults=True)
    d["solver"] = {"tol": 1e-13, "linear_solver": "dense"}
    p = Problem(d)
    p.evaluate(gradient=False)
    static = [s for s in seen if s.start == "static"]
    assert len(static) == 1 and len(seen) == 2
    assert static[0] == p.settings.replace(start="static", validity="off", store="all")
    assert (static[0].tol, static[0].solver) == (1e-13, "dense")
    assert (seen[1].start, seen[1].tol, seen[1].solver) == ("rest", 1e-13, "dense")


def _bar(initial, t_end, h):
    """A bar of length L along (0.6, 0.8) (inclined, so that the axis' direction matters),
    clamped at O, free at B, 4 quadratic elements (9 nodes), EA = 1e6 N, rhoA = 1 kg/m:
    axial wave speed c = 1000 m/s."""
    section = {"shape": "given", "EA": 1e6, "EI": 100.0, "GA": 1e9, "rhoA": 1.0, "rhoI": 1e-4}
    return Problem({"points": {"O": [0, 0], "B": [0.6 * L, 0.8 * L]},
                    "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                                "elements": 4, "section": section}],
                    "joints": [{"type": "clamp", "body": "rod", "at": "O"}],
                    "time": {"t_end": t_end, "h": h},
                    "initial": {"beams": [dict(body="rod", **initial)]}})


def test_given_axial_field_and_rate_are_the_initial_state():
    """axial = u0 s and axial_rate = v0 s^2 at s = 0, 0.5, 1 (a line and a parabola: the
    spline reproduces them; both zero at the clamped root): the simulation's state at t = 0
    has every node moved by u0 s along the axis (0.6, 0.8) from the assembled configuration,
    with velocity v0 s^2 along it (after the core's projection onto the joints' velocity
    constraints), no rotation and no rotation rate: positions to 1e-15 m (the rounding of
    coordinates of about 1 m), velocities to 1e-12 v0."""
    u0, v0 = 1e-5, 0.01
    s = [0.0, 0.5, 1.0]
    p = _bar({"s": s, "axial": [u0 * x for x in s], "axial_rate": [v0 * x * x for x in s]},
             t_end=1e-5, h=1e-5)
    ev = p.evaluate(gradient=False, store="all")
    nodes = 3 * np.asarray(p.mechanism.model.body("rod").nodes)
    sn = np.linspace(0.0, 1.0, nodes.size)
    q_rest, _ = p.mechanism.initial_state()
    dq = ev.result.q[0] - q_rest
    qd = ev.result.qd[0]
    for k, a in ((0, 0.6), (1, 0.8)):
        assert np.max(np.abs(dq[nodes + k] - a * u0 * sn)) < 1e-15
        assert np.max(np.abs(qd[nodes + k] - a * v0 * sn ** 2)) < 1e-12 * v0
    assert np.max(np.abs(dq[nodes + 2])) < 1e-15 and np.max(np.abs(qd[nodes + 2])) < 1e-12 * v0


def test_axially_prestretched_bar_oscillates_at_its_axial_frequency():
    """axial = u0 sin(pi s / 2) at the 9 nodes (the first axial mode of a clamped-free bar),
    released at rest: the tip moves as u0 cos(omega_1 t), omega_1 = (pi/2) c / L (e.g.
    Meirovitch, Fundamentals of Vibrations, 8.3): 0 at a quarter period T/4 (to 1e-3 u0:
    generalized-alpha's period error (omega h)^2/12 = 2e-5 at h = T/400 moves the zero by
    3e-5 u0), -u0 at T/2 and +u0 at T (to 1e-4 u0; the mode of 4 quadratic elements and the
    spline through 9 samples of the sine are exact to well below that)."""
    u0 = 1e-6
    T = 4.0 * L / 1000.0                   # 2 pi / omega_1 = 4 L / c
    x = np.linspace(0.0, 1.0, 9)
    p = _bar({"axial": (u0 * np.sin(np.pi * x / 2)).tolist()}, t_end=T, h=T / 400)
    ev = p.evaluate(gradient=False, store="all")
    tip = 3 * p.mechanism.model.body("rod").nodes[-1]
    q_rest, _ = p.mechanism.initial_state()
    r = ev.result
    u = (r.q[:, tip] - q_rest[tip]) * 0.6 + (r.q[:, tip + 1] - q_rest[tip + 1]) * 0.8
    assert abs(u[0] - u0) < 1e-15
    assert abs(np.interp(T / 4, r.t, u)) < 1e-3 * u0
    assert abs(np.interp(T / 2, r.t, u) + u0) < 1e-4 * u0
    assert abs(u[-1] - u0) < 1e-4 * u0
