"""Element-wise design variables (docs/case-format.md, "Element-wise variables"):
the expansion of a variable into one component per element or group (names, bounds, start,
the element each component sizes), exact gradients of mass, deviation and stress with respect
to the components (the tube's mass formula; central finite differences), the same mechanism
written with scalar variables, the smoothness rows (max_step, max_step_relative), the weakly
coupled method's static model, and the errors of inconsistent input.
"""
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from flexmbs.errors import CaseError
from flexmbs.methods.esl import equivalent_static_loads
from flexmbs.methods.weakly import StaticModel
from flexmbs.model.casefile import description_from_dict
from flexmbs.problem import Problem

CASES = Path(__file__).resolve().parents[1] / "cases"
RHO = 2700.0
#: wall ratio 0.1: A = pi/4 (d^2 - (0.8 d)^2) = 0.09 pi d^2
AREA = 0.09 * math.pi


def _raw(name):
    return tomllib.loads((CASES / f"{name}.toml").read_text())


def _small(elements=3, t_end=0.05, **extra):
    """robot_2dof_tapered with `elements` per arm and a short horizon."""
    over = {"bodies.arm1.elements": elements, "bodies.arm2.elements": elements,
            "time.t_end": t_end}
    over.update(extra)
    return over


@pytest.fixture(scope="module")
def grouped():
    """3 elements per arm; arm 1 one diameter per element, arm 2 two groups [[1], [2, 3]]; a
    stress response on both arms; 100 steps."""
    raw = _raw("robot_2dof_tapered")
    raw["responses"].append({"name": "stress", "type": "stress", "bodies": ["arm1", "arm2"]})
    return Problem(raw, overrides=_small(**{"design.d_arm2.groups": [[1], [2, 3]]}))


@pytest.fixture(scope="module")
def hollow():
    """3 elements per arm, tubes of given wall: one diameter per element of each arm and one
    wall thickness t (mm) shared by both arms in groups [[1], [2, 3]]; stress on both arms."""
    raw = _raw("robot_2dof_tapered")
    raw["responses"].append({"name": "stress", "type": "stress", "bodies": ["arm1", "arm2"]})
    raw["design"].append({"name": "t", "unit": "mm", "lower": 1.0, "upper": 10.0,
                          "start": 5.0, "groups": [[1], [2, 3]]})
    for b in raw["bodies"][:2]:
        b["section"].pop("wall_ratio")
        b["section"]["thickness"] = "t"
    return Problem(raw, overrides=_small())


def test_tube_mass_gradient_with_elementwise_diameter_and_grouped_wall(hollow):
    """Tube area pi (d t - t^2): mass = rho pi sum_e L_e (d_e t_e - t_e^2), dm/dd_e =
    rho pi L_e t_e and dm/dt_g = rho pi sum over the group's elements of both arms of
    L_e (d_e - 2 t_e) (per mm: 1e-6), L_e = 0.2 m."""
    p = hollow
    assert p.variables[-2:] == ["t[1]", "t[2]"]
    x = np.array([41.0, 37.0, 29.0, 33.0, 28.0, 23.0, 4.0, 2.5])
    p.mechanism.set_design(x)
    value, grad = p._response(p._resp["mass"], x, None, True)
    d = x[:6].reshape(2, 3) * 1e-3
    t = np.array([4.0, 2.5, 2.5]) * 1e-3
    le = 0.2
    assert value == pytest.approx(RHO * math.pi * le * np.sum(d * t - t * t), rel=1e-12)
    dd = (RHO * math.pi * le * t * 1e-3 * np.ones((2, 1))).ravel()
    per_el = RHO * math.pi * le * (d - 2 * t).sum(axis=0) * 1e-3
    np.testing.assert_allclose(grad, np.concatenate([dd, [per_el[0], per_el[1] + per_el[2]]]),
                               rtol=1e-12)


