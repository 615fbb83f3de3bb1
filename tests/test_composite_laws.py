"""Composite laws of the case format (docs/case-format.md, "Laws"): 'piecewise' (a list of
segments, each any law over its interval) and 'sum' (a list of laws added), and a beam with a
'given' section and no material.

Sources: the spin-up law of J. C. Simo, L. Vu-Quoc, "On the dynamics of flexible beams under
large overall motions - the plane case", J. Appl. Mech. 53 (1986), Part II, eq. (7.1),
theta(t) = (w/T)(t^2/2 + (T/2pi)^2 (cos(2 pi t/T) - 1)) for t < T, w (t - T/2) after, is a
polynomial plus a harmonic up to T and a polynomial after; the Euler-Bernoulli cantilever
under an end load P: tip deflection P L^3 / (3 EI) (e.g. Timoshenko & Gere, Mechanics of
Materials, Appendix G, case 1).
"""
import math

import numpy as np
import pytest

from flexmbs import simulate
from flexmbs.errors import ModelError
from flexmbs.model.description import Description, Law
from flexmbs.model.laws import TimeLaw
from flexmbs.model.mechanism import Mechanism, make_law
from flexmbs.analysis.settings import InitialConditions, SimulationSettings


def _spin_up_case_law(w, T):
    """Simo & Vu-Quoc's eq. (7.1) written with the case format's laws."""
    c = (T / (2 * math.pi)) ** 2
    return {"type": "piecewise", "segments": [
        {"until": T, "law": {"type": "sum", "laws": [
            {"type": "polynomial", "coefficients": [-w * c / T, 0.0, w / (2 * T)]},
            {"type": "harmonic", "amplitude": w * c / T, "frequency_hz": 1.0 / T,
             "phase": math.pi / 2}]}},
        {"law": {"type": "polynomial", "coefficients": [-w * T / 2, w]}}]}


def test_piecewise_sum_law_is_the_spin_up_law():
    """The spin-up law of Simo & Vu-Quoc eq. (7.1) as piecewise(sum(polynomial, harmonic),
    polynomial) equals the closed form and its analytic rate and acceleration to 1e-12
    (relative to the law's scale), on both sides of the break T = 15 s."""
    w, T = 4.0, 15.0
    law = make_law(Law.model_validate(_spin_up_case_law(w, T)), "spin-up")
    t = np.concatenate([np.linspace(0.0, 20.0, 401), [T - 1e-9, T]])
    c = (T / (2 * math.pi)) ** 2
    value = np.where(t < T, w / T * (t ** 2 / 2 + c * (np.cos(2 * math.pi * t / T) - 1)),
                     w * (t - T / 2))
    rate = np.where(t < T, w / T * (t - T / (2 * math.pi) * np.sin(2 * math.pi * t / T)), w)
    accel = np.where(t < T, w / T * (1 - np.cos(2 * math.pi * t / T)), 0.0)
    v, d, a = law.evaluate(t)
    assert np.max(np.abs(v - value)) < 1e-12 * w * 20
    assert np.max(np.abs(d - rate)) < 1e-12 * w * 20
    assert np.max(np.abs(a - accel)) < 1e-12 * w


def test_piecewise_takes_each_segment_on_its_interval():
    """Segment k's law on [until_{k-1}, until_k), the later law at a break (constant 1, 2, 3
    on [0,1), [1,2), [2,..): the values 1, 2, 2, 3 at t = 0.5, 1, 1.5, 2); each segment's law is
    of the absolute time (a ramp 'polynomial [0, 1]' in the last segment gives t)."""
    law = TimeLaw.piecewise([1.0, 2.0], [1.0, 2.0, TimeLaw(lambda t: t, lambda t: 1 + 0 * t,
                                                            lambda t: 0 * t)])
    v, d, _ = law.evaluate(np.array([0.5, 1.0, 1.5, 2.0, 3.0]))
    assert v.tolist() == [1.0, 2.0, 2.0, 2.0, 3.0]
    assert d.tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]


