"""What a case or study file may make flexmbs write or print: no option from a file names a
file to write, every path derived from a study stays in the output folder, and text from a
file reaches the terminal with its control characters escaped.
"""
import json
from pathlib import Path

import pytest

from flexmbs.cli.common import printable
from flexmbs.cli.main import main
from flexmbs.errors import CaseError
from flexmbs.paper.study import load_study

CASES = Path(__file__).resolve().parents[1] / "cases"


def _study(tmp_path, table_extra="", extra=""):
    (tmp_path / "published.json").write_text(json.dumps({"a": {"b": {}}}))
    f = tmp_path / "study.toml"
    f.write_text(f'''{extra}
[study]
name = "mine"
published = "published.json"

[tables.1]
title = "t"
case = "robot_2dof"
published = ["a", "b"]
starts = [[50.0, 50.0, 50.0, 50.0]]
{table_extra}
''')
    return f


@pytest.mark.parametrize("table_extra, extra, key", [
    ("", '[options]\nweakly = { history = "/tmp/x.jsonl" }\n', "options.weakly.history"),
    ('options = { fully = { history = "h.jsonl" } }', "", "tables.1.options.fully.history"),
    ('options = { weakly = { resume = true } }', "", "tables.1.options.weakly.resume"),
])
def test_study_options_may_not_name_a_file(tmp_path, table_extra, extra, key):
    """`history` (a file the run would overwrite) or `resume` in a study's [options] or a
    table's options: CaseError naming the key (the study is refused before any run)."""
    f = _study(tmp_path, table_extra, extra)
    with pytest.raises(CaseError, match=rf"key '{key}': a study's runs are stored by"):
        load_study(f)


@pytest.mark.parametrize("key", ['"../../../x"', '"/abs/x"', '"a.b"'])
def test_map_key_is_a_plain_name(tmp_path, key):
    """A map key naming a path ('../../../x', '/abs/x', or with a dot) is refused: its results
    would go to OUT/jobs/KEY, outside the output folder."""
    f = _study(tmp_path, extra="", table_extra=(
        f'\n[maps.{key}]\nfigure = 1\ntable = 1\nstep = 2\naxes = ["p2", "p4"]\n'
        'zoom = [[20, 30], [20, 30]]\n'))
    with pytest.raises(CaseError, match="a map's key names its folder of results: letters"):
        load_study(f)


def test_case_description_is_printed_escaped(tmp_path, capsys):
    """A case whose description holds ESC [2J (clear screen) and a bell: `flexmbs simulate`
    prints them escaped (\\x1b[2J, \\x07), no control character reaches stdout."""
    d = (CASES / "robot_2dof.toml").read_text()
    d = d.replace('description = "2-dof robot, tip along a straight line, deviation (28)"',
                  'description = "evil \\u001b[2J\\u0007 text"')
    assert "\\u001b" in d
    f = tmp_path / "evil.toml"
    f.write_text(d)
    assert main(["simulate", str(f), "--t-end", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "evil \\x1b[2J\\x07 text" in out
    assert not any(ord(c) < 32 and c != "\n" for c in out)


def test_printable_keeps_text_and_escapes_controls():
    """printable: plain and accented text unchanged; ESC, BEL, a bidi override escaped;
    newlines kept only when asked."""
    assert printable("Brüls, 0.65 s") == "Brüls, 0.65 s"
    assert printable("a\x1b[31mb\x07\u202e") == "a\\x1b[31mb\\x07\\u202e"
    assert printable("a\nb") == "a\\nb" and printable("a\nb", True) == "a\nb"
