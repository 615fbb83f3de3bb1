"""Ending runs on request: a compiled run stops within a step when its cancel flag is set
(flexmbs.core.run_interruptible: Ctrl-C in the main thread sets it), each run has a flag of its
own, and the command line ends a simulation or a film on SIGINT (exit 130) or SIGTERM (exit 143)
with one line and nothing half-written left. A film that cannot be written whole raises
ResourceError and leaves no file.

The runs are the four-bar (cases/fourbar.toml) over 20 s: 40 000 steps, 6 s and more of the
core (measured at commit dbd5ceb: 2.9 s for the first 20 000 steps, `Problem("fourbar",
{"time.t_end": 10.0}).simulate()`, load 6 on 2 cores), so that a run that did not stop on
request would exceed every time bound below by seconds."""
import _thread
import os
import resource
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import flexmbs.analysis.simulate as simulate_module
from flexmbs.core import cancel_flag, simulate_arrays
from flexmbs.errors import Interrupted, ResourceError
from flexmbs.problem import Problem

LONG = 20.0         #: simulated time (s) of a long run
PY = sys.executable


class _Captured(Exception):
    pass


def _core_arguments(t_end, monkeypatch, case="fourbar"):
    """(problem, arguments): the arguments `simulate` gives the compiled run of the case
    over t_end (s), taken on their way to run_interruptible, without running it; the problem
    owns the KLU analysis they name by address, and must outlive their use."""
    def capture(fn, stack_bytes=0, **kwargs):
        raise _Captured(kwargs)

    prob = Problem(case, overrides={"time.t_end": t_end})
    with monkeypatch.context() as m:
        m.setattr(simulate_module, "run_interruptible", capture)
        try:
            prob.simulate()
        except _Captured as c:
            return prob, c.args[0]
    raise AssertionError("the compiled run was not reached")


def test_a_set_cancel_flag_ends_its_run_and_no_other(monkeypatch):
    """Two long runs in two threads, each with its own cancel flag. The first flag is set 0.5 s
    in: its run raises Interrupted within 1 s, at a simulated time inside (0, t_end); the
    other run is still going 0.5 s later; its flag, set then, ends it within 1 s, further in
    simulated time than the first."""
    prob, kw = _core_arguments(LONG, monkeypatch)
    flags = [cancel_flag(), cancel_flag()]
    outcome, ended = {}, {}

    def run(k):
        try:
            outcome[k] = simulate_arrays(**kw, cancel=flags[k])
        except Interrupted as exc:
            outcome[k] = exc
        ended[k] = time.monotonic()

    threads = [threading.Thread(target=run, args=(k,)) for k in (0, 1)]
    for th in threads:
        th.start()
    time.sleep(0.5)
    assert not ended, "a run ended before its flag was set"
    for k in (0, 1):
        if k == 1:
            time.sleep(0.5)
            assert 1 not in ended, "the other run stopped with the first"
        flags[k][0] = 1
        t_set = time.monotonic()
        threads[k].join(timeout=10)
        assert isinstance(outcome.get(k), Interrupted), outcome.get(k)
        assert ended[k] - t_set < 1.0
        assert 0 < outcome[k].time < LONG
    assert outcome[1].time > outcome[0].time
    del prob


def test_a_flag_set_before_the_run_stops_the_static_start(monkeypatch):
    """The robot of cases/robot_2dof.toml starts from static equilibrium (start = "static"):
    with its flag set before the call, the core returns Status.INTERRUPTED at t = 0 before the
    first static iteration (stats: 0 static iterations, 0 steps); with the flag clear the same
    call makes static iterations and every step."""
    import flexmbs._core as _core
    from flexmbs.core import RunOutput, Status, _with_handle

    prob, kw = _core_arguments(0.01, monkeypatch, case="robot_2dof")
    assert kw["static_start"] == 1
    owner, args = _with_handle(kw)
    for value in (1, 0):
        flag = cancel_flag()
        flag[0] = value
        out = RunOutput(*_core.simulate(**args, cancel=flag))
        status, stats, info = out.status, out.stats, out.info
        if value:
            assert status == Status.INTERRUPTED and info[0] == 0.0
            assert stats[4] == 0 and stats[5] == 0
        else:
            assert status == Status.OK and stats[4] > 0 and stats[5] == kw["nsteps"]
    del owner, prob