def test_sum_adds_values_rates_and_accelerations():
    """sum(harmonic sin(2 pi t), polynomial 1 + t^2) = 1 + t^2 + sin(2 pi t): rate 2t +
    2 pi cos(2 pi t), acceleration 2 - 4 pi^2 sin(2 pi t), to 1e-12."""
    law = make_law(Law.model_validate({"type": "sum", "laws": [
        {"type": "harmonic", "amplitude": 1.0, "frequency_hz": 1.0},
        {"type": "polynomial", "coefficients": [1.0, 0.0, 1.0]}]}))
    t = np.linspace(0, 1, 11)
    v, d, a = law.evaluate(t)
    s, c = np.sin(2 * np.pi * t), np.cos(2 * np.pi * t)
    assert np.allclose(v, 1 + t * t + s, atol=1e-12, rtol=0)
    assert np.allclose(d, 2 * t + 2 * np.pi * c, atol=1e-12, rtol=0)
    assert np.allclose(a, 2 - 4 * np.pi ** 2 * s, atol=1e-11, rtol=0)


@pytest.mark.parametrize("law, words", [
    ({"type": "piecewise", "segments": [{"law": {"type": "constant", "value": 0}}, {"law": {
        "type": "constant", "value": 1}}]}, "every segment but the last needs until"),
    ({"type": "piecewise", "segments": [{"until": 2, "law": {"type": "constant", "value": 0}},
                                        {"until": 1, "law": {"type": "constant", "value": 0}},
                                        {"law": {"type": "constant", "value": 1}}]},
     "must increase strictly"),
    ({"type": "sum", "laws": [{"type": "reference"}]}, "is of type 'reference'"),
    ({"type": "sum", "laws": [{"type": "constant", "value": 1, "absolute": True}]},
     "set it on the sum law itself"),
    ({"type": "constant", "value": 1, "laws": [{"type": "constant", "value": 1}]},
     "laws belongs to a 'sum' law"),
    ({"type": "sum"}, "needs laws"),
])
def test_bad_composite_laws_are_refused_with_the_reason(law, words):
    """Each malformed composite law is a validation error whose message says what is wrong."""
    with pytest.raises(ValueError, match=words):
        Law.model_validate(law)


def test_piecewise_breaks_must_match_the_laws():
    """TimeLaw.piecewise with as many breaks as laws is a ModelError naming the count."""
    with pytest.raises(ModelError, match="one fewer than the 2 laws"):
        TimeLaw.piecewise([1.0, 2.0], [0.0, 1.0])


def _cantilever(material=None, elements=4, load=-10.0):
    """A 1 m cantilever of a 'given' section (EA 1e8 N, EI 100 N m^2), end load fy."""
    d = {"points": {"O": [0, 0], "B": [1, 0]},
         "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                     "elements": elements,
                     "section": {"shape": "given", "EA": 1e8, "EI": 100.0, "GA": 1e8,
                                 "rhoA": 1.0, "rhoI": 1e-4}}],
         "joints": [{"type": "clamp", "body": "rod", "at": "O"}],
         "loads": [{"body": "rod", "at": "B", "fy": load}],
         "time": {"t_end": 0.002, "h": 0.001, "start": "static"}}
    if material is not None:
        d["materials"] = {"m": material}
        d["bodies"][0]["material"] = "m"
    return d


def test_given_section_needs_no_material():
    """A beam of 'given' section without a material: its static tip deflection under P = 1 N
    is P L^3/(3 EI) = 1/300 m (Euler-Bernoulli; the shear part P L/GA = 1e-8 m and the
    geometric nonlinearity (about (w/L)^2 = 1e-5 relative) are within the 1e-3 tolerance)."""
    mech = Mechanism(Description.model_validate(_cantilever(load=-1.0)))
    q0, _ = mech.initial_state()
    r = simulate(mech.model, 0.002, 0.001,
                 settings=SimulationSettings(start="static", store="all"),
                 initial=InitialConditions(q0=q0))
    tip = mech.node[("rod", "B")]
    assert abs(r.q[0, r.dofs.tolist().index(3 * tip + 1)] + 1 / 300) < 1e-3 / 300


