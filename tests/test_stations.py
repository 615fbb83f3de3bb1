"""Responses at stations along a beam (docs/case-format.md, "Responses"): `at = {body, s}`
for deviation terms, the deflection from the chord ('deflection'), strains ('strain') and
stress; their design gradients by direct differentiation and by the discrete adjoint (Taylor
tests, flexmbs.analysis.checks.taylor_test); the layout of the coordinates (Mechanism.layout, the
names `flexmbs simulate --out` writes).

Analytic references: the cantilever of length L under an end load P (Euler-Bernoulli; e.g.
Timoshenko & Gere, Mechanics of Materials, Appendix G, case 1): w(x) = P x^2 (3L - x)/(6 EI),
curvature kappa(x) = P (L - x)/EI, and the Navier stress of the extreme fibre
sigma = M c / I = P (L - x) c / I.
"""
import math

import numpy as np
import pytest

from flexmbs.analysis.checks import taylor_test
from flexmbs.model.description import Description
from flexmbs.model.mechanism import Mechanism
from flexmbs.problem import Problem
from flexmbs.responses.station import locate

L, EI, P = 1.0, 100.0, 0.3          # tip deflection P L^3/(3 EI) = 1 mm: small rotations


def _cantilever(responses, section=None, elements=4):
    """A clamped 1 m beam under the end load fy = -P, solved statically ([time] start =
    'static'): its first time point is the static solution."""
    section = section or {"shape": "given", "EA": 1e9, "EI": EI, "GA": 1e12, "rhoA": 1.0,
                          "rhoI": 1e-4}
    d = {"points": {"O": [0, 0], "B": [L, 0]},
         "materials": {"steel": {"E": 2e11, "nu": 0.3, "rho": 7800}},
         "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                     "elements": elements, "section": section}],
         "joints": [{"type": "clamp", "body": "rod", "at": "O"}],
         "loads": [{"body": "rod", "at": "B", "fy": -P}],
         "responses": responses,
         "time": {"t_end": 0.002, "h": 0.001, "start": "static"}}
    if section["shape"] != "given":
        d["bodies"][0]["material"] = "steel"
    return Problem(d)


def _w(x):
    return -P * x * x * (3 * L - x) / (6 * EI)


def test_locate_puts_a_station_in_its_element():
    """s = 0.45 of 4 elements: element 1 (0-based) at xi = 2 (1.8 - 1) - 1 = 0.6; s = 1 in the
    last element at xi = 1; s = 0.5 (a boundary) in the element after it at xi = -1; the shape
    values sum to 1."""
    m = _cantilever([]).mechanism.model
    p = locate(m, "rod", 0.45)
    assert (p.index, round(p.xi, 12)) == (1, 0.6) and abs(p.n.sum() - 1) < 1e-15
    assert (locate(m, "rod", 1.0).index, locate(m, "rod", 1.0).xi) == (3, 1.0)
    assert (locate(m, "rod", 0.5).index, locate(m, "rod", 0.5).xi) == (2, -1.0)


def test_cantilever_deflection_at_a_station():
    """Deviation term {at = {rod, s = 0.45}, y}: the mid-element point of a 3-node element is
    the quadratic interpolation of its nodes. Nodal deflections of this element are exact for
    the cubic w(x) (the rotation, quadratic, is in the element's space), so the station gives
    the quadratic interpolant of w at x = 0.45: analytic to 1e-5 relative (shear P/GA and
    second-order terms (w/L)^2 = 1e-6), and w(0.45) itself to its interpolation error
    w''' (x-a)(x-a-h/2)(x-a-h)/6 = 1.5e-3 relative (tolerance 2e-2)."""
    p = _cantilever([{"name": "w", "type": "deviation",
                      "terms": [{"at": {"body": "rod", "s": 0.45}, "component": "y"}]}])
    w = p.evaluate(gradient=False).values["w"][0]
    x = np.array([0.25, 0.375, 0.5])                   # element 2's nodes
    lag = np.polynomial.polynomial.polyfit(x, _w(x), 2)
    interp = abs(np.polynomial.polynomial.polyval(0.45, lag))
    assert abs(w - interp) < 1e-5 * interp
    assert abs(w - abs(_w(0.45))) < 2e-2 * abs(_w(0.45))


