"""Case values that used to be read as something else: a sampled law beyond its table, a
boolean where a number is expected, a relative drive's constant law, overflowing or empty
inputs. Each is refused with an error naming the input, or done as the case says.
"""
import tomllib
from pathlib import Path

import numpy as np
import pytest

from flexmbs.errors import CaseError, ModelError
from flexmbs.model.casefile import description_from_dict
from flexmbs.model.laws import TimeLaw
from flexmbs.problem import Problem

CASES = Path(__file__).resolve().parents[1] / "cases"


def _robot(t_end=0.3):
    d = tomllib.loads((CASES / "robot_2dof.toml").read_text())
    d["time"]["t_end"] = t_end
    return d


def _with_sampled_load(extrapolate=None, t_end=0.3):
    d = _robot(t_end)
    law = {"type": "samples", "times": [0.0, 0.1], "values": [0.0, 1.0],
           "interpolation": "pchip"}
    if extrapolate is not None:
        law["extrapolate"] = extrapolate
    d["loads"] = [{"body": "arm2", "at": "tip", "fy": -10.0, "law": law}]
    return d


# ----------------------------------------------------------------------------- sampled laws
def test_sampled_law_beyond_its_table_is_an_error():
    """A load through samples at t = 0 and 0.1 s on a 0.3 s run: ModelError naming the load,
    a time past 0.1 s and the 'extrapolate' key (the law used to grow on linearly)."""
    with pytest.raises(ModelError, match=r"load 1.*outside its samples' times \(0 to 0\.1 s\)"
                                         r".*extrapolate"):
        Problem(_with_sampled_load()).evaluate(gradient=False)


def test_sampled_law_within_its_table_runs():
    """The same load on a 0.1 s run (the table's span) is not refused."""
    Problem(_with_sampled_load(t_end=0.1)).evaluate(gradient=False)


def test_hold_and_linear_extrapolation_are_exact():
    """extrapolate='hold': beyond the last sample the value is the last sample's, rate and
    acceleration 0; 'linear': value y_end + y'(t_end) (t - t_end), rate y'(t_end), acceleration
    0. Checked at t = 0.2 and 0.3 s on samples of y = t^2 at 0, 0.05, 0.1 s (cubic spline:
    exact for a quadratic, so y(0.1) = 0.01, y'(0.1) = 0.2)."""
    t = [0.0, 0.05, 0.1]
    y = [0.0, 0.0025, 0.01]
    hold = TimeLaw.samples(t, y, extrapolate="hold")
    v, r, a = hold.evaluate(np.array([0.2, 0.3]))
    np.testing.assert_allclose(v, 0.01, rtol=1e-12)
    np.testing.assert_array_equal(r, 0.0)
    np.testing.assert_array_equal(a, 0.0)
    lin = TimeLaw.samples(t, y, extrapolate="linear")
    v, r, a = lin.evaluate(np.array([0.2, 0.3]))
    np.testing.assert_allclose(v, [0.01 + 0.2 * 0.1, 0.01 + 0.2 * 0.2], rtol=1e-12)
    np.testing.assert_allclose(r, 0.2, rtol=1e-12)
    np.testing.assert_array_equal(a, 0.0)


def test_extrapolate_in_a_case_file():
    """extrapolate = 'hold' in a case runs the 0.3 s simulation; a bad value or extrapolate on
    another law type is a CaseError naming the key."""
    Problem(_with_sampled_load("hold")).evaluate(gradient=False)
    with pytest.raises(CaseError, match="extrapolate"):
        description_from_dict(_with_sampled_load("forever"))
    d = _robot()
    d["loads"] = [{"body": "arm2", "at": "tip", "fy": -1.0,
                   "law": {"type": "constant", "value": 1.0, "extrapolate": "hold"}}]
    with pytest.raises(CaseError, match="extrapolate applies to a 'samples' law"):
        description_from_dict(d)


# ----------------------------------------------------------------------------- booleans
def _set(d, path, value):
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return d


@pytest.mark.parametrize("path, key", [
    (("bodies", 2, "mass"), "bodies.2.point_mass.mass"),
    (("time", "t_end"), "time.t_end"),
    (("bodies", 0, "elements"), "bodies.0.beam.elements"),
    (("bodies", 0, "order"), "bodies.0.beam.order"),
    (("materials", "aluminium", "nu"), "materials.aluminium.nu"),
    (("points", "A"), "points.A"),
])
def test_a_boolean_is_not_a_number(path, key):
    """`true` where a case expects a number (a mass, t_end, a count of elements, the element
    order, Poisson's ratio, a point's coordinate) is a CaseError naming the key and saying it
    got a boolean (pydantic read it as 1: 1 kg, 1 s, 1 element)."""
    value = [True, 0.0] if path == ("points", "A") else True
    d = _set(_robot(), path, value)
    with pytest.raises(CaseError) as err:
        description_from_dict(d)
    msg = str(err.value)
    assert key.split(".")[0] in msg and path[-1] in msg and "must be a number, not a boolean, got True" in msg, msg