def test_other_sections_still_need_a_material():
    """A circle section without a material is refused, naming the beam and the section."""
    d = _cantilever()
    d["bodies"][0]["section"] = {"shape": "circle", "diameter": 0.01}
    with pytest.raises(ValueError, match="beam 'rod': a 'circle' section needs a material"):
        Description.model_validate(d)


def _hub(law):
    """A 1 m beam pinned at its root and turned there by `law`."""
    return {"points": {"O": [0, 0], "B": [1, 0]},
            "bodies": [{"name": "rod", "type": "beam", "from": "O", "to": "B",
                        "section": {"shape": "given", "EA": 1e8, "EI": 100.0, "rhoA": 1.0,
                                    "rhoI": 1e-4}}],
            "joints": [{"type": "pin", "body": "rod", "at": "O"}],
            "drives": [{"type": "rotation", "body": "rod", "at": "O", "law": law,
                        "name": "hub"}],
            "time": {"t_end": 0.01, "h": 0.001}}


def test_a_piecewise_motion_must_not_jump():
    """A drive's piecewise law whose value jumps at a break (0 then 1 rad at t = 0.5 s) is a
    ModelError naming the drive, the break and both values; a rate jump (0 then 2 rad/s,
    the value continuous) is a warning; the spin-up law (continuous in value and rate) is
    accepted without either."""
    import warnings
    jump = {"type": "piecewise", "segments": [
        {"until": 0.5, "law": {"type": "constant", "value": 0.0}},
        {"law": {"type": "polynomial", "coefficients": [1.0]}}]}
    with pytest.raises(ModelError, match="hub: the piecewise law jumps at until = 0.5 s "
                                         "from 0 \\(segment 1\\) to 1 \\(segment 2\\)"):
        Mechanism(Description.model_validate(_hub(jump)))
    kink = {"type": "piecewise", "segments": [
        {"until": 0.5, "law": {"type": "constant", "value": 0.0}},
        {"law": {"type": "polynomial", "coefficients": [-1.0, 2.0]}}]}
    with pytest.warns(UserWarning, match="rate jumps at until = 0.5 s from 0 to 2"):
        Mechanism(Description.model_validate(_hub(kink)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Mechanism(Description.model_validate(_hub(_spin_up_case_law(4.0, 15.0))))


def test_a_sum_motion_must_not_jump():
    """A drive's sum of laws whose piecewise term jumps (0 then 1 rad at t = 0.5 s, plus a
    harmonic, 0 there) jumps too: a ModelError naming the drive, the break and both values
    (the harmonic's sin(pi) is 0 to rounding); two piecewise terms whose jumps cancel (+1 and -1 rad at the same break)
    make a continuous motion, accepted."""
    step_up = {"type": "piecewise", "segments": [
        {"until": 0.5, "law": {"type": "constant", "value": 0.0}},
        {"law": {"type": "polynomial", "coefficients": [1.0]}}]}
    step_down = {"type": "piecewise", "segments": [
        {"until": 0.5, "law": {"type": "constant", "value": 0.0}},
        {"law": {"type": "polynomial", "coefficients": [-1.0]}}]}
    wave = {"type": "harmonic", "amplitude": 0.1, "frequency_hz": 1.0}
    with pytest.raises(ModelError, match="hub: the sum of laws jumps at t = 0.5 s from "
                                         r"\S+e-1\d to 1 \(a piecewise term's break\)"):
        Mechanism(Description.model_validate(_hub({"type": "sum", "laws": [step_up, wave]})))
    Mechanism(Description.model_validate(_hub({"type": "sum",
                                               "laws": [step_up, step_down, wave]})))