def test_deflection_from_the_chord():
    """Deflection of s = 0.5 from the chord through the ends: w(L/2) - w(L)/2 = P L^3/(16 EI)
    above the chord (positive: on its left, from 'from' to 'to'), to 1e-4 relative (second
    order in the rotations, 1e-6, and the shear P/GA); zero at s = 0 and s = 1."""
    p = _cantilever([{"name": f"w{k}", "type": "deflection", "at": {"body": "rod", "s": s}}
                     for k, s in enumerate((0.0, 0.5, 1.0))])
    v = p.evaluate(gradient=False).values
    ref = P * L ** 3 / (16 * EI)
    assert abs(v["w1"][0] - ref) < 1e-4 * ref
    assert abs(v["w0"][0]) < 1e-12 and abs(v["w2"][0]) < 1e-12


@pytest.mark.parametrize("s", [0.1, 0.45, 0.9])
def test_curvature_and_stress_at_a_station(s):
    """Curvature at a station: -P (L - x)/EI (the rotation, quadratic in x, is in the 3-node
    element's space: exact to the second-order terms, 1e-4 relative tolerance); the stress of
    a d = 20 mm steel circle there: Navier's P (L - x) c / I to 1e-3 relative (axial strain
    from the deflection's second order adds E eps, below 1e-5 of it)."""
    d = 0.02
    inertia = math.pi * d ** 4 / 64
    p = _cantilever([{"name": "k", "type": "strain", "at": {"body": "rod", "s": s},
                      "component": "curvature"},
                     {"name": "sig", "type": "stress", "at": {"body": "rod", "s": s}}],
                    section={"shape": "circle", "diameter": d})
    ei = 2e11 * inertia
    v = p.evaluate(gradient=False).values
    kap = -P * (L - s * L) / ei
    assert abs(v["k"][0] - kap) < 1e-4 * abs(kap)
    sig = P * (L - s * L) * (d / 2) / inertia
    assert abs(v["sig"][0] - sig) < 1e-3 * sig


def _swinging(constraint):
    """A 0.8 m aluminium arm with a 0.5 kg tip mass turned 0.2 rad by a smooth step over
    0.05 s, two diameter groups (mm), responses at stations, every step constrained."""
    S = lambda s: {"body": "arm", "s": s}                                   # noqa: E731
    responses = [
        {"name": "w", "type": "deflection", "at": S(0.45)},
        {"name": "dev", "type": "deviation", "terms": [
            {"at": S(0.3), "component": "y", "frame": "arm"},
            {"at": S(0.7), "component": "angle", "relative_to": {"at": S(0.1)}}]},
        {"name": "k", "type": "strain", "at": S(0.6), "component": "curvature"},
        {"name": "e", "type": "strain", "at": S(0.6), "component": "axial"},
        {"name": "sig", "type": "stress", "at": S(0.2)}]
    limits = {"w": 0.01, "dev": 0.05, "k": 0.1, "e": 1e-4, "sig": 1e8}
    return Problem({
        "points": {"O": [0, 0], "A": [0.8, 0]},
        "materials": {"al": {"E": 7e10, "nu": 0.33, "rho": 2700}},
        "design": [{"name": "d", "lower": 5, "upper": 50, "start": 20, "unit": "mm",
                    "groups": [[1, 2], [3, 4]]}],
        "bodies": [{"name": "arm", "type": "beam", "from": "O", "to": "A", "elements": 4,
                    "material": "al", "section": {"shape": "circle", "diameter": "d"}},
                   {"name": "tip", "type": "mass", "at": "A", "on": "arm", "mass": 0.5}],
        "joints": [{"type": "pin", "body": "arm", "at": "O"}],
        "drives": [{"type": "rotation", "body": "arm", "at": "O",
                    "law": {"type": "smooth_step", "end": 0.2, "t1": 0.05}}],
        "responses": responses,
        "constraints": [{"response": n, "upper": u, "over": constraint}
                        for n, u in limits.items()],
        "time": {"t_end": 0.04, "h": 1e-3}})


