"""What the command line prints: `flexmbs --version`, the citation file, the verdicts of
`optimize` (one meaning each, docs/json-output.md "What `optimize` reports"), the verified step
and the command that re-checks it, and the units of the printed numbers."""
import json
import re
import shlex
from pathlib import Path

import pytest

import flexmbs
from flexmbs.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- version, citation
def test_version_prints_the_package_version(capsys):
    """`flexmbs --version` prints "flexmbs X.Y.Z" with flexmbs.__version__
    (python/flexmbs/version.py) and exits with status 0."""
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"flexmbs {flexmbs.__version__}"


def test_citation_file_has_the_required_cff_keys():
    """CITATION.cff parses as YAML and has the keys Citation File Format 1.2.0 requires
    (cff-version, message, title, authors), the package's version, and the paper as
    preferred-citation: its title and authors as the paper states them (Tromme, Brüls,
    Duysinx) and its DOI."""
    yaml = pytest.importorskip("yaml")
    d = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert d["cff-version"] == "1.2.0"
    for key in ("message", "title", "authors"):
        assert d[key]
    assert str(d["version"]) == flexmbs.__version__
    paper = d["preferred-citation"]
    assert paper["type"] == "article"
    assert paper["title"] == ("Weakly and fully coupled methods for structural optimization "
                              "of flexible mechanisms")
    assert [a["family-names"] for a in paper["authors"]] == ["Tromme", "Brüls", "Duysinx"]
    assert paper["doi"].startswith("10.1007/s11044-")
    assert (paper["journal"], paper["volume"], paper["year"]) == (
        "Multibody System Dynamics", 38, 2016)


# ----------------------------------------------------------------------------- optimize verdicts
def _run_json(capsys, args):
    status = main(args + ["--json"])
    out, err = capsys.readouterr()
    assert out.strip(), err
    return status, json.loads(out)


def _violation_words_name_their_iterate(reason, feasible, tol):
    """A reason may quote the constraint violation of the last iterate; when it quotes one
    above the tolerance for a feasible design, it names it as the last iterate's."""
    for m in re.finditer(r"constraint violation (\S+?)[,)\s]", reason):
        value = float(m.group(1))
        if feasible and value > tol:
            assert "last iterate's" in reason[max(0, m.start() - 40):m.start() + 20], reason


def _check_verdicts(d):
    """The invariants of docs/json-output.md ("What `optimize` reports")."""
    tol = d["feasibility_tol"]
    assert d["max_violation"] >= 0.0
    assert d["feasible"] == (d["max_violation"] <= tol)
    v = d["verification"]
    assert d["verified"] == (None if v is None else v["verified"])
    assert d["verified_h"] == (None if v is None else v["h"])
    _violation_words_name_their_iterate(d["reason"], d["feasible"], tol)


def _recheck(capsys, d):
    """The printed check command, run: it simulates the design at the verified step, whose
    largest g is the verification's (the same simulation: to 1e-9 relative)."""
    words = shlex.split(d["check_command"])
    assert words[:2] == ["flexmbs", "simulate"]
    assert f"time.h={d['verified_h']!r}" in words
    status, ev = _run_json(capsys, words[1:])
    assert status == 0
    assert ev["design"] == pytest.approx(d["design"], rel=1e-15)
    assert ev["resolution"]["h"] == pytest.approx(d["verified_h"], rel=1e-12)
    assert ev["max_violation"] == pytest.approx(d["verification"]["max_violation"], rel=1e-9)


def test_single_run_verdicts_are_consistent(capsys):
    """`flexmbs optimize robot_2dof --method fully --json`: feasible == (max_violation <=
    feasibility_tol), converged implies feasible (the fully coupled stopping test asks it),
    verified and verified_h are the verification's, h is the case's step (5e-4 s,
    cases/robot_2dof.toml), the exit status is 0 exactly when converged, and the printed
    check command reproduces the verified step's largest g."""
    status, d = _run_json(capsys, ["optimize", "robot_2dof", "--method", "fully"])
    _check_verdicts(d)
    assert status == (0 if d["converged"] else 1)
    assert not d["converged"] or d["feasible"]
    assert d["h"] == 5e-4 and d["objective_unit"] == "kg"
    assert d["verified"] is True and d["verified_h"] < d["h"]
    _recheck(capsys, d)


