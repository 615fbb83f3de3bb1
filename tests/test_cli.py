"""The command line (flexmbs.cli.main): every bad argument or unwritable output path is one line on
stderr with exit status 2 and no traceback, found before the run; the names reported are the
files written; Ctrl-C during `optimize` and `reproduce` prints one line naming where the results
are and how to resume, exits with 130, and loses nothing already written."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from flexmbs.cli.main import main
from flexmbs.methods.result import HistoryWriter, read_history


def _no_simulation(monkeypatch):
    """Make any simulation fail the test: the error must come before the run."""
    from flexmbs.problem import Problem

    def forbidden(self, *a, **k):
        raise AssertionError("simulation started although an argument was bad")
    monkeypatch.setattr(Problem, "simulate", forbidden)
    monkeypatch.setattr(Problem, "evaluate", forbidden)


def _one_error_line(capsys):
    """The single line on stderr (and no traceback, no result on stdout)."""
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err and "max deviation" not in out and "report:" not in out
    return lines[0]


# ----------------------------------------------------------------------------- bad arguments
def test_unknown_figure_format_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    """--plot r.xyz: matplotlib has no .xyz writer; the error names the file and the formats
    it writes (png among them), before any simulation, and writes nothing."""
    _no_simulation(monkeypatch)
    f = tmp_path / "r.xyz"
    assert main(["simulate", "robot_2dof", "--plot", str(f)]) == 2
    line = _one_error_line(capsys)
    assert "r.xyz" in line and "'.xyz'" in line and ".png" in line and ".pdf" in line
    assert not f.exists()
    assert main(["optimize", "robot_2dof", "--plot", str(f)]) == 2
    assert "'.xyz'" in _one_error_line(capsys)


@pytest.mark.parametrize("args", [
    ["simulate", "robot_2dof", "--out", "{bad}/r.npz"],
    ["simulate", "robot_2dof", "--plot", "{bad}/r.png"],
    ["optimize", "robot_2dof", "--history", "{bad}/h.jsonl"],
    ["optimize", "robot_2dof", "--plot", "{bad}/r.png"],
    ["reproduce", "--table", "1", "--out", "{bad}/out"],
    ["demo", "--out", "{bad}/out"],
])
def test_unwritable_output_folder_is_refused_before_the_run(tmp_path, monkeypatch, capsys, args):
    """An output path whose folder cannot be created or written (here: under a regular file,
    which even root cannot write into) is one line naming the path, before any simulation."""
    _no_simulation(monkeypatch)
    bad = tmp_path / "file"
    bad.write_text("a regular file\n")
    args = [a.format(bad=bad) for a in args]
    assert main(args) == 2
    line = _one_error_line(capsys)
    assert str(bad) in line and ("not a folder" in line or "Not a directory" in line)
    assert bad.read_text() == "a regular file\n"


def test_full_disk_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    """With 1 kB free (shutil.disk_usage patched), --out of a 1301-step run (q and qd of 30
    unknowns: several hundred kB) is refused before the run with a ResourceError giving the
    estimate and the free space; so is a reproduction's output folder."""
    import shutil
    from collections import namedtuple
    _no_simulation(monkeypatch)
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 1000, 1000))
    assert main(["simulate", "robot_2dof", "--out", str(tmp_path / "r.npz")]) == 2
    line = _one_error_line(capsys)
    assert "ResourceError" in line and "r.npz" in line and "0.0 MB are free" in line
    assert main(["reproduce", "--table", "1", "--out", str(tmp_path / "rep")]) == 2
    line = _one_error_line(capsys)
    assert "ResourceError" in line and "rep" in line
    assert os.listdir(tmp_path) == ["rep"] and os.listdir(tmp_path / "rep") == []


@pytest.mark.parametrize("args,option", [
    (["simulate", "robot_2dof", "--design", "-40,30,35,25"], "--design=-40,30,35,25"),
    (["optimize", "robot_2dof", "--start", "-4e1,30,35,25"], "--start=-4e1,30,35,25"),
])
def test_negative_design_tells_to_attach_the_value(capsys, args, option):
    """argparse reads '-40,30,...' as an option; the error says to write --design=-40,..."""
    assert main(args) == 2
    out, err = capsys.readouterr()
    assert "Traceback" not in err and f"write {option}" in err


