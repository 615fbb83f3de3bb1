"""README.md, the front page, is run and checked against its sources: its case file, shell
commands and Python block are executed in document order in a temporary folder (the runner of
tests/test_tutorial.py), the results are checked against closed forms, and the measured
numbers it quotes are those of the committed report and benchmark records it names."""
from __future__ import annotations

import math
import pathlib
import re

import pytest

from test_tutorial import run_tutorial

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


@pytest.fixture(scope="module")
def front(tmp_path_factory):
    folder = tmp_path_factory.mktemp("readme")
    ran, namespace, written = run_tutorial(folder, README.read_text(encoding="utf-8"))
    return dict(folder=folder, ran=ran, ns=namespace, written=written)


def _tube_mass(d):
    """Mass (kg) of the README's arm: an aluminium tube (rho 2700 kg/m^3), outer diameter d (m),
    wall 0.1 d, 0.6 m long: rho pi/4 (d^2 - (0.8 d)^2) L."""
    return 2700.0 * math.pi / 4 * (d ** 2 - (0.8 * d) ** 2) * 0.6


def test_every_command_runs(front):
    """The README's case file is written, and each of its commands (evaluate, optimize,
    animate) exits with status 0 and writes what it names (the film arm.gif)."""
    assert front["written"] == 1
    assert [r["argv"][0] for r in front["ran"]] == ["evaluate", "optimize", "animate"]
    for r in front["ran"]:
        assert r["status"] == 0, (r["line"], r["stderr"])
    assert (front["folder"] / "arm.gif").stat().st_size > 0


def test_python_block_against_closed_forms(front):
    """The Python block's evaluation at d = 40 mm gives the tube's mass of the closed form
    rho pi/4 (d^2 - (0.8 d)^2) L to round-off; its optimum is feasible, on its 1 mm tip-error
    limit (the mass grows with d, so the lightest feasible tube meets the limit: within 1e-3
    of it) and has the closed-form mass of its own diameter."""
    ev, opt = front["ns"]["ev"], front["ns"]["opt"]
    assert ev.values["mass"] == pytest.approx(_tube_mass(0.040), rel=1e-12)
    assert opt.feasible
    d = float(opt.design[0]) * 1e-3
    assert opt.objective == pytest.approx(_tube_mass(d), rel=1e-12)
    final = front["ns"]["prob"].evaluate(opt.design, gradient=False)
    assert final.values["tip_error"].max() == pytest.approx(1.0e-3, rel=1e-3)


def test_optimum_stated_in_the_comment(front):
    """The optimum the Python block's comment states (d in mm, mass in kg, tip error in mm)
    is the one the block computes, to the digits written."""
    text = README.read_text(encoding="utf-8")
    m = re.search(r"# d = ([\d.]+) mm, ([\d.]+) kg, tip error ([\d.]+) mm", text)
    assert m, "the comment of optimize_fully's line in the README's Python block"
    d, mass, err = m.groups()
    opt = front["ns"]["opt"]
    final = front["ns"]["prob"].evaluate(opt.design, gradient=False)
    assert f"{float(opt.design[0]):.{len(d.split('.')[1])}f}" == d
    assert f"{opt.objective:.{len(mass.split('.')[1])}f}" == mass
    assert f"{final.values['tip_error'].max() * 1e3:.{len(err.split('.')[1])}f}" == err


def test_table_1_is_the_committed_report():
    """Each flexmbs row of the README's Table 1 (mass and p1..p4) is the row of Table 1 in the
    committed report docs/reproduction/README.md (its bold numbers), and the count of
    reproduced findings is the report's summary."""
    text = README.read_text(encoding="utf-8")
    report = (ROOT / "docs" / "reproduction" / "README.md").read_text(encoding="utf-8")
    table1 = report[report.index("## Table 1"):report.index("## Table 2")]
    ours = [re.findall(r"[\d.]+", line.split("flexmbs |")[1])
            for line in text.splitlines() if line.startswith("| | | flexmbs |")]
    theirs = [re.findall(r"\*\*([\d.]+)\*\*", line)
              for line in table1.splitlines() if "**flexmbs**" in line]
    assert len(ours) == 2 and ours == theirs
    found = re.search(r"(\d+) of its (\d+)\s+checked findings reproduced", text)
    assert found and f"Summary: {found[1]} of {found[2]} findings reproduced" in report


def test_exudyn_ratios_are_the_benchmark_record():
    """The Exudyn / flexmbs ratios the README quotes at h = 5e-4 s (commit f1ff418) are those
    of benchmarks/README.md, and its ranges over the meshes and steps (commit 5f47ea6) are the
    smallest and largest ratios of that record's table, its default rows and its reuse rows."""
    text = " ".join(README.read_text(encoding="utf-8").split())
    bench = (ROOT / "benchmarks" / "README.md").read_text(encoding="utf-8")
    quoted = re.search(r"Exudyn takes ([\d.]+), ([\d.]+), ([\d.]+) and ([\d.]+) times", text)
    assert quoted and "default " + ", ".join(quoted.groups()) in " ".join(bench.split())
    rows = [line for line in bench[bench.index("| el/arm | config  | h = 4e-3"):].splitlines()
            if re.match(r"\| \d+", line)][:8]
    for config in ("default", "reuse"):
        ratios = [float(c) for line in rows if line.split("|")[2].strip() == config
                  for c in line.split("|")[3:9]]
        assert len(ratios) == 24
        said = re.search(r"([\d.]+) to ([\d.]+) (?:times )?with " + ("the defaults" if config
                         == "default" else '`newton="reuse"`'), text)
        assert said and (float(said[1]), float(said[2])) == (min(ratios), max(ratios)), config