def test_ctrl_c_in_the_main_thread_ends_the_run_within_a_second():
    """Python: a KeyboardInterrupt (Ctrl-C, here `_thread.interrupt_main`) 0.5 s into a long
    simulation raises within 1 s, and the core's helper thread has ended with it."""
    prob = Problem("fourbar", overrides={"time.t_end": LONG})
    timer = threading.Timer(0.5, _thread.interrupt_main)
    t0 = time.monotonic()
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        prob.simulate()
    elapsed = time.monotonic() - t0
    timer.join()
    assert elapsed < 1.5
    assert not [th for th in threading.enumerate() if th.name == "flexmbs-core"]


_ANNOUNCED = """
import sys
import flexmbs.analysis.simulate as S
real = S.run_interruptible
def announced(*a, **k):
    print("core", flush=True)
    return real(*a, **k)
S.run_interruptible = announced
from flexmbs.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def _cli(args, cwd, **kw):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("FLEXMBS_DEBUG", None)
    return subprocess.Popen([PY, "-c", _ANNOUNCED, *args], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True,
                            preexec_fn=_default_signals, **kw)


def _default_signals():
    """The child starts with SIGINT and SIGTERM at their default actions, as from a shell (a
    background job's parent may ignore them, and ignored signals are inherited)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _signal_when(proc, ready, sig, delay=0.3):
    """Send `sig` to the process group `delay` s after `ready()` (a line read), return (exit
    status, seconds from the signal to the exit, stderr)."""
    ready()
    time.sleep(delay)
    t0 = time.monotonic()
    os.killpg(proc.pid, sig)
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    return proc.returncode, time.monotonic() - t0, err


@pytest.mark.parametrize("sig, code, line", [(signal.SIGINT, 130, "interrupted"),
                                             (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_a_signal_ends_flexmbs_simulate_within_seconds(tmp_path, sig, code, line):
    """`flexmbs simulate fourbar --t-end 20` signalled 0.3 s into its compiled run: exit status
    130 (SIGINT) or 143 (SIGTERM, 128 + 15) within 3 s, one line on stderr naming it, no
    traceback."""
    proc = _cli(["simulate", "fourbar", "--t-end", str(LONG)], tmp_path)
    status, seconds, err = _signal_when(proc, lambda: proc.stdout.readline(), sig)
    assert status == code, err
    assert seconds < 3.0
    assert err.strip().splitlines() == [f"flexmbs simulate: {line}"]


@pytest.mark.parametrize("suffix", [".mp4", ".pvd"])
def test_sigterm_during_animate_leaves_no_temporary_file(tmp_path, suffix):
    """SIGTERM while `flexmbs animate` writes its frames (its temporary film or frame folder
    exists beside the output): exit 143 with one line, and the folder holds nothing but what
    was there before (no temporary film, no frame folder, no output)."""
    out = tmp_path / f"x{suffix}"
    proc = _cli(["animate", "fourbar", "--t-end", "0.5", "--out", str(out), "--frames", "1000"],
                tmp_path)

    def writing():
        t0 = time.monotonic()
        while not [p for p in tmp_path.iterdir() if p.name.startswith(".x")]:
            if proc.poll() is not None or time.monotonic() - t0 > 60:
                pytest.fail(f"no temporary output seen: {proc.communicate()}")
            time.sleep(0.01)

    status, seconds, err = _signal_when(proc, writing, signal.SIGTERM, delay=0.1)
    assert status == 143, err
    assert len(err.strip().splitlines()) == 1 and "terminated (SIGTERM)" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def _limit_file_size():
    resource.setrlimit(resource.RLIMIT_FSIZE, (20 * 1024, resource.RLIM_INFINITY))


def test_an_mp4_that_cannot_be_written_whole_fails_with_resource_error(tmp_path):
    """`flexmbs animate --out x.mp4` under a 20 kB file size limit (`ulimit -f 20`), which cuts
    the film short: ffmpeg itself reports no error; the film read back holds fewer frames than
    were sent, so the command exits 2 with one ResourceError line naming the film and the
    limit, and no file is left."""
    out = tmp_path / "x.mp4"
    env = dict(os.environ)
    env.pop("FLEXMBS_DEBUG", None)
    # 10 frames: a 77 kB film without the limit
    run = subprocess.run([PY, "-m", "flexmbs", "animate", "fourbar", "--t-end", "0.05", "--out",
                          str(out), "--frames", "10"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120,
                         preexec_fn=_limit_file_size)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "ResourceError" in lines[0] and str(out) in lines[0]
    assert "ulimit -f" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_an_mp4_read_back_short_of_frames_is_refused(tmp_path, monkeypatch):
    """The check behind the previous test, in Python: `animate` with an encoder that stops
    after 3 frames without an error raises ResourceError naming the path, and leaves no file."""
    import flexmbs.visual.animation as A

    real = A._write_mp4

    def short(path, frames, fps):
        return real(path, (f for k, f in enumerate(frames) if k < 3), fps)

    monkeypatch.setitem(A._WRITERS, ".mp4", short)
    prob = Problem("fourbar", overrides={"time.t_end": 0.05})
    res = prob.simulate(store="all")
    out = tmp_path / "x.mp4"
    with pytest.raises(ResourceError, match="x.mp4.*3 of its 10 frames"):
        A.animate(prob, res, out, frames=10)
    assert list(tmp_path.iterdir()) == []


def test_an_adjoint_optimization_interrupted_in_the_core_resumes_to_the_same_design(
        tmp_path, monkeypatch):
    """A fully coupled MMA run with adjoint gradients (the robot of cases/robot_2dof.toml over
    0.1 s) interrupted by Ctrl-C while its 6th backward pass runs (the core returns
    Status.INTERRUPTED; the optimization raises KeyboardInterrupt) keeps a valid history, and
    resumed from it ends at the design of the uninterrupted run (1e-12 relative, the criterion
    of tests/test_resume.py) after replaying every recorded analysis."""
    import flexmbs.analysis.adjoint as adjoint_module
    from flexmbs.optimize import optimize_fully, read_history

    def robot():
        return Problem("robot_2dof", {"time.t_end": 0.1}, gradient_method="adjoint")

    ref = optimize_fully(robot(), optimizer="mma")
    real, calls, seen = adjoint_module.run_interruptible, [], []

    def ctrl_c_in_sixth_backward_pass(fn, stack_bytes=0, **kwargs):
        if fn is not adjoint_module.simulate_adjoint_arrays:
            return real(fn, stack_bytes, **kwargs)
        calls.append(1)
        if len(calls) != 6:
            return real(fn, stack_bytes, **kwargs)

        def pressed(**kw):      # Ctrl-C, then the backward pass starts
            _thread.interrupt_main()
            time.sleep(0.3)
            try:
                return fn(**kw)
            except BaseException as exc:
                seen.append(exc)
                raise

        return real(pressed, stack_bytes, **kwargs)

    h = tmp_path / "h.jsonl"
    monkeypatch.setattr(adjoint_module, "run_interruptible", ctrl_c_in_sixth_backward_pass)
    with pytest.raises(KeyboardInterrupt):
        optimize_fully(robot(), optimizer="mma", history=h)
    monkeypatch.undo()
    assert len(calls) == 6 and len(seen) == 1 and isinstance(seen[0], Interrupted)
    recs = read_history(h)
    recorded = sum(len(r["evaluations"]) for r in recs)
    assert recs and recorded >= 1
    res = optimize_fully(robot(), optimizer="mma", history=h, resume=True)
    np.testing.assert_allclose(res.design, ref.design, rtol=1e-12, atol=0)
    assert res.iterations == ref.iterations
    assert res.details["replayed_simulations"] == recorded