@pytest.mark.parametrize("args", [["demo", "--workers=-3"], ["reproduce", "--workers", "0"],
                                  ["demo", "--workers", "two"]])
def test_workers_below_one_is_a_clear_error(capsys, args):
    """--workers must be an integer >= 1: the message names the option and the value."""
    assert main(args) == 2
    _, err = capsys.readouterr()
    value = args[-1].split("=")[-1]
    assert "--workers" in err and "integer >= 1" in err and value in err
    assert "Traceback" not in err


def test_debug_shows_the_traceback(monkeypatch, capsys):
    """--debug (anywhere) or FLEXMBS_DEBUG=1 adds the traceback before the one-line error."""
    _no_simulation(monkeypatch)
    assert main(["simulate", "robot_2dof", "--design", "1,2", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("flexmbs simulate:")
    monkeypatch.setenv("FLEXMBS_DEBUG", "1")
    assert main(["simulate", "robot_2dof", "--design", "1,2"]) == 2
    assert "Traceback" in capsys.readouterr().err


# ----------------------------------------------------------------------------- names written
def test_reported_names_are_the_files_written(tmp_path, capsys, monkeypatch):
    """--out result and --plot fig (no extensions): numpy's .npz and matplotlib's .png are
    added, and the JSON reports exactly the files that exist; the .npz holds the run (its
    deviation maximum is the reported one) and the figure is a PNG."""
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "robot_2dof", "--t-end", "0.05", "--out", "result", "--plot", "fig",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["out"] == "result.npz" and out["plot"] == "fig.png"
    assert sorted(os.listdir(tmp_path)) == ["fig.png", "result.npz"]
    with np.load(tmp_path / out["out"]) as d:
        dev = out["responses"]["deviation_28"]
        assert d["response_deviation_28"].max() == dev["max"] and d["t"].size == 101
    assert (tmp_path / out["plot"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ----------------------------------------------------------------------------- history files
def test_history_with_a_cut_short_last_line(tmp_path):
    """A history whose last record was cut short (crash or full disk during the write) reads
    back as the complete records with a warning; a bad line elsewhere is a ModelError naming
    the file and the line."""
    from flexmbs.errors import ModelError
    h = tmp_path / "h.jsonl"
    with HistoryWriter(h) as w:
        for k in (1, 2):
            w.write({"iteration": k, "design_mm": np.array([50.0, 40.0 + k])})
    whole = h.read_text()
    h.write_text(whole + '{"iteration": 3, "design_')
    with pytest.warns(UserWarning, match="line 3 is cut short"):
        recs = read_history(h)
    assert recs == [{"iteration": 1, "design_mm": [50.0, 41.0]},
                    {"iteration": 2, "design_mm": [50.0, 42.0]}]
    h.write_text('{"iteration": 1}\n{"itera\n' + whole)
    with pytest.raises(ModelError, match=r"h\.jsonl.*line 2"):
        read_history(h)


# ----------------------------------------------------------------------------- Ctrl-C
def _start(args, cwd):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("FLEXMBS_DEBUG", None)
    # own process group (Ctrl-C goes to the group); SIGINT handled even when this process
    # was started with it ignored (a background job of a non-interactive shell)
    return subprocess.Popen([sys.executable, "-m", "flexmbs", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(proc, ready, timeout=60.0):
    t0 = time.monotonic()
    while not ready():
        if proc.poll() is not None:
            pytest.fail(f"finished before Ctrl-C: {proc.communicate()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            pytest.fail("never got ready")
        time.sleep(0.02)


def _ctrl_c(proc):
    """SIGINT to the whole process group, as Ctrl-C in a terminal."""
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raise


_IMPORTS_DURING_RUN = """
import sys
import flexmbs.methods.weakly as W
from flexmbs.cli.main import main
orig, new = W.optimize_weakly, []
def wrapped(*a, **k):
    before = set(sys.modules)
    try:
        return orig(*a, **k)
    finally:
        new.extend(sorted(set(sys.modules) - before))
W.optimize_weakly = wrapped
main(["optimize", "robot_2dof", "--max-cycles", "2", "--no-progress"])
print("NEW", new)
"""


def test_optimize_imports_nothing_during_the_run(tmp_path):
    """`flexmbs optimize` imports what its optimizers load on first use before the run
    (flexmbs.optimizers.library.preload), so that a Ctrl-C cannot land in an import: a
    KeyboardInterrupt escaping an import's exec of a string is marked unhandled by CPython,
    and the process then ended by SIGINT after printing its resume line (exit status -2
    instead of 130 for one early Ctrl-C in four). Without preload the run imported some 60
    modules (scipy.optimize's, numpy.f2py's); with it, none (fresh interpreter)."""
    env = dict(os.environ)
    env.pop("FLEXMBS_DEBUG", None)
    out = subprocess.run([sys.executable, "-c", _IMPORTS_DURING_RUN], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("NEW ")]
    assert line, out.stderr[-2000:]
    assert line[0] == "NEW []", line[0][:500]


def test_ctrl_c_during_optimize(tmp_path):
    """Ctrl-C after the first cycle of `flexmbs optimize --history`: exit status 130, one line
    on stderr naming the history file and the --start that resumes from its last design, no
    traceback, and the history holds every cycle that was done (each with its design)."""
    h = tmp_path / "h.jsonl"
    # eps 1e-12: the ESL test (25) never stops it early, the run outlasts the poll below
    proc = _start(["optimize", "robot_2dof", "--history", str(h), "--max-cycles", "30",
                   "--eps", "1e-12"], tmp_path)
    _wait_for(proc, lambda: h.exists() and h.read_text().endswith("\n"))
    out, err = _ctrl_c(proc)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(h) in lines[0], err
    recs = read_history(h)
    assert recs and all(len(r["design"]) == 4 for r in recs)
    last = ",".join(f"{v:.6g}" for v in recs[-1]["design"])
    assert f"--start={last}" in lines[0]
    # every cycle reported on the terminal is in the history (a Ctrl-C may fall between a
    # record's write and its printed line, so the history may hold one more)
    assert out.count("cycle ") <= len(recs)


def test_ctrl_c_during_reproduce(tmp_path):
    """Ctrl-C while `flexmbs reproduce --table 1` runs its jobs: exit status 130, one line
    naming the job folder and how to resume, no traceback."""
    out_dir = tmp_path / "rep"
    proc = _start(["reproduce", "--table", "1", "--out", str(out_dir), "--workers", "1",
                   "--no-figures"], tmp_path)
    _wait_for(proc, lambda: (out_dir / "jobs" / "optimizations").is_dir())
    time.sleep(0.5)
    out, err = _ctrl_c(proc)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(out_dir / "jobs") in lines[0] and "run the same command again" in lines[0]
    # nothing half-written is left where a result belongs
    for f in (out_dir / "jobs" / "optimizations").glob("*.json"):
        json.loads(f.read_text())


def test_simulate_json_gives_the_published_table1_design(capsys):
    """`flexmbs simulate robot_2dof --design <Table 1 weakly optimum> --json`: the paper's mass
    0.962 kg (Table 1; 229.02 sum p^2 = 0.9623 kg) and its deviation (28) on the 1 mm limit
    (docs/paper-cases.md: 0.99-1.00 mm at the published optima; tolerance 1 %), at the last step of the
    1301-step grid."""
    assert main(["simulate", "robot_2dof", "--design", "39.29,28.33,34.94,25.19", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["responses"]["mass"]["value"] == pytest.approx(0.962, rel=1e-3)
    dev = out["responses"]["deviation_28"]
    assert dev["max"] == pytest.approx(1e-3, rel=0.01)
    assert dev["t_at_max"] == pytest.approx(0.65, abs=1e-12)


def test_simulate_summary_names_every_response_and_the_overrides(capsys):
    """The summary lists each response of the case with its maximum; --t-end (0.05 s: 100
    steps of 5e-4 s, as Result.stats['steps'] counts them) and --set time.h=1e-3 (50 steps)
    change the grid."""
    assert main(["simulate", "robot_2dof", "--t-end", "0.05"]) == 0
    out = capsys.readouterr().out
    assert "deviation_28" in out and "deviation_30" in out and "of 100)" in out
    assert "100 steps of h = 0.0005 s" in out
    assert main(["simulate", "robot_2dof", "--t-end", "0.05", "--set", "time.h=1e-3"]) == 0
    out = capsys.readouterr().out
    assert "of 50)" in out and "50 steps of h = 0.001 s" in out


@pytest.mark.parametrize("argv, words", [
    (["--t-end", "0.5", "--set", "time.t_end=[1,2]"],
     ["--t-end 0.5", "time.t_end=[1, 2]", "two values of time.t_end"]),
    (["--t-end", "0.5", "--set", "time.t_end=0.25"], ["--t-end 0.5", "time.t_end=0.25"]),
    (["--h", "0.001", "--set", "time.h=auto"], ["--h 0.001", "time.h='auto'"]),
    (["--rho-inf", "0.5", "--set", "time.rho_inf=0.9"], ["--rho-inf 0.5", "time.rho_inf=0.9"]),
    (["--t-end", "0.5", "--set", "time={t_end=0.3}"], ["--t-end 0.5", "--set time=", "0.3"]),
    (["--set", "time.h=1e-3", "--set", "time.h=2e-3"],
     ["'time.h=1e-3'", "'time.h=2e-3'", "two values of time.h"]),
])
def test_an_option_and_a_set_of_its_key_with_two_values_are_refused(monkeypatch, capsys,
                                                                    argv, words):
    """--t-end, --h and --rho-inf stand for time.t_end, time.h and time.rho_inf: given with a
    --set of the same key (or of its table) with another value, or a key set twice with two
    values, one error line names both before any run (neither value is dropped silently, an
    invalid one included)."""
    _no_simulation(monkeypatch)
    assert main(["evaluate", "fourbar", *argv]) == 2
    line = _one_error_line(capsys)
    for w in words:
        assert w in line, (w, line)


def test_an_option_and_a_set_of_its_key_with_one_value_are_taken():
    """--t-end 0.01 with --set time.t_end=0.01 (the same value, 1e-2 written otherwise): the
    problem's horizon is 0.01 s (time.t_end), so the time grid of step 5e-4 s ends there."""
    from flexmbs.cli.common import add_case_arguments, problem_from_args
    import argparse
    p = argparse.ArgumentParser()
    add_case_arguments(p)
    prob = problem_from_args(p.parse_args(["fourbar", "--t-end", "0.01", "--set",
                                           "time.t_end=1e-2"]))
    assert prob.description.time.t_end == 0.01


@pytest.mark.parametrize("argv, words", [
    (["--method", "fully", "--max-iterations", "10", "--set", "optimize.max_iterations=5"],
     ["--max-iterations 10", "optimize.max_iterations=5"]),
    (["--method", "fully", "--starts", "3", "--set", "optimize.multistart.starts=4"],
     ["--starts 3", "optimize.multistart.starts=4"]),
    (["--eps", "0.01", "--set", "optimize.weakly.eps=0.02"],
     ["--eps 0.01", "optimize.weakly.eps=0.02"]),
])
def test_an_optimize_option_and_a_set_of_its_key_with_two_values_are_refused(
        monkeypatch, capsys, argv, words):
    """The optimize options stand for keys of the case's [optimize] table (--max-iterations:
    optimize.max_iterations, --starts: optimize.multistart.starts, --eps:
    optimize.weakly.eps): given with a --set of that key with another value, one error line
    names both before any run."""
    _no_simulation(monkeypatch)
    assert main(["optimize", "fourbar", *argv]) == 2
    line = _one_error_line(capsys)
    for w in [*words, "give one"]:
        assert w in line, (w, line)
