"""docs/tutorial.md is run: its fenced code blocks are executed in document order in a
temporary folder, and what it says of the results is checked.

Blocks that run (the rest, e.g. ```text outputs, are only read):

- ```toml file=NAME      writes the block to NAME;  ```toml file=NAME append  appends to it;
- ```sh                  every line is a `flexmbs ...` command, run through
                         flexmbs.cli.main.main in the folder; its exit status must be 0, or N
                         when the line ends with the comment `# exit status N`;
- ```python              exec'd, every python block in one namespace.

The checks below are the statements the tutorial makes (each could fail): the exit statuses,
the files and frame counts the commands write, the rod's mass and its gradient against the
closed form, the exact gradient of the ram's deviation against a central difference, and the
optimum being feasible (also at the verified step), lighter than the start and on the
deviation limit.
"""
from __future__ import annotations

import math
import os
import pathlib
import re
import shlex
import xml.etree.ElementTree as ET

import numpy as np
import pytest

DOC = pathlib.Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"

_FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.S | re.M)
_STATUS = re.compile(r"#\s*exit status (\d+)\s*$")


def blocks(text):
    """[(language, info words, body)] of the fenced code blocks of a markdown text."""
    out = []
    for m in _FENCE.finditer(text):
        words = m.group(1).split()
        out.append((words[0] if words else "", words[1:], m.group(2)))
    return out


def commands(body):
    """[(argv after 'flexmbs', expected exit status, line)] of a shell block."""
    out = []
    for line in body.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _STATUS.search(line)
        argv = shlex.split(line, comments=True)
        assert argv[0] == "flexmbs", f"a shell line of the tutorial that is not a flexmbs command: {line!r}"
        out.append((argv[1:], int(m.group(1)) if m else 0, line))
    return out


def run_tutorial(folder, text):
    """Run the blocks of `text` in `folder`; returns (commands run with their status and
    output, python namespace, number of toml files written)."""
    from flexmbs.cli.main import main
    import contextlib
    import io

    ran, namespace, written = [], {"__name__": "tutorial"}, 0
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        for lang, info, body in blocks(text):
            if lang == "toml":
                target = [w.split("=", 1)[1] for w in info if w.startswith("file=")]
                if not target:
                    continue
                with open(target[0], "a" if "append" in info else "w", encoding="utf-8") as f:
                    f.write(body)
                written += 1
            elif lang in ("sh", "shell", "console", "bash"):
                for argv, expected, line in commands(body):
                    stdout, stderr = io.StringIO(), io.StringIO()
                    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                        status = main(argv)
                    ran.append(dict(argv=argv, line=line, expected=expected, status=status,
                                    stdout=stdout.getvalue(), stderr=stderr.getvalue()))
            elif lang == "python":
                exec(compile(body, str(DOC), "exec"), namespace)
    finally:
        os.chdir(cwd)
    return ran, namespace, written