def test_components_expand_names_bounds_start_and_elements(grouped):
    """Names d[k] from 1, bounds and start repeated per component; component k of d_arm1 sizes
    element k of arm 1 and group k of d_arm2 the elements of that group: rhoA of every element
    is rho 0.09 pi d^2 of its own component (the tube of wall ratio 0.1, by hand)."""
    p = grouped
    assert p.variables == ["d_arm1[1]", "d_arm1[2]", "d_arm1[3]", "d_arm2[1]", "d_arm2[2]"]
    np.testing.assert_array_equal(p.lower, [20.0] * 5)
    np.testing.assert_array_equal(p.upper, [60.0] * 5)
    np.testing.assert_array_equal(p.start, [50.0] * 5)
    assert p.mechanism.units == ["mm"] * 5
    x = np.array([41.0, 37.0, 29.0, 33.0, 23.0])
    m = p.mechanism.set_design(x)
    props = m.element_properties()
    for body, dims in (("arm1", [41.0, 37.0, 29.0]), ("arm2", [33.0, 23.0, 23.0])):
        for e, d in zip(m.body(body).elements, dims):
            assert props[3, e] == pytest.approx(RHO * AREA * (d * 1e-3) ** 2, rel=1e-13)


def test_mass_and_its_gradient_are_the_tube_formula(grouped):
    """Mass = rho 0.09 pi sum_e L_e d_e^2 over both arms (lengths 0.6 m, element L/3) and
    dm/dd_k = 2 rho 0.09 pi d_k 1e-6 sum of the lengths component k sizes (per mm)."""
    x = np.array([41.0, 37.0, 29.0, 33.0, 23.0])
    p = grouped
    p.mechanism.set_design(x)
    value, grad = p._response(p._resp["mass"], x, None, True)
    le = 0.6 / 3
    per_el = np.array([41.0, 37.0, 29.0, 33.0, 23.0, 23.0]) * 1e-3
    assert value == pytest.approx(RHO * AREA * le * np.sum(per_el ** 2), rel=1e-12)
    lengths = np.array([le, le, le, le, 2 * le])
    np.testing.assert_allclose(grad, 2 * RHO * AREA * x * 1e-6 * lengths, rtol=1e-12)


def test_one_elementwise_variable_links_two_beams_element_by_element():
    """Both arms name d_arm1 (3 elements each): 3 components, component k sizes element k of
    arm 1 and of arm 2 (rhoA by hand), and dmass/dd_k = 2 x 2 rho 0.09 pi d_k 1e-6 L_e (the
    two arms' equal element lengths, 0.2 m)."""
    raw = _raw("robot_2dof_tapered")
    raw["bodies"][1]["section"]["diameter"] = "d_arm1"
    del raw["design"][1]
    p = Problem(raw, overrides=_small())
    assert p.variables == ["d_arm1[1]", "d_arm1[2]", "d_arm1[3]"]
    x = np.array([45.0, 35.0, 25.0])
    m = p.mechanism.set_design(x)
    props = m.element_properties()
    for body in ("arm1", "arm2"):
        for e, d in zip(m.body(body).elements, x):
            assert props[3, e] == pytest.approx(RHO * AREA * (d * 1e-3) ** 2, rel=1e-13)
    _, grad = p._response(p._resp["mass"], x, None, True)
    np.testing.assert_allclose(grad, 2 * 2 * RHO * AREA * x * 1e-6 * 0.2, rtol=1e-12)


@pytest.mark.parametrize("which", ["grouped", "hollow"])
def test_deviation_and_stress_gradients_match_central_differences(which, request):
    """d(deviation_28)/dx and d(stress)/dx at the last step and at mid-horizon (100 steps,
    non-uniform design; per-element and grouped diameters, or per-element diameters and a
    grouped wall shared by the arms), direct differentiation against central differences with
    a step of 1.25e-4 x_i: agreement to 1e-6 of the gradient's largest entry. Measured:
    at most 7.9e-8 (the central difference's truncation, falling as step^2: with fixed steps of
    0.02, 0.005, 0.00125 mm, 7.5e-5, 4.7e-6, 2.9e-7 on the hollow arms' grouped wall;
    1e-8 at 0.001 mm on the grouped diameters)."""
    p = request.getfixturevalue(which)
    x = {"grouped": np.array([41.0, 37.0, 29.0, 33.0, 23.0]),
         "hollow": np.array([41.0, 37.0, 29.0, 33.0, 28.0, 23.0, 4.0, 2.5])}[which]
    ev = p.evaluate(x, gradient=True)
    h = 1.25e-4 * x
    steps = [50, -1]
    for name in ("deviation_28", "stress"):
        g = ev.gradients[name][steps]
        fd = np.zeros_like(g)
        for i in range(x.size):
            e = np.zeros(x.size)
            e[i] = h[i]
            vp = p.evaluate(x + e, gradient=False).values[name][steps]
            vm = p.evaluate(x - e, gradient=False).values[name][steps]
            fd[:, i] = (vp - vm) / (2 * h[i])
        err = np.abs(fd - g).max(axis=1) / np.abs(g).max(axis=1)
        assert np.all(err < 1e-6), (name, err)