def test_a_boolean_is_not_a_number_in_a_study(tmp_path):
    """A study's multi-start `starts = true` is a CaseError naming the key and the boolean."""
    from flexmbs.paper.study import load_study
    f = tmp_path / "s.toml"
    f.write_text('[study]\nname = "s"\npublished = "p.json"\n[tables.1]\ntitle = "t"\n'
                 'case = "robot_2dof"\npublished = ["a", "b"]\n'
                 'starts = [[50.0, 50.0, 50.0, 50.0]]\n'
                 '[[tables.1.variants]]\nkey = "m"\nlabel = "m"\nmethod = "fully"\n'
                 'multistart = { starts = true }\n')
    with pytest.raises(CaseError, match=r"multistart\.starts' must be a number, not a boolean"):
        load_study(f)


# ----------------------------------------------------------------------------- drives
def _constant_drive(value, absolute=False, kind="rotation"):
    d = _robot(0.05)
    law = {"type": "constant", "value": value}
    if absolute:
        law["absolute"] = True
    drive = {"type": kind, "body": "arm1", "at": "O", "law": law}
    if kind == "translation":
        drive["axis"] = [1.0, 0.0]
    d["drives"][0] = drive
    return d


@pytest.mark.parametrize("kind", ["rotation", "translation"])
def test_constant_law_on_a_relative_drive_is_refused(kind):
    """A drive measured from the initial configuration with a constant law of value 0.5 (the
    law's value at t = 0 is subtracted: no motion at all) is a CaseError naming the drive's
    law, the value and the way out; value 0 (hold) and, for a rotation, absolute = true (the
    angle itself) are accepted."""
    with pytest.raises(CaseError, match=r"drives\[0\].*constant law \(value = 0\.5\) cannot move "
                                        r"this drive.*subtracted"):
        description_from_dict(_constant_drive(0.5, kind=kind))
    description_from_dict(_constant_drive(0.0, kind=kind))
    if kind == "rotation":
        description_from_dict(_constant_drive(0.5, absolute=True))


# ----------------------------------------------------------------------------- limits
@pytest.mark.parametrize("args", [["simulate", "robot_2dof", "--t-end", "1e308"],
                                  ["simulate", "robot_2dof", "--set", "time.t_end=1e308"],
                                  ["optimize", "robot_2dof", "--t-end", "1e308"]])
def test_overflowing_t_end_is_a_case_error(args, capsys):
    """t_end = 1e308 s (1e308 / 5e-4: an infinite number of steps) from --t-end, --set or a
    case: exit 2 and a CaseError naming time.t_end, time.h and the core's step limit (it was
    an OverflowError)."""
    from flexmbs.cli.main import main
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "CaseError: time.t_end = 1e+308 s with time.h = 0.0005 s" in err
    assert "more than the core's 2147483646" in err
    with pytest.raises(CaseError, match="time.t_end = 1e"):
        Problem(_robot(1e308))


def test_empty_polynomial_is_a_case_error():
    """law = {type = "polynomial", coefficients = []}: a CaseError naming the key (it was an
    IndexError building the law)."""
    d = _robot()
    d["loads"] = [{"body": "arm2", "at": "tip", "fy": -1.0,
                   "law": {"type": "polynomial", "coefficients": []}}]
    with pytest.raises(CaseError, match=r"loads\[0\]\.law\.coefficients"):
        description_from_dict(d)


@pytest.mark.parametrize("study, text", [
    ("{tmp}/missing/s.toml", "study '{tmp}/missing/s.toml' not found: give a path to a .toml "
                             "file or one of the shipped studies: paper"),
    ("{tmp}", "study '{tmp}' is a folder, not a file"),
])
def test_reproduce_with_a_missing_study_or_a_folder(tmp_path, capsys, study, text):
    """`reproduce --study` of a missing file or of a folder: exit 2 and a CaseError naming it
    (the missing one lists the shipped studies; it was an AttributeError), nothing written."""
    from flexmbs.cli.main import main
    out = tmp_path / "out"
    assert main(["reproduce", "--study", study.format(tmp=tmp_path), "--out", str(out)]) == 2
    assert text.format(tmp=tmp_path) in capsys.readouterr().err
    assert not out.exists()