def test_multistart_verdicts_are_the_best_start_s(capsys):
    """`flexmbs optimize fourbar --method fully --starts 2 --max-iterations 6 --json` (one
    start ends feasible at its iteration cap, the other infeasible): the top-level design,
    objective, max_violation, feasible, converged, reason, verified, verified_h and h are the
    best start's; every start's feasible == (max_violation <= feasibility_tol); the best is
    not converged (its run stopped at the cap), so neither is the result, and the exit status
    is 1; the check command reproduces the verified step's largest g."""
    status, d = _run_json(capsys, ["optimize", "fourbar", "--method", "fully", "--starts", "2",
                                   "--max-iterations", "6", "--workers", "1"])
    best = d["best"]
    assert best is not None
    for key in ("design", "objective", "max_violation", "feasible", "converged", "reason", "h"):
        assert d[key] == best[key], key
    assert d["verification"] == best["verification"]
    _check_verdicts(d)
    for o in d["optima"]:
        assert o["feasible"] == (o["max_violation"] <= d["feasibility_tol"])
        _violation_words_name_their_iterate(o["reason"], o["feasible"], d["feasibility_tol"])
    assert "maximum number of iterations (6)" in best["reason"]
    assert d["converged"] is False and status == 1
    assert d["feasible"] is True and d["feasible_starts"] == 1
    _recheck(capsys, d)


# ----------------------------------------------------------------------------- units, hints
def test_optimize_summary_names_units_and_the_verified_step(capsys):
    """`flexmbs optimize robot_2dof --method fully` (cases/robot_2dof.toml: diameters in mm,
    objective the mass in kg, h = 5e-4 s): every progress line gives the design in mm and the
    objective in kg, the summary the objective in kg at h = 0.0005 s, the verification's ±
    relative to the limit, and after the verified step the command that re-checks it with
    that step as time.h."""
    assert main(["optimize", "robot_2dof", "--method", "fully"]) == 0
    out = capsys.readouterr().out.splitlines()
    its = [ln for ln in out if ln.startswith("iteration")]
    assert its and all(re.search(r"x = \[[^]]*\] mm  objective \S+ kg  ", ln) for ln in its)
    assert any(re.fullmatch(r"  objective mass = \S+ kg at h = 0\.0005 s", ln) for ln in out)
    ver = next(ln for ln in out if ln.startswith("  verified at h = "))
    assert "g and its error relative to the limit" in ver
    k = next(i for i, ln in enumerate(out) if ln.startswith("  re-check at the verified step"))
    h = re.search(r"h = (\S+) s", out[k]).group(1)
    assert float(h) == 0.0005 / 4
    assert out[k + 1].strip().startswith("flexmbs simulate robot_2dof --design=")
    assert out[k + 1].endswith(f"--set time.h={float(h)!r}")


def test_check_table_and_figure_title_carry_units(capsys):
    """`flexmbs check robot_2dof`: each row gives its value's unit (deviations in m); the
    overview figure's title (flexmbs.visual.plots.plot_overview) gives the objective in kg
    and the step of its feasibility verdict."""
    main(["check", "robot_2dof", "--set", "time.t_end=0.1"])
    rows = [ln.split() for ln in capsys.readouterr().out.splitlines()
            if ln.startswith("  deviation_")]
    assert rows and all(r[2] == "m" for r in rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from flexmbs.problem import Problem
    from flexmbs.visual.plots import plot_overview
    prob = Problem("robot_2dof", overrides={"time.t_end": 0.1})
    ev = prob.evaluate(prob.start, gradient=False, store="all")
    fig = plot_overview(prob, ev.result, ev)
    try:
        title = fig._suptitle.get_text()
    finally:
        plt.close(fig)
    assert re.search(r"mass \S+ kg, feasible at h = 0\.0005 s$", title), title


def test_simulate_of_an_infeasible_design_says_the_verdict_is_the_step_s(capsys):
    """`flexmbs simulate fourbar --design 54,15.3,16.3` (deviation 1.057 mm against the 1 mm
    limit at the case's h = 5e-4 s): the summary says INFEASIBLE, names deviation_A as the
    largest row, and adds a note that the verdict is the case's step's; with --error, whose
    estimate is not in its asymptotic range there, the note says the verdict may change at a
    finer step (the error estimate is no bound)."""
    main(["simulate", "fourbar", "--design", "54,15.3,16.3"])
    out = capsys.readouterr().out
    assert "INFEASIBLE: largest g = " in out and "deviation_A's" in out
    note = next(ln for ln in out.splitlines() if ln.startswith("  note"))
    assert "the verdict is at the case's h = 0.0005 s" in note
    main(["simulate", "fourbar", "--design", "54,15.3,16.3", "--error"])
    note = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("  note"))
    assert "may change at a finer step: deviation_A not in the asymptotic range" in note