@pytest.mark.parametrize("method", ["direct", "adjoint"])
def test_station_gradients_pass_the_taylor_test(method):
    """Taylor test of the constraint rows of each station response (deflection, deviation of
    stations with a station relative_to, curvature, axial strain, stress), gradients by
    `method`: the remainder falls at order > 1.8 over 6 halvings of the step (2 for an exact
    gradient, 1 for a wrong one), above the Newton noise (1e-10 of the normalised rows)."""
    p = _swinging("every_step")
    x = p.start
    ev = p.evaluate(x, gradient=True, method=method)
    names = np.array(ev.constraint_names)
    keys = ["w", "dev", "k", "e", "sig"]

    def rows(c):
        return {k: c[names == k] for k in keys}

    def fun(y):
        return rows(p.evaluate(y, gradient=False).constraints)
    jac = {k: ev.jacobian[names == k] for k in keys}
    checks = taylor_test(fun, x, jac, direction=np.array([1.0, -0.6]), step=1.0,
                         value=rows(ev.constraints), noise=1e-10)
    for k, c in checks.items():
        assert c.ok, (k, c.table())


def test_direct_and_adjoint_station_gradients_agree():
    """The KS rows of the station responses: the adjoint's gradient equals direct
    differentiation's to 1e-6 relative (the same discrete derivative, two ways)."""
    p = _swinging("ks")
    x = p.start
    jd = p.evaluate(x, gradient=True, method="direct").jacobian
    ja = p.evaluate(x, gradient=True, method="adjoint").jacobian
    assert np.max(np.abs(jd - ja)) < 1e-6 * np.max(np.abs(jd))


def test_stations_are_checked_against_the_case():
    """A station on a body that is not a beam, a body given twice differently, and s outside
    [0, 1] are errors naming the response and the key."""
    base = {"points": {"O": [0, 0], "B": [1, 0]},
            "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                        "section": {"shape": "given", "EA": 1, "EI": 1, "rhoA": 1, "rhoI": 1}},
                       {"name": "m", "type": "mass", "at": "B", "mass": 1, "inertia": 1}],
            "joints": [{"type": "pin", "body": "rod", "at": "O"}],
            "time": {"t_end": 1}}
    for resp, words in [
            ({"name": "r", "type": "deflection", "at": {"body": "m", "s": 0.5}},
             "response 'r': body 'm' is not a beam"),
            ({"name": "r", "type": "deviation", "terms": [
                {"body": "m", "at": {"body": "rod", "s": 0.5}}]},
             "body = 'm' contradicts at.body = 'rod'"),
            ({"name": "r", "type": "strain", "at": {"body": "rod", "s": 1.5}},
             "less than or equal to 1"),
            ({"name": "r", "type": "stress", "bodies": ["rod"], "at": {"body": "rod", "s": 0}},
             "exactly one of bodies")]:
        with pytest.raises(ValueError, match=words):
            Description.model_validate(dict(base, responses=[resp]))


def test_layout_names_every_coordinate():
    """Mechanism.layout: coordinate 3 n + k is component k of node n; the beam's nodes carry
    its name, its end points and their fractions s = k/(nodes - 1) (4 quadratic elements: 9
    nodes, s = 0, 1/8, ..., 1) and their initial positions x = s L."""
    mech = _cantilever([]).mechanism
    lay = mech.layout()
    assert lay["dof_node"].tolist() == [k // 3 for k in range(mech.model.ndof)]
    assert lay["dof_component"][:3].tolist() == ["x", "y", "angle"]
    rod = [int(n) for n in lay["body_nodes"][0].split(",")]
    assert lay["body_names"].tolist() == ["rod"] and len(rod) == 9
    assert np.allclose(lay["node_s"][rod], np.arange(9) / 8)
    assert np.allclose(lay["node_xy"][rod, 0], np.arange(9) / 8 * L)
    assert lay["node_point"][rod[0]] == "O" and lay["node_point"][rod[-1]] == "B"
    assert lay["node_point"][rod[4]] == "" and set(lay["node_body"][rod]) == {"rod"}


def test_a_built_mechanism_refuses_a_bad_station():
    """locate() outside [0, 1] or on a point mass: ModelError naming the body and the value."""
    from flexmbs.errors import ModelError
    mech = Mechanism(Description.model_validate({
        "points": {"O": [0, 0], "B": [1, 0]},
        "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                    "section": {"shape": "given", "EA": 1, "EI": 1, "rhoA": 1, "rhoI": 1}},
                   {"name": "m", "type": "mass", "at": "B", "mass": 1, "inertia": 1}],
        "joints": [{"type": "clamp", "body": "rod", "at": "O"}],
        "time": {"t_end": 0.01, "h": 0.01}}))
    with pytest.raises(ModelError, match="s must be a number in \\[0, 1\\].*got 2"):
        locate(mech.model, "rod", 2)
    with pytest.raises(ModelError, match="body 'm' is not a beam"):
        locate(mech.model, "m", 0.5)