def test_elementwise_design_is_the_scalar_case_element_by_element():
    """robot_2dof with 4 elements per arm (scalar p1..p4, each on 2 elements through the list
    diameter = ["p1", "p2"]) and robot_2dof_tapered with 4 elements per arm at the same
    sections element by element (d_arm1 = [p1, p1, p2, p2], d_arm2 = [p3, p3, p4, p4]) are one
    mechanism written two ways: same mass and deviation histories (to 1e-12), and by the chain
    rule dF/dp1 = dF/dd_arm1[1] + dF/dd_arm1[2], ... (to 1e-9 of the gradient); 0.05 s."""
    p = [44.0, 31.0, 38.0, 27.0]
    scalar = Problem("robot_2dof", overrides=_small(elements=4))
    tapered = Problem("robot_2dof_tapered", overrides=_small(elements=4))
    a = scalar.evaluate(p, gradient=True)
    b = tapered.evaluate(np.repeat(p, 2), gradient=True)
    chain = np.kron(np.eye(4), np.ones((2, 1)))          # (8, 4): d_arm components -> p
    for name in ("mass", "deviation_28", "deviation_30"):
        np.testing.assert_allclose(b.values[name], a.values[name], rtol=1e-12, atol=0)
        gb = np.asarray(b.gradients[name]) @ chain
        ga = np.asarray(a.gradients[name])
        np.testing.assert_allclose(gb, ga, rtol=0, atol=1e-9 * np.abs(ga).max())


