"""Study files (docs/study-format.md): the paper's study as data, a user's study through
`flexmbs reproduce --study`, and the validation of a study file (CaseError naming the file and
the key).

The user study reuses stored optimization results of docs/reproduction/jobs (the committed
reproduction of the paper's Table 1, robot_2dof at 0.65 s from [50, 50, 50, 50] mm), so no
optimization runs; its published numbers are written by the test: the paper's Table 1 (0.962 kg
for both methods, Tromme, Brüls & Duysinx) and, as a regression that must fail, a mass 20 %
above it.
"""
import json
import shutil
from pathlib import Path

import pytest

from flexmbs.cli import main
from flexmbs.errors import CaseError
from flexmbs.study import load_study

ROOT = Path(__file__).resolve().parents[1]
STORE = ROOT / "docs" / "reproduction" / "jobs" / "optimizations"


def test_shipped_study_runs_are_the_stored_reproduction():
    """The paper's study (cases/studies/paper.toml) asks for exactly the 24 optimizations whose
    results docs/reproduction/jobs/optimizations holds (the committed reproduction of
    Tables 1-8), so that its report is re-rendered from them without running any."""
    study = load_study()
    names = {r.name for t in study.tables.values() for r in t.runs()}
    stored = {p.stem for p in STORE.glob("*.json")}
    assert len(stored) == 24
    assert names == stored


def _user_study(tmp_path, mass, extra=""):
    (tmp_path / "published.json").write_text(json.dumps({"mine": {"t1": {
        "weakly": {"mass": mass, "iter": None, "inner_iter": None, "p": None},
        "fully": {"mass": mass, "iter": None, "inner_iter": None, "p": None}}}}))
    f = tmp_path / "study.toml"
    f.write_text(f'''
[study]
name = "mine"
published = "published.json"

[tables.1]
title = "my regression"
case = "robot_2dof"
overrides = {{ "time.t_end" = 0.65 }}
published = ["mine", "t1"]
starts = [[50.0, 50.0, 50.0, 50.0]]
checks = [{{ type = "mass_within", rel = 0.01 }}]
{extra}''')
    return f


@pytest.mark.parametrize("mass, verdict, status", [(0.962, "yes", 0), (0.962 * 1.2, "**no**", 0)])
def test_user_study_checks_against_its_published_numbers(tmp_path, capsys, mass, verdict, status):
    """`flexmbs reproduce --study FILE`: a user's study compares stored runs with the numbers of
    its own published file. Against the paper's Table 1 mass (0.962 kg; flexmbs 0.9586 and
    0.9584 kg in docs/reproduction, -0.4 %) the 1 % check is reproduced for both methods;
    against a mass 20 % higher it is not (and the report says so)."""
    out = tmp_path / "out"
    (out / "jobs").mkdir(parents=True)
    shutil.copytree(STORE, out / "jobs" / "optimizations")
    f = _user_study(tmp_path, mass)
    assert main(["reproduce", "--study", str(f), "--out", str(out), "--workers", "1",
                 "--no-figures"]) == status
    readme = (out / "README.md").read_text()
    assert readme.startswith("# flexmbs reproduction of mine, Table 1")
    rows = [ln for ln in readme.splitlines()
            if ln.startswith("| ") and "converged, mass within 1 %" in ln]
    assert len(rows) == 2 and all(ln.endswith(f"| {verdict} |") for ln in rows)
    data = json.loads((out / "comparison.json").read_text())
    assert [c["ok"] for c in data["checks"]] == [verdict == "yes"] * 2
    assert data["settings"]["stored_runs"]           # nothing optimized again


@pytest.mark.parametrize("extra, text", [
    ('[maps.m]\nfigure = 1\ntable = 1\nstep = 2\naxes = ["p2", "p9"]\nzoom = [[1, 2], [1, 2]]',
     "key 'maps.m': 'p9' is not a design variable of table 1's case (p1, p2, p3, p4)"),
    ('[maps.m]\nfigure = 1\ntable = 3\nstep = 2\naxes = ["p2", "p4"]\nzoom = [[1, 2], [1, 2]]',
     "key 'maps.m.table': no table 3 (tables: 1)"),
    ('[[figures]]\nkey = "f"\nnumber = 1\nkind = "two_methods"\ntable = 1\nwaht = "x"',
     "key 'figures[0].waht' is not a known key (see docs/study-format.md), got 'x'; allowed in "
     "[figures[0]]: key, number, kind, table, what"),
    ('[options]\nweakly = { max_cylces = 3 }',
     "key 'options.weakly.max_cylces' is not an option of the weakly coupled optimizer"),
], ids=["variable", "table", "unknown key", "option"])
def test_bad_study_names_file_and_key(tmp_path, extra, text):
    """A study file with a design variable, a table or an optimizer option that does not
    exist, or an unknown key, is a CaseError naming the file and the key (and the allowed
    values or keys)."""
    f = _user_study(tmp_path, 1.0, extra)
    with pytest.raises(CaseError) as err:
        load_study(f)
    assert text in str(err.value) and str(f) in str(err.value)


def test_bad_check_and_start(tmp_path):
    """A check of an unknown type lists the types; a start with the wrong number of values
    names the table's key and the case's variables (CaseError naming the file)."""
    f = _user_study(tmp_path, 1.0)
    f.write_text(f.read_text().replace('type = "mass_within"', 'type = "mass_whithin"'))
    with pytest.raises(CaseError, match=r"tables\.1\.checks\[0\].*'mass_within'"):
        load_study(f)
    f = _user_study(tmp_path, 1.0)
    f.write_text(f.read_text().replace("[[50.0, 50.0, 50.0, 50.0]]", "[[50.0, 50.0]]"))
    with pytest.raises(CaseError, match=r"key 'tables\.1\.starts\[0\]' must have 4 values "
                                        r"\(p1, p2, p3, p4\), got \[50\.0, 50\.0\]"):
        load_study(f)


def test_reproduce_unknown_table_of_study(tmp_path, capsys):
    """`--table 9` of a study without table 9: exit status 2, one line naming the study's
    tables."""
    f = _user_study(tmp_path, 1.0)
    assert main(["reproduce", "--study", str(f), "--table", "9", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--table must be among the study's tables 1" in err and "got 9" in err
