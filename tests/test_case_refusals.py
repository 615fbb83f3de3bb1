"""Bad case values and output paths refused before any run, each by one error naming the input.

A case is read with `flexmbs.model.casefile.read_description` (validation by pydantic and
`Description.check_references`); what it refuses is a CaseError naming the file, the key and
what to give (docs/case-format.md). The animate command checks its output paths before the
simulation (`flexmbs.visual.export.frame_folder`).
"""
from __future__ import annotations

import os
import tomllib
from pathlib import Path

import pytest

from flexmbs.cli.main import main
from flexmbs.errors import CaseError, ModelError
from flexmbs.model.casefile import read_description

CASES = Path(__file__).resolve().parents[1] / "cases"


def _write(tmp_path, case, edit):
    """The shipped case `case` changed by `edit(dict)`, written as TOML; its path."""
    from test_casefile_fuzz import to_toml
    data = tomllib.loads((CASES / f"{case}.toml").read_text(encoding="utf-8"))
    edit(data)
    path = tmp_path / f"{case}_edited.toml"
    path.write_text(to_toml(data), encoding="utf-8")
    return path


def _given_without_rhoI(d):
    d["bodies"][0]["section"] = {"shape": "given", "EA": 1e8, "EI": 1e3, "rhoA": 5.0}
    del d["bodies"][0]["material"]
    del d["design"][0]


def _given_rhoI_zero(d):
    _given_without_rhoI(d)
    d["bodies"][0]["section"]["rhoI"] = 0.0


def _long_stroke(d):
    d["paths"][0]["x"]["stroke"] = 5e99


def _long_polynomial(d):
    d["paths"][0]["y"] = {"type": "polynomial", "coefficients": [0.0, 0.0, 1e308, 0.0, 1e308]}


def _tiny_axis(d):
    d["joints"][3]["axis"] = [1e-300, 0.0]


def _huge_axis(d):
    d["joints"][3]["axis"] = [1e300, 1e300]


def _free_point_mass(d):
    d["bodies"][3] = {"name": "mass_A", "type": "mass", "at": "A", "mass": 5.0}
    d["joints"].append({"type": "hinge", "bodies": ["crank", "mass_A"], "at": "A"})


def _nothing_holds(d):
    del d["joints"], d["drives"]


@pytest.mark.parametrize("case, edit, words", [
    ("fourbar", _given_without_rhoI, ["bodies[0].section", "rhoI", "got none",
                                      "rhoA EI / EA (here 5e-05)"]),
    ("fourbar", _given_rhoI_zero, ["bodies[0].section", "rhoI", "got 0.0"]),
    # the bound of a cycloid over t_end <= 1 s: stroke (1 s / period + 1) = 5e99 x 3; the
    # robot's points span a box of 0.5196 m x 0.5196 m: diagonal 0.735 m
    ("robot_2dof", _long_stroke, ["path 1: x", "1.5e+100 m", "0.735 m"]),
    ("robot_2dof", _long_polynomial, ["path 1: y", "inf m"]),
    ("slider_crank_press", _tiny_axis, ["joints[3]", "axis = [1e-300, 0.0]", "length 1e-300"]),
    ("slider_crank_press", _huge_axis, ["joints[3]", "axis = [1e+300, 1e+300]"]),
    ("fourbar", _free_point_mass, ["body 'mass_A'", "inertia = 0", "give inertia > 0"]),
    ("fourbar", _nothing_holds, ["no [[joints]], no [[drives]]", "give [[joints]]"]),
])
def test_bad_case_value_is_one_case_error(tmp_path, case, edit, words):
    """Each value makes a run fail (a given section without rhoI and a point mass of its own
    without inertia under a hinge: a coordinate without mass; a path stroke of 5e99 m: an
    overflow of the rigid reference's substeps; a slider axis of length 1e-300: a squared
    length that underflows; a case with no joints and no drives: no constraint equations); reading the file is a CaseError naming the file, the key and the
    value given."""
    path = _write(tmp_path, case, edit)
    with pytest.raises(CaseError) as err:
        read_description(path)
    msg = str(err.value)
    assert str(path) in msg
    for w in words:
        assert w in msg, (w, msg)
    assert "\n" not in msg.strip()


@pytest.mark.parametrize("target", ["/dev/zero", "/dev/null"])
def test_case_linked_to_a_device_is_named_so(tmp_path, target):
    """A case path that is a symbolic link to a character device is refused as 'a character
    device, not a regular file' (files.file_kind), not as 'not found'."""
    link = tmp_path / "x.toml"
    link.symlink_to(target)
    with pytest.raises(CaseError, match=r"x\.toml.*is a character device, not a regular file"):
        read_description(link)


def test_case_that_is_a_broken_link_is_named_so(tmp_path):
    """A case path that is a symbolic link to nothing names the link's target."""
    link = tmp_path / "x.toml"
    link.symlink_to(tmp_path / "gone.toml")
    with pytest.raises(CaseError, match=r"x\.toml.*is a link to .*gone\.toml.*does not exist"):
        read_description(link)


def test_pvd_frame_folder_that_is_a_link_is_refused_before_the_run(tmp_path, monkeypatch,
                                                                   capsys):
    """`flexmbs animate ... --out m.pvd` where m/ is a symbolic link to a folder: one error
    line naming the link, before any simulation (the frames replace the folder at the end of
    the run, which a link cannot take); the link and its target are left as they were."""
    from flexmbs.problem import Problem

    def forbidden(self, *a, **k):
        raise AssertionError("simulation started although --out was bad")
    monkeypatch.setattr(Problem, "evaluate", forbidden)
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "keep.txt").write_text("x")
    (tmp_path / "m").symlink_to(target)
    assert main(["animate", "fourbar", "--out", str(tmp_path / "m.pvd")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "symbolic link" in err[0] and "m'" in err[0], err
    assert (tmp_path / "m").is_symlink() and (target / "keep.txt").exists()


def test_frame_folder_refuses_a_link_in_python(tmp_path):
    """flexmbs.visual.export.frame_folder: a frame folder that is a link (even to nothing) is
    a ModelError naming it."""
    from flexmbs.visual.export import frame_folder
    (tmp_path / "m").symlink_to(tmp_path / "nowhere")
    with pytest.raises(ModelError, match="symbolic link"):
        frame_folder(tmp_path / "m.pvd")