def test_smoothness_rows_are_the_documented_linear_constraints():
    """max_step s = 5 mm on d_arm1 (4 elements): rows (x[k+1] - x[k])/s - 1 and
    (x[k] - x[k+1])/s - 1 for each of the 3 neighbour pairs; max_step_relative r = 0.25 on
    d_arm2: (x[k+1] - 1.25 x[k])/(0.25 upper) and the swapped row; Evaluation appends them
    after the response constraints, with their constant Jacobian and names, values by hand."""
    prob = Problem("robot_2dof_tapered", overrides=_small(
        elements=4, t_end=0.002, **{"design.d_arm2.max_step_relative": 0.25,
                                    "design.d_arm2.max_step": None}))
    x = np.array([50.0, 47.0, 40.0, 41.0, 30.0, 36.0, 36.0, 29.0])
    ev = prob.evaluate(x, gradient=True)
    one = 12
    assert ev.constraints.size == 5 + one        # 5 steps of deviation_28, then 12 rows
    g, J = ev.constraints[-one:], ev.jacobian[-one:]
    assert ev.constraint_names[-one:] == ["d_arm1 max_step"] * 6 + \
        ["d_arm2 max_step_relative"] * 6
    d1, d2 = x[:4], x[4:]
    want = []
    for k in range(3):
        want += [(d1[k + 1] - d1[k]) / 5.0 - 1.0, (d1[k] - d1[k + 1]) / 5.0 - 1.0]
    for k in range(3):
        want += [(d2[k + 1] - 1.25 * d2[k]) / 15.0, (d2[k] - 1.25 * d2[k + 1]) / 15.0]
    np.testing.assert_allclose(g, want, rtol=1e-14, atol=1e-15)
    # the second pair of d_arm1 steps by 7 mm > 5 mm and d_arm2's first by 20 % < 25 %
    assert g[3] == pytest.approx(0.4, rel=1e-12) and g[6] < 0 and g[7] < 0
    np.testing.assert_array_equal(J[0], [-0.2, 0.2, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(J[7], [0, 0, 0, 0, 1 / 15.0, -1.25 / 15.0, 0, 0])


def test_weakly_static_model_gradients_with_elementwise_variables():
    """The weakly coupled method's static model (ESL of one simulation, 3 elements per arm,
    0.05 s) with per-element and grouped diameters: its deviation-chain rows and the rows of a
    stress limit on both arms have exact gradients (Taylor remainder of order 2, > 1.8, along
    a random direction, steps 2^-2 .. 2^-7 mm; a 1e-2 relative error in the stress rows'
    jacobian gives order < 1.3; measured: 2.002, 2.002 and 0.86; the static solve is direct,
    no Newton noise); the smoothness rows are among its constraints."""
    from flexmbs.analysis.checks import taylor_test
    raw = _raw("robot_2dof_tapered")
    raw["responses"].append({"name": "stress", "type": "stress", "bodies": ["arm1", "arm2"]})
    raw["constraints"].append({"response": "stress", "upper": 20e6})
    prob = Problem(raw, overrides=_small(**{"design.d_arm2.groups": [[1], [2, 3]]}))
    static = StaticModel(prob)
    x = np.array([41.0, 37.0, 29.0, 33.0, 23.0])
    res = prob.simulate(x, store="all")
    model = prob.mechanism.set_design(x)
    static.set_loads(equivalent_static_loads(model, res, static.frames,
                                             stiffness=static.stiffness))
    _, _, g, J, _, names = static.evaluate(x)
    assert {"deviation_28", "stress", "d_arm1 max_step"} <= set(names)
    assert J.shape == (g.size, 5)
    rows = {n: np.array([k for k, m in enumerate(names) if m == n])
            for n in ("deviation_28", "stress")}

    def split(gg):
        out = {n: gg[r] for n, r in rows.items()}
        out["wrong"] = gg[rows["stress"]]
        return out
    jac = {n: J[r] for n, r in rows.items()}
    jac["wrong"] = J[rows["stress"]] * (1 + 1e-2)
    checks = taylor_test(lambda q: split(static.evaluate(q, False)[2]), x, jac, None,
                         step=2.0 ** -2, halvings=5, value=split(g))
    assert checks["deviation_28"].ok, checks["deviation_28"].table()
    assert checks["stress"].ok, checks["stress"].table()
    assert checks["wrong"].order < 1.3


def test_fully_coupled_optimization_respects_the_smoothness_limit():
    """The fully coupled method (MMA) on the tapered robot, 3 elements per arm, 0.1 s, the
    deviation limited to 0.789 mm (3x its value at the start): without max_step the optimum
    tapers by more than 2 mm per element (measured 6.4 to 9.7 mm); with max_step = 1 mm every
    neighbour step is at most 1 mm (the linear rows reached the optimizer) and at least
    0.99 mm (they bind), and the optimum is heavier (a constrained minimum cannot be lighter;
    measured 1.013 and 1.193 kg). Both runs converge (KKT), under a second each."""
    from flexmbs.optimize import optimize_fully
    over = _small(t_end=0.1, **{"constraints.0.upper": 7.89e-4})
    free = optimize_fully(Problem("robot_2dof_tapered", overrides={
        **over, "design.d_arm1.max_step": None, "design.d_arm2.max_step": None}))
    smooth = optimize_fully(Problem("robot_2dof_tapered", overrides={
        **over, "design.d_arm1.max_step": 1.0, "design.d_arm2.max_step": 1.0}))
    assert free.converged and smooth.converged, (free.reason, smooth.reason)

    def steps(x):
        return np.abs(np.diff(np.reshape(x, (2, 3)), axis=1))
    assert steps(free.design).max() > 2.0, free.design
    assert np.all(steps(smooth.design) <= 1.0 + 1e-6), smooth.design
    assert np.all(steps(smooth.design) >= 0.99), smooth.design
    assert smooth.objective > free.objective


# ----------------------------------------------------------------------------- errors
def _tapered(edit):
    raw = _raw("robot_2dof_tapered")
    edit(raw)
    return raw


def _set(raw, where, **kw):
    where(raw).update(kw)


@pytest.mark.parametrize("edit,message", [
    (lambda r: _set(r, lambda r: r["design"][1], groups=[[1, 2, 3], [4, 5, 6, 7], [9]]),
     r"design variable 'd_arm2' \(groups\): groups = .* names element 9, but body 'arm2' has "
     r"8 elements"),
    (lambda r: _set(r, lambda r: r["design"][1], groups=[[1, 2, 3], [4, 5, 6]]),
     r"design variable 'd_arm2' \(groups\): .*leave element\(s\) \[7, 8\] of body 'arm2'"),
    (lambda r: _set(r, lambda r: r["design"][1], groups=[[1, 2], [2, 3]]),
     r"design variable 'd_arm2': groups = .* lists element 2 twice"),
    (lambda r: _set(r, lambda r: r["design"][1], groups=[[1, 0]]),
     r"key 'design\[1\]\.groups\[0\]\[1\]' .*greater than or equal to 1, got 0"),
    (lambda r: (_set(r, lambda r: r["bodies"][1]["section"], diameter="d_arm1"),
                _set(r, lambda r: r["bodies"][1], elements=6)),
     r"design variable 'd_arm1' \(per_element\): the beams sharing it have different numbers "
     r"of elements \('arm1': 8, 'arm2': 6\)"),
    (lambda r: _set(r, lambda r: r["bodies"][1]["section"], diameter=["d_arm2", 0.03]),
     r"design variable 'd_arm2' \(per_element\): body 'arm2' names it inside the list "
     r"section\.diameter"),
    (lambda r: _set(r, lambda r: r["bodies"][1]["section"], diameter=0.03),
     r"design variable 'd_arm2' \(per_element\): no beam section names it"),
    (lambda r: _set(r, lambda r: r["design"][1], per_element=False),
     r"design variable 'd_arm2': max_step = 5.0 needs an element-wise variable"),
    (lambda r: _set(r, lambda r: r["design"][1], per_element=False, max_step=None,
                    groups=[[1, 2, 3, 4], [5, 6, 7, 8]]),
     r"design variable 'd_arm2': groups = .* per_element = false"),
    (lambda r: _set(r, lambda r: r["design"][1], max_step=-1.0),
     r"key 'design\[1\]\.max_step' .*greater than 0, got -1.0"),
])
def test_inconsistent_elementwise_input_names_the_key(edit, message):
    """Wrong group indices (beyond the beam, missing, repeated, below 1), an element-wise
    variable shared by beams of different element counts, used inside a per-element list or
    by no beam, a smoothness limit on a scalar variable, groups with per_element = false, a
    negative max_step: each a CaseError naming the variable, the key and the value."""
    with pytest.raises(CaseError, match=message):
        description_from_dict(_tapered(edit), "robot_2dof_tapered.toml")


def test_a_design_of_the_wrong_length_names_the_components():
    """A design that does not list every component is a ModelError naming the count and the
    element-wise variables as d[1..n]."""
    from flexmbs.errors import ModelError
    p = Problem("robot_2dof_tapered", overrides=_small(t_end=0.002))
    with pytest.raises(ModelError, match=r"design must be 6 finite numbers "
                                         r"\(d_arm1\[1\.\.3\], d_arm2\[1\.\.3\]\), got \[40, 30\]"):
        p.evaluate([40, 30])


def test_progress_line_summarizes_many_variables():
    """A progress line of `flexmbs optimize` lists a design of up to 8 variables and gives the
    count and range of a larger one (a line with 64 numbers per iteration is unreadable)."""
    from flexmbs.cli.optimize import _iteration_line
    rec = dict(iteration=3, objective=0.5, max_violation=0.0, kkt_residual=1e-2, simulations=4)
    few = _iteration_line(dict(rec, design=[39.29, 28.33]))
    assert "x = [39.29, 28.33]" in few
    many = _iteration_line(dict(rec, design=list(np.linspace(0.5, 60.0, 64))))
    assert "x = (64 values in [0.5, 60])" in many


def test_result_plot_draws_small_profiles_on_a_second_axis(tmp_path, monkeypatch):
    """OptimizationResult.plot with element-wise diameters (~50 mm) and walls (~1 mm): a PNG is
    written, the walls go to a second y axis (labelled 'right axis') and the diameters stay
    on the first, so that both profiles can be read."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from flexmbs.methods.result import OptimizationResult
    names = [f"D[{k}]" for k in range(1, 5)] + [f"t[{k}]" for k in range(1, 5)]
    design = np.array([60.0, 55.0, 40.0, 22.0, 0.5, 0.5, 0.6, 0.5])
    res = OptimizationResult(
        method="fully", case="x", variables=names, units=["mm"] * 8, design=design,
        start=np.array([50.0] * 4 + [5.0] * 4), objective=0.3, objective_name="mass",
        mass_kg=0.3, max_violation=0.0, max_deviation_m=None, iterations=2,
        inner_iterations=None, evaluations=2, simulations=2, converged=False, reason="cap",
        history=[{"iteration": 1, "mass_kg": 0.5, "max_violation": 0.0},
                 {"iteration": 2, "mass_kg": 0.3, "max_violation": 0.0}], wall_time_s=1.0)
    figs = []
    monkeypatch.setattr(plt, "close", lambda fig: figs.append(fig))
    out = res.plot(tmp_path / "r.png")
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", out
    axes = figs[0].axes
    labels = {ax.get_ylabel(): [ln.get_label() for ln in ax.get_lines()] for ax in axes}
    assert any("t [mm] (right axis)" in v for v in labels.get("design value (right axis)", []))
    assert any(v == "D [mm]" for v in labels["design value"])