CASE_TOML = """
[points]
O = [0, 0]
B = [1, 0]

[[bodies]]
name = "rod"
type = "beam"
from = "O"
to = "B"
elements = 4
section = { shape = "given", EA = 1e9, EI = 100.0, GA = 1e12, rhoA = 1.0, rhoI = 1e-4 }

[[joints]]
type = "clamp"
body = "rod"
at = "O"

[[loads]]
body = "rod"
at = "B"
fy = -0.3

[[responses]]
name = "mid"
type = "deflection"
at = { body = "rod", s = 0.5 }

[time]
t_end = 0.01
h = 0.001
start = "static"
"""


def test_out_file_names_nodes_and_gives_the_mid_span(tmp_path):
    """`flexmbs simulate CASE --out`: with the file's own names (node_s, node_body,
    dof_node, dof_component) the mid-span node and the rod's ends are found, and the
    deflection from the chord computed from their columns of q equals the file's
    'deflection' response history to 1e-15 m (the same formula on the same numbers), which
    starts (static start) at P L^3/(16 EI) to 1e-4 (test_deflection_from_the_chord)."""
    from flexmbs.cli.main import main
    case = tmp_path / "rod.toml"
    case.write_text(CASE_TOML)
    assert main(["simulate", str(case), "--out", str(tmp_path / "r.npz")]) == 0
    with np.load(tmp_path / "r.npz") as f:
        on_rod = f["node_body"] == "rod"
        node = {s: int(np.flatnonzero(on_rod & np.isclose(f["node_s"], s))[0])
                for s in (0.0, 0.5, 1.0)}
        col = {(int(n), str(c)): k for k, (n, c) in enumerate(zip(f["dof_node"],
                                                                  f["dof_component"]))}
        q = f["q"]
        r = {s: q[:, [col[(n, "x")], col[(n, "y")]]] for s, n in node.items()}
        c, p = r[1.0] - r[0.0], r[0.5] - r[0.0]
        w = (c[:, 0] * p[:, 1] - c[:, 1] * p[:, 0]) / np.hypot(c[:, 0], c[:, 1])
        assert np.max(np.abs(w - f["response_mid"])) < 1e-15
        ref = P * L ** 3 / (16 * EI)
        assert abs(f["response_mid"][0] - ref) < 1e-4 * ref


def test_station_responses_carry_their_units():
    """The JSON's units (flexmbs.output.units, docs/json-output.md) name the station
    responses' units: a deflection in m, an axial strain dimensionless ('1'), a curvature in
    1/m, a stress in Pa."""
    from flexmbs.output import units
    at = {"body": "rod", "s": 0.5}
    p = _cantilever([{"name": "w", "type": "deflection", "at": at},
                     {"name": "eps", "type": "strain", "at": at},
                     {"name": "k", "type": "strain", "at": at, "component": "curvature"},
                     {"name": "sig", "type": "stress", "at": at}],
                    section={"shape": "circle", "diameter": 0.02})
    assert units(p)["responses"] == {"w": "m", "eps": "1", "k": "1/m", "sig": "Pa"}


def test_a_station_on_a_boundary_up_to_rounding_is_in_the_element_after_it():
    """s = 0.58 of 50 elements: 0.58 * 50 is 28.999999999999996 in floating point, a boundary:
    the station is in element 29 (0-based) at xi = -1, as s = 0.5 of 4 elements is, not in
    element 28 at xi = 1 (same position, but strains and stresses read another element)."""
    m = _cantilever([], elements=50).mechanism.model
    p = locate(m, "rod", 0.58)
    assert (p.index, p.xi) == (29, -1.0)