@pytest.fixture(scope="module")
def tutorial(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tutorial")
    ran, namespace, written = run_tutorial(folder, DOC.read_text(encoding="utf-8"))
    return dict(folder=folder, ran=ran, ns=namespace, written=written)


def _option(argv, name):
    return argv[argv.index(name) + 1] if name in argv else None


def test_every_step_runs(tutorial):
    """Every command of the tutorial exits with the status the tutorial states (0, or the
    1 of a convergence check that is not converged), and each step it describes is there:
    case files written, simulate, check, evaluate, optimize and animate run."""
    ran = tutorial["ran"]
    for r in ran:
        assert r["status"] == r["expected"], (r["line"], r["status"], r["stderr"])
    assert tutorial["written"] >= 4
    run = {r["argv"][0] for r in ran}
    assert {"simulate", "check", "evaluate", "optimize", "animate"} <= run


def test_check_verdicts(tutorial):
    """`flexmbs check` is not converged at h = 2 ms (the ram's deviation changes by about 4 %
    of its limit at h/2, above the 1 % asked) and converged at the case's 0.5 ms (0.25 %);
    its exit status says so (1 and 0)."""
    checks = [r for r in tutorial["ran"] if r["argv"][0] == "check"]
    assert [r["status"] for r in checks] == [1, 0]
    assert "NOT converged" in checks[0]["stdout"]
    assert "every response converged" in checks[1]["stdout"]


def test_animation_files(tutorial):
    """The GIF has the frame count asked with --frames; the ParaView series has one frame per
    time point, t_end / h + 1 = 0.1 / 5e-4 + 1 = 201 (the default: every step), each a .vtu
    file that exists; the Python export wrote the number of frames it was asked."""
    from PIL import Image

    folder = tutorial["folder"]
    films = [r for r in tutorial["ran"] if r["argv"][0] == "animate"
             and _option(r["argv"], "--out").endswith(".gif")]
    series = [r for r in tutorial["ran"] if r["argv"][0] == "animate"
              and _option(r["argv"], "--out").endswith(".pvd")]
    assert films and series
    for r in films:
        with Image.open(folder / _option(r["argv"], "--out")) as im:
            assert im.n_frames == int(_option(r["argv"], "--frames"))
    for r in series:
        pvd = folder / _option(r["argv"], "--out")
        sets = ET.parse(pvd).getroot().findall(".//DataSet")
        assert len(sets) == round(0.1 / 5e-4) + 1
        assert all((pvd.parent / s.get("file")).is_file() for s in sets)
    ns = tutorial["ns"]
    assert ns["anim"].frames == 20
    with Image.open(folder / ns["anim"].path) as im:
        assert im.n_frames == 20
    pvd, vtus, steps = ns["series"]
    assert len(vtus) == len(steps) == 11 and all((folder / v).is_file() for v in vtus)


def test_mass_and_its_gradient(tutorial):
    """The rod's mass is rho pi d^2 / 4 L (steel 7850 kg/m^3, d = 12 mm, L = |AB| =
    sqrt(0.2^2 + 0.05^2) m) and its gradient 2 m / d per mm, to rounding."""
    ev = tutorial["ns"]["ev"]
    length = math.hypot(0.2, 0.05)
    mass = 7850.0 * math.pi * 0.012**2 / 4 * length
    assert ev.values["rod_mass"] == pytest.approx(mass, rel=1e-12)
    assert ev.gradients["rod_mass"][0] == pytest.approx(2 * mass / 12.0, rel=1e-9)


def test_gradient_matches_central_difference(tutorial):
    """The exact (direct differentiation) gradient of the ram's deviation at its peak step
    equals the central difference the tutorial computes (step 0.01 mm: truncation about
    (0.01/12)^2 ~ 1e-6 relative; measured agreement 1.4e-6) to 1e-4."""
    ns = tutorial["ns"]
    assert ns["exact"] == pytest.approx(ns["central"], rel=1e-4)
    assert ns["exact"] < 0          # a thicker rod deviates less


def test_optimum(tutorial):
    """The fully coupled optimum is feasible (largest g <= FEASIBILITY_TOL) at the case's step
    and at the verified step, lighter than the start, and on the deviation limit: mass grows
    with d and the deviation falls with d, so the lightest feasible rod makes the deviation
    constraint active (g within the optimizer's active_tol 1e-3 of 0). The design the
    tutorial animates, the optimum rounded up to 0.1 mm, is feasible too."""
    import flexmbs

    ns = tutorial["ns"]
    opt = ns["opt"]
    assert opt.converged and opt.feasible
    assert opt.verification is not None and opt.verification.feasible
    assert opt.design[0] < 12.0 and opt.objective < ns["ev"].values["rod_mass"]
    g = (np.max(opt.evaluation.values["ram_error"]) - 2.0e-5) / 2.0e-5
    assert -1e-3 <= g <= flexmbs.FEASIBILITY_TOL
    shown = {float(_option(r["argv"], "--design")) for r in tutorial["ran"]
             if r["argv"][0] == "animate"}
    assert shown == {math.ceil(opt.design[0] * 10) / 10}
    prob = flexmbs.Problem(tutorial["folder"] / "my.toml")
    assert prob.evaluate(sorted(shown), gradient=False).feasible
