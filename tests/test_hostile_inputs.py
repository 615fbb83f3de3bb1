"""Hostile inputs: absurd numbers, deeply nested files, special files, wrong stored content.

On the command line every bad argument is one line on stderr with exit status 2 (no
traceback); in Python a typed error (ModelError, CaseError, ResourceError) names the input, the
value and what is allowed. Nothing may hang, read without end or exhaust the memory first.
"""
from __future__ import annotations

import numpy as np
import pytest

from flexmbs.cli.main import main
from flexmbs.errors import ModelError, ResourceError


def _one_error_line(capsys):
    """The single line on stderr (no traceback, nothing on stdout)."""
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def _no_simulation(monkeypatch):
    """Make any simulation fail the test: the error must come before the run."""
    from flexmbs.problem import Problem

    def forbidden(self, *a, **k):
        raise AssertionError("simulation started although an argument was bad")
    monkeypatch.setattr(Problem, "simulate", forbidden)
    monkeypatch.setattr(Problem, "evaluate", forbidden)


# ----------------------------------------------------------------------------- command line
def test_checkpoint_interval_beyond_the_run_gives_the_adjoint_gradient():
    """checkpoints=10**20 (beyond a C int: OverflowError before): the adjoint keeps the initial
    state only and its constraint Jacobian (21 rows x 4 variables over 20 steps) equals the
    direct differentiation's, the same discretisation differentiated exactly: equal to
    rounding (measured 2.4e-12 of the largest entry), asserted to 1e-8."""
    from flexmbs.problem import Problem

    ov = {"time.t_end": 0.01}
    direct = Problem("robot_2dof", overrides=ov).evaluate(None, gradient=True)
    adj = Problem("robot_2dof", overrides=ov, gradient_method="adjoint",
                  checkpoints=10 ** 20).evaluate(None, gradient=True)
    assert adj.stats["adjoint_checkpoints"] == 10 ** 20
    scale = np.max(np.abs(direct.jacobian))
    assert scale > 0
    np.testing.assert_allclose(adj.jacobian, direct.jacobian, rtol=0, atol=1e-8 * scale)


@pytest.mark.parametrize("address", ["not a url", "bogus", "tcp://host-without-port"])
def test_bad_dask_address_is_one_line_before_any_job(monkeypatch, capsys, address):
    """--dask with an address that has no port or no host: one line naming --dask and the
    value, exit 2, before any simulation (optimize --starts) and before any job (reproduce:
    once, not once per job)."""
    _no_simulation(monkeypatch)
    import flexmbs.batch as batch

    def forbidden(*a, **k):
        raise AssertionError("a batch started although --dask was bad")
    monkeypatch.setattr(batch, "run_batch", forbidden)
    assert main(["optimize", "robot_2dof", "--method", "fully", "--starts", "2",
                 "--dask", address]) == 2
    line = _one_error_line(capsys)
    assert "--dask" in line and repr(address) in line
    assert main(["reproduce", "--table", "1", "--dask", address, "--out", "unused"]) == 2
    line = _one_error_line(capsys)
    assert "--dask" in line and repr(address) in line


def test_bad_dask_address_in_python():
    """run_batch(dask='bogus') is a ModelError naming dask and the value, before any job."""
    from flexmbs.batch import run_batch

    with pytest.raises(ModelError, match=r"dask 'bogus' is not a Dask scheduler address"):
        run_batch(_double, {"a": dict(x=1)}, dask="bogus")


def test_negative_seed(capsys):
    """--seed=-1: numpy refused it from deep inside the sampler (ValueError); it is an argument
    error naming --seed, and start_designs(seed=-1) a ModelError naming seed."""
    from flexmbs.methods.multistart import start_designs

    with pytest.raises(ModelError, match=r"seed must be an integer >= 0.*-1"):
        start_designs([1.0], [2.0], 2, seed=-1)
    assert main(["optimize", "robot_2dof", "--method", "fully", "--starts", "2",
                 "--seed=-1"]) == 2
    err = capsys.readouterr().err
    assert "--seed" in err and "-1" in err and "Traceback" not in err


def test_candidates_beyond_memory_are_refused(monkeypatch, capsys):
    """--candidates 10**9 with 4 variables: at least 8 bytes x 4 values x 10**9 = 32 GB of
    designs alone, beyond a 1 GB limit: a ResourceError naming --candidates before drawing
    (a raw MemoryError before)."""
    _no_simulation(monkeypatch)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "1G")
    assert main(["optimize", "robot_2dof", "--method", "fully", "--starts", "2",
                 "--candidates", "1000000000"]) == 2
    line = _one_error_line(capsys)
    assert "ResourceError" in line and "--candidates" in line and "1000000000" in line
    from flexmbs.methods.multistart import multistart
    with pytest.raises(ResourceError, match="candidates = 1000000000"):
        multistart("robot_2dof", 2, options=dict(candidates=10 ** 9))


def test_starts_beyond_memory_are_refused_before_drawing(monkeypatch, capsys):
    """--starts 10**7 with 4 variables under a 16 GB limit: the drawn designs alone (about
    3.8 GB, multistart.sample_memory) fit, but every start keeps its job, fingerprint and
    result (START_RECORD_BYTES each): 10**7 x (4 x 4 x 8 + 250 + 10 000) bytes = 104 GB, a
    ResourceError naming --starts, the count and that estimate, before any start is drawn."""
    import flexmbs.methods.multistart as ms
    _no_simulation(monkeypatch)

    def forbidden(*a, **k):
        raise AssertionError("starts drawn although they cannot fit in memory")
    monkeypatch.setattr(ms, "start_designs", forbidden)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "16G")
    assert main(["optimize", "robot_2dof", "--method", "fully", "--starts", "10000000"]) == 2
    line = _one_error_line(capsys)
    assert "ResourceError" in line and "--starts" in line and "10000000" in line
    assert "records need about 104 GB" in line and "16 GB" in line, line
    with pytest.raises(ResourceError, match="starts = 10000000"):
        ms.multistart("robot_2dof", 10 ** 7)


# ----------------------------------------------------------------------------- deep nesting
DEEP = 10_000


def _study(folder, published_text=None, extra=""):
    """A minimal study file beside its published JSON (tests/test_file_safety.py's)."""
    from test_file_safety import _study as study_file

    f = study_file(folder, extra=extra)
    if published_text is not None:
        (folder / "published.json").write_text(published_text)
    return f


@pytest.mark.parametrize("value", ["[" * DEEP + "1" + "]" * DEEP,
                                   "{a = " * DEEP + "1" + "}" * DEEP])
def test_case_nested_too_deeply(tmp_path, capsys, value):
    """A case value nested 10 000 levels (arrays, inline tables): a CaseError naming the file
    and 'nested too deeply' (a RecursionError with thousands of lines before), and one line on
    the command line."""
    from flexmbs.model.casefile import read_description
    from flexmbs.errors import CaseError

    f = tmp_path / "deep.toml"
    f.write_text(f'x = {value}\n[[bodies]]\nname = "a"\n')
    with pytest.raises(CaseError, match=r"deep\.toml: nested too deeply"):
        read_description(f)
    assert main(["simulate", str(f)]) == 2
    assert "nested too deeply" in _one_error_line(capsys)


def test_study_nested_too_deeply(tmp_path):
    """A study file with a value nested 10 000 levels, and a study whose published JSON nests
    100 000 levels: CaseError naming the file and 'nested too deeply'."""
    from flexmbs.errors import CaseError
    from flexmbs.paper.study import load_study

    f = _study(tmp_path, extra="x = " + "[" * DEEP + "1" + "]" * DEEP + "\n")
    with pytest.raises(CaseError, match=r"study\.toml: nested too deeply"):
        load_study(f)
    g = tmp_path / "other"
    g.mkdir()
    f = _study(g, published_text="[" * 100_000 + "]" * 100_000)
    with pytest.raises(CaseError, match=r"published\.json: nested too deeply"):
        load_study(f)


# ----------------------------------------------------------------------------- extreme numbers
ALU = dict(E=72e9, nu=0.3, rho=2700.0)


@pytest.mark.parametrize("make", [lambda d: __import__("flexmbs").Circle(d),
                                  lambda d: __import__("flexmbs").Tube.with_wall_ratio(d, 0.1),
                                  lambda d: __import__("flexmbs").Tube(d, d / 4),
                                  lambda d: __import__("flexmbs").Rectangle(d, d)],
                         ids=["Circle", "Tube.with_wall_ratio", "Tube", "Rectangle"])
@pytest.mark.parametrize("d", [1e308, 1e-300, 1e-200])
def test_section_sizes_beyond_double_precision(make, d):
    """A section of size 1e308 (d^4 overflows: OverflowError before) or 1e-300 / 1e-200 (d^4
    underflows to 0: ZeroDivisionError, or a singular system blamed on missing joints,
    before): ModelError naming the section and the range of sizes, for its properties and
    their derivatives."""
    import flexmbs as fx

    sec, mat = make(d), fx.Material(**ALU)
    for call in (sec.properties, sec.property_derivatives):
        with pytest.raises(ModelError, match=r"overflow or underflow double precision"):
            call(mat)
        with pytest.raises(ModelError, match=type(sec).__name__):
            call(mat)


@pytest.mark.parametrize("design", ["1e308", "1e-300", "1e-200"])
def test_design_beyond_double_precision_on_the_command_line(capsys, design):
    """simulate --design 1e308 (or 1e-300, 1e-200): one line naming the beam, the element and
    the section, exit 2."""
    assert main(["simulate", "robot_2dof", "--design", design]) == 2
    line = _one_error_line(capsys)
    assert "ModelError" in line and "beam 'arm1', element 1" in line and "Tube(" in line


@pytest.mark.parametrize("interpolation", ["cubic", "pchip"])
@pytest.mark.parametrize("t, values", [
    ([0.0, 1.0, 2.0, 3.0], [0.0, 1e308, -1e308, 0.0]),
    ([0.0, 1.0, 2.0], [0.0, 1e308, 0.0]),
    ([0.0, 1e-300, 2e-300], [0.0, 1.0, 2.0]),
])
def test_samples_beyond_double_precision(interpolation, t, values):
    """TimeLaw.samples through +-1e308 (scipy's ValueError before) or over times 1e-300
    apart (infinite slopes): ModelError naming the law, at construction."""
    from flexmbs.model.laws import TimeLaw

    with pytest.raises(ModelError, match=r"TimeLaw\.samples 'push'"):
        TimeLaw.samples(t, values, name="push", interpolation=interpolation)


def test_samples_beyond_double_precision_in_a_case(capsys):
    """A case's sampled load law through +-1e308: one line naming the law, exit 2."""
    assert main(["simulate", "slider_crank_press", "--set",
                 "loads.0.law.values=[0.0, 0.0, 1e308, -1e308, 0.0, 0.0]",
                 "--set", "loads.0.law.interpolation='cubic'"]) == 2
    line = _one_error_line(capsys)
    assert "ModelError" in line and "'load 1'" in line


# ----------------------------------------------------------------------------- special files
def _double(x):
    """A batch job: 2 x."""
    return 2 * x


def _run_with_timeout(func, seconds=20):
    """func() in a thread: the test fails (instead of hanging) when it does not return."""
    import threading

    out = {}

    def run():
        try:
            out["value"] = func()
        except BaseException as exc:       # noqa: BLE001 - re-raised below
            out["error"] = exc
    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(seconds)
    assert not th.is_alive(), f"{func} did not return within {seconds} s (hangs)"
    if "error" in out:
        raise out["error"]
    return out.get("value")


def test_binary_history_to_resume(tmp_path, capsys):
    """A binary file given to --resume: ModelError naming the file and 'not UTF-8' (a
    UnicodeDecodeError before), one line on the command line."""
    from flexmbs.methods.result import read_history

    f = tmp_path / "h.jsonl"
    f.write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(ModelError, match=r"h\.jsonl.*not UTF-8"):
        read_history(f)
    assert main(["optimize", "robot_2dof", "--history", str(f), "--resume"]) == 2
    assert "not UTF-8" in _one_error_line(capsys)


def test_fifo_history_is_refused(tmp_path, capsys):
    """A FIFO given as --history (opening it for writing blocked until a reader came): refused
    at once, naming the file and 'FIFO'; with --resume too (the read blocked)."""
    import os
    from flexmbs.methods.result import HistoryWriter, read_history

    f = tmp_path / "pipe"
    os.mkfifo(f)
    with pytest.raises(ModelError, match="FIFO"):
        _run_with_timeout(lambda: HistoryWriter(f))
    with pytest.raises(ModelError, match="FIFO"):
        _run_with_timeout(lambda: read_history(f))
    assert _run_with_timeout(lambda: main(["optimize", "robot_2dof", "--history", str(f),
                                           "--resume"])) == 2
    line = _one_error_line(capsys)
    assert "FIFO" in line and str(f) in line


@pytest.mark.parametrize("what", ["history", "study", "case", "store"])
def test_dev_zero_is_refused(capsys, what):
    """/dev/zero as a history, a study, a case or a store (read until the memory ran out):
    refused at once as a character device (or as no folder), naming it."""
    import os
    if not os.path.exists("/dev/zero"):
        pytest.skip("no /dev/zero")
    from flexmbs.batch import run_batch
    from flexmbs.model.casefile import read_description
    from flexmbs.methods.result import HistoryWriter, read_history
    from flexmbs.paper.study import load_study

    call = {"history": lambda: read_history("/dev/zero"),
            "study": lambda: load_study("/dev/zero"),
            "case": lambda: read_description("/dev/zero"),
            "store": lambda: run_batch(_double, {"a": dict(x=1)}, workers=1,
                                        store="/dev/zero")}
    with pytest.raises(ModelError, match="/dev/zero"):
        _run_with_timeout(call[what])
    if what == "history":
        with pytest.raises(ModelError, match="character device"):
            _run_with_timeout(lambda: HistoryWriter("/dev/zero", resume=True))


def test_special_file_in_a_store_is_not_a_result(tmp_path):
    """A FIFO under a stored job's name (reading it blocked): not a result; the job runs
    again, with a warning naming the file."""
    import os
    from flexmbs.batch import run_batch

    os.mkfifo(tmp_path / "a.json")
    with pytest.warns(UserWarning, match=r"a\.json"):
        out = _run_with_timeout(lambda: run_batch(_double, {"a": dict(x=-3)}, workers=1,
                                                  store=tmp_path))
    assert out == {"a": -6}


# ----------------------------------------------------------------------------- stored results
def _square(x):
    """A batch job whose result has a schema: {'x': x, 'square': x * x}."""
    return {"x": x, "square": x * x}


def _square_schema():
    from flexmbs.batch import StoredResult

    class SquareResult(StoredResult):
        x: float
        square: float
    return SquareResult


@pytest.mark.parametrize("content", ["[]", '{"foo": 1}', '{"x": "3", "square": "9"}', "null",
                                     '"a string"', '{"x": 3, "square": [9]}'])
def test_stored_result_of_the_wrong_content_is_computed_again(tmp_path, content):
    """A stored job file that is valid JSON but not a result (a list, another object, strings
    for numbers): not reused (a TypeError or KeyError in the reader before); the job runs
    again, with a warning naming the file and the key, and the result is the job's (3^2 = 9)."""
    from flexmbs.batch import run_batch

    _square.result_schema = _square_schema()
    f = tmp_path / "a.json"
    f.write_text(content)
    with pytest.warns(UserWarning, match=r"a\.json"):
        out = run_batch(_square, {"a": dict(x=3.0)}, workers=1, store=tmp_path)
    assert out == {"a": {"x": 3.0, "square": 9.0}}
    # the file now holds the result: a rerun reuses it without a warning
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert run_batch(_square, {"a": dict(x=3.0)}, workers=1, store=tmp_path) == out


def test_stored_multistart_start_of_the_wrong_content(tmp_path):
    """multistart's store: a start's file rewritten with its fingerprint kept but its values
    as strings (or removed) is computed again with a warning naming the file, and the
    multi-start ends at the same optimum as the run that wrote the file (the same start,
    optimizer and iterations: equal to rounding)."""
    import json
    from flexmbs.methods.multistart import multistart
    from flexmbs.problem import Problem

    prob = Problem("robot_2dof", overrides={"time.t_end": 0.05})
    first = multistart(prob, 1, store=tmp_path, options=dict(verify=False),
                       fully=dict(max_iterations=2))
    f = tmp_path / "start000.json"
    good = json.loads(f.read_text())
    for bad in ({"fingerprint": good["fingerprint"], "foo": 1},
                dict(good, objective=str(good["objective"]), simulations="3")):
        f.write_text(json.dumps(bad))
        with pytest.warns(UserWarning, match=r"start000\.json.*key '"):
            again = multistart(prob, 1, store=tmp_path, options=dict(verify=False),
                               fully=dict(max_iterations=2))
        assert again.optima[0]["objective"] == pytest.approx(first.optima[0]["objective"],
                                                             rel=1e-12)


def test_stored_reproduce_results_are_checked(tmp_path):
    """reproduce's reader of stored results (its `_stored`): a file with the right fingerprint
    but without the keys the report reads is None (computed again), with a warning naming the
    file; a real result of max_deviation_job passes."""
    import json
    from flexmbs.sweep import max_deviation_job, MaxDeviationResult
    from flexmbs.paper.reproduce import _stored

    fp = {"flexmbs": "x", "method": "m", "options": {}, "description": {}}
    good = dict(max_deviation_job("robot_2dof", [50.0] * 4, {"time.t_end": 0.05}),
                fingerprint=fp)
    f = tmp_path / "p.json"
    f.write_text(json.dumps(good))
    assert _stored(f, fp, MaxDeviationResult) == good
    f.write_text(json.dumps(dict(good, mass_kg="2.3")))
    with pytest.warns(UserWarning, match=r"p\.json.*'mass_kg'"):
        assert _stored(f, fp, MaxDeviationResult, warn=True) is None
    f.write_text(json.dumps({"fingerprint": dict(fp, options="x")}))
    assert _stored(f, fp) is None          # a malformed fingerprint: stale, not a crash


# ----------------------------------------------------------------------------- memory
def test_rigid_reference_memory_is_refused_before_computing_it(monkeypatch, capsys):
    """FLEXMBS_MEMORY_LIMIT=600M, robot_2dof at h = 5e-10 s to 0.0015 s: 3 000 001 time
    points, whose rigid reference (at least 3 poses x 3 values x 2 groups x 8 bytes = 144 bytes
    a point: 432 MB, and its laws) reached 5.85 GB before the simulation's estimate refused:
    a ResourceError naming time.h and t_end before the reference is computed."""
    import flexmbs.model.kinematics as kin
    from flexmbs.problem import Problem

    def forbidden(*a, **k):
        raise AssertionError("the rigid reference was computed although it does not fit")
    monkeypatch.setattr(kin, "rigid_reference", forbidden)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "600M")
    with pytest.raises(ResourceError, match=r"rigid reference over 3000001 time points.*time\.h"):
        Problem("robot_2dof", overrides={"time.h": 5e-10, "time.t_end": 0.0015})
    assert main(["evaluate", "robot_2dof", "--h", "5e-10", "--t-end", "0.0015"]) == 2
    assert "ResourceError" in _one_error_line(capsys)


@pytest.mark.parametrize("case", ["robot_2dof", "fourbar"])
def test_rigid_reference_memory_estimate_bounds_the_traced_peak(case):
    """flexmbs.model.kinematics.reference_memory is an upper bound of the memory the rigid reference
    allocates (its peak traced by tracemalloc over 20 001 time points, numpy arrays included)
    and within a factor 2 of it (the resources' estimates' promise, flexmbs.resources)."""
    import tracemalloc
    from flexmbs.model.casefile import read_description
    from flexmbs.model.kinematics import reference_memory
    from flexmbs.model.mechanism import Mechanism

    d0 = read_description(case)
    Mechanism(d0).reference                      # imports and caches outside the trace
    d = read_description(case, overrides={"time.h": d0.time.t_end / 20000})
    tracemalloc.start()
    try:
        m = Mechanism(d)
        m.reference
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    following = sum(dr.law.type == "reference" for dr in d.drives)
    est = reference_memory(m.reference_model, m.t.size, following)
    assert peak <= est <= 2 * peak, (peak, est)


# ----------------------------------------------------------------------------- unclear -> clear
@pytest.mark.parametrize("args", [
    ["simulate", "robot_2dof", "--out="], ["simulate", "robot_2dof", "--plot", " "],
    ["optimize", "robot_2dof", "--history="], ["reproduce", "--out="],
    ["optimize", "robot_2dof", "--method", "fully", "--starts", "2", "--store="],
])
def test_empty_output_name_is_refused(monkeypatch, capsys, args):
    """--out '' (and --plot, --history, --store, reproduce --out): an empty name wrote nothing
    and said nothing; it is a one-line usage error naming the option, exit 2, before any
    simulation."""
    _no_simulation(monkeypatch)
    assert main(args) == 2
    line = _one_error_line(capsys)
    option = next(a for a in args if a.startswith("--") and a.rstrip("=") in
                  ("--out", "--plot", "--history", "--store")).rstrip("=")
    assert f"argument {option}" in line and "expected a file or folder name" in line


@pytest.mark.parametrize("args", [
    ["simulate"], ["bogus"], ["simulate", "robot_2dof", "--no-such-option"],
    ["simulate", "robot_2dof", "--design", "-40,30,35,25"],
    ["optimize", "robot_2dof", "--method", "fully", "--starts", "2", "--seed=-1"],
    ["reproduce", "--table", "x"],
])
def test_usage_errors_are_one_line(capsys, args):
    """argparse's usage errors (a missing CASE, an unknown command or option, a bad value)
    printed the usage, 2-7 lines, before the error: one line now, exit 2, naming --help."""
    assert main(args) == 2
    line = _one_error_line(capsys)
    assert line.startswith("flexmbs") and "error:" in line and "--help" in line


@pytest.mark.parametrize("design", [np.array([50 + 1j] * 4), [50.0, 50.0, 50.0, complex(50, 0)],
                                    np.array([50.0] * 4, dtype=complex)])
def test_complex_design_is_refused(design):
    """A complex design (even with zero imaginary parts) was cast to float with numpy's
    ComplexWarning only: a ModelError naming the design and 'complex'."""
    from flexmbs.problem import Problem

    p = Problem("robot_2dof", overrides={"time.t_end": 0.01})
    with pytest.raises(ModelError, match=r"design must be 4 real numbers.*complex"):
        p.evaluate(design, gradient=False)


@pytest.mark.parametrize("which", ["q0", "qd0"])
def test_complex_initial_state_is_refused(which):
    """simulate(initial=InitialConditions(q0=complex)) or qd0: a ModelError naming the
    argument and 'complex'."""
    import flexmbs as fx
    from flexmbs.problem import Problem

    model = Problem("robot_2dof", overrides={"time.t_end": 0.01}).mechanism.model
    state = model.compile().qref.astype(complex)
    if which == "qd0":
        state = np.zeros_like(state)
    with pytest.raises(ModelError, match=rf"{which} must be an array of real numbers.*complex"):
        fx.simulate(model, 0.01, initial=fx.InitialConditions(**{which: state}))


def test_unknown_mma_option_lists_the_valid_keys():
    """An unknown key of the MMA's options (once a TypeError of MMA.__init__) is a ModelError
    naming the key and listing the allowed ones (flexmbs.model.options.MMAOptions), before any
    simulation."""
    from flexmbs.optimize import optimize_fully

    with pytest.raises(ModelError, match=r"unknown option 'mma.bogus'; allowed: "
                                         r"conservative, move.*max_inner"):
        optimize_fully("robot_2dof", optimizer="mma", options=dict(mma={"bogus": 1}))


@pytest.mark.parametrize("scale", [-1.0, [50.0, 50.0, -1.0, 50.0], [1.0, 2.0]])
def test_bad_scale_is_named(scale):
    """A bad design scale (once reported as a bad design): the error names `scale` (a
    negative value: FullyOptions' validation; a wrong length: the problem's)."""
    from flexmbs.optimize import optimize_fully

    with pytest.raises(ModelError, match=r"^(options: option scale\.\d = -1\.0: Input should be "
                                         r"greater than 0|scale must be 4 positive finite "
                                         r"numbers)"):
        optimize_fully("robot_2dof", options=dict(scale=scale, max_iterations=1))


def test_history_that_is_a_folder(tmp_path):
    """optimize_fully(history=<a folder>) was IsADirectoryError: a ModelError naming the
    history and 'a folder'."""
    from flexmbs.optimize import optimize_fully

    with pytest.raises(ModelError, match=r"history .* is a folder"):
        optimize_fully("robot_2dof", history=tmp_path, options=dict(max_iterations=1))


def test_store_that_is_a_file(tmp_path):
    """run_batch(store=<a file>) was FileExistsError: a ModelError naming the store."""
    from flexmbs.batch import run_batch

    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(ModelError, match=r"store '.*/f' is a file, not a folder"):
        run_batch(_double, {"a": dict(x=1)}, workers=1, store=f)


def test_case_and_study_files_with_a_bom(tmp_path):
    """A UTF-8 byte-order mark at the start of a case file ("Invalid statement" before) or a
    study file is dropped: the case reads as the same file without it (equal descriptions)."""
    from pathlib import Path
    from flexmbs.model.casefile import case_path, read_description
    from flexmbs.paper.study import load_study

    text = Path(case_path("robot_2dof")).read_text(encoding="utf-8")
    f = tmp_path / "bom.toml"
    f.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    assert read_description(f) == read_description("robot_2dof")
    s = _study(tmp_path)
    s.write_bytes(b"\xef\xbb\xbf" + s.read_bytes())
    assert load_study(s).name == "mine"


def test_job_names_of_a_case_file_with_a_space(tmp_path):
    """A study table whose case is 'my case.toml': its runs' job names held the space, which
    run_batch refuses, so every job failed; they are valid job names now, distinct from those
    of 'my_case.toml' (a hash of the original name is added), and the shipped names are
    unchanged."""
    import shutil
    from flexmbs.batch import _NAME, job_name
    from flexmbs.model.casefile import case_path
    from flexmbs.paper.reproduce import table_runs
    from flexmbs.paper.study import load_study

    shutil.copy(case_path("robot_2dof"), tmp_path / "my case.toml")
    f = _study(tmp_path)
    f.write_text(f.read_text().replace('case = "robot_2dof"',
                                       f'case = "{(tmp_path / "my case.toml").as_posix()}"'))
    runs = table_runs([1], load_study(f))
    assert runs and all(_NAME.match(r.name) for r in runs)
    assert all(r.name.startswith("my_case-") for r in runs)
    assert job_name("my case-weakly") != job_name("my_case-weakly") == "my_case-weakly"
    assert job_name("robot_2dof-t0.65-weakly-50-50-50-50") == \
        "robot_2dof-t0.65-weakly-50-50-50-50"


@pytest.mark.parametrize("table_options, variant_options, key, got", [
    ("{ weakly = { frame_kind = [1, 2] } }", "{}", "tables.1.options.weakly.frame_kind",
     "[1, 2]"),
    ("{}", "{ mma_options = [1] }", "tables.1.variants[0].options.mma_options", "[1]"),
    ("{}", "{ mma_options = { move = [1] } }",
     "tables.1.variants[0].options.mma_options.move", "[1]"),
])
def test_study_option_of_a_wrong_kind_is_one_sentence(tmp_path, table_options, variant_options,
                                                      key, got):
    """A study option that is no scalar nor a table of scalars (a list for frame_kind or
    mma_options) gave one pydantic error per member of the union (4 to 8 lines naming 'bool',
    'int', 'float', 'str'): one sentence naming the key, what it may be and the value."""
    from flexmbs.errors import CaseError
    from flexmbs.paper.study import load_study

    f = _study(tmp_path)
    f.write_text(f.read_text() + f'''options = {table_options}
[[tables.1.variants]]
key = "v"
label = "v"
method = "fully"
options = {variant_options}
start = [50.0, 50.0, 50.0, 50.0]
''')
    with pytest.raises(CaseError) as err:
        load_study(f)
    msg = str(err.value)
    assert msg.count("key '") == 1, msg
    assert f"key '{key}' must be a number, a string or true/false" in msg and msg.endswith(got)
    assert ".bool" not in msg and ".str" not in msg


def _failed_start(x):
    """A batch job whose result holds non-finite numbers (as a failed start's)."""
    return {"x": x, "share": float("nan"), "values": np.array([1.0, np.inf, -np.inf]),
            "nested": [{"y": np.float64("nan")}]}


def test_stored_result_is_standard_json(tmp_path):
    """A stored result holding NaN or infinities (a failed start's optimizer_share) was written
    as bare NaN, which is not JSON (a strict parser refuses it): null instead, and the file
    parses with NaN refused."""
    import json
    from flexmbs.batch import run_batch

    run_batch(_failed_start, {"a": dict(x=1.0)}, workers=1, store=tmp_path)

    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    got = json.loads((tmp_path / "a.json").read_text(), parse_constant=refuse)
    assert got == {"x": 1.0, "share": None, "values": [1.0, None, None],
                   "nested": [{"y": None}]}


def test_existing_history_needs_resume(tmp_path, monkeypatch, capsys):
    """optimize --history h.jsonl again without --resume truncated the earlier run's history
    without a word: one line naming the file and suggesting --resume or another name, exit
    2, before any simulation, and the file is left as it was."""
    _no_simulation(monkeypatch)
    h = tmp_path / "h.jsonl"
    h.write_text('{"iteration": 1}\n')
    assert main(["optimize", "robot_2dof", "--history", str(h)]) == 2
    line = _one_error_line(capsys)
    assert str(h) in line and "--resume" in line and "another --history" in line
    assert h.read_text() == '{"iteration": 1}\n'


def test_history_is_locked_against_a_second_run(tmp_path):
    """Two runs writing one history left it unreadable (interleaved lines): the second
    HistoryWriter on a file that another process holds is refused at once (ModelError naming
    the file and 'locked'), and the first run's records are untouched (they read back)."""
    import subprocess
    import sys
    from flexmbs.methods.result import HistoryWriter, read_history

    h = tmp_path / "h.jsonl"
    w = HistoryWriter(h)
    w.write({"iteration": 1, "design": [1.0]})
    code = ("import sys\nfrom flexmbs.methods.result import HistoryWriter\n"
            "from flexmbs.errors import ModelError\n"
            "try:\n    HistoryWriter(sys.argv[1])\nexcept ModelError as e:\n"
            "    print(e); sys.exit(3)\n")
    other = subprocess.run([sys.executable, "-c", code, str(h)], capture_output=True,
                           text=True, timeout=120)
    assert other.returncode == 3, other.stderr
    assert "locked" in other.stdout and str(h) in other.stdout
    w.write({"iteration": 2, "design": [2.0]})
    w.close()
    assert [r["iteration"] for r in read_history(h)] == [1, 2]
    # closed: the file can be resumed by another writer (lock released)
    again = subprocess.run([sys.executable, "-c", code.replace("HistoryWriter(sys.argv[1])",
                                                               "HistoryWriter(sys.argv[1], "
                                                               "resume=True)"), str(h)],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr


def test_resumed_history_keeps_whole_records(tmp_path):
    """Resuming a history whose last line is cut short (an interrupted write) drops that line
    and appends after the whole records; a whole last record without its newline gets one."""
    import warnings
    from flexmbs.methods.result import HistoryWriter, read_history

    h = tmp_path / "h.jsonl"
    h.write_text('{"iteration": 1, "design": [1.0]}\n{"iteration": 2, "des')
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = HistoryWriter(h, resume=True)
    assert [r["iteration"] for r in w.previous] == [1]
    w.write({"iteration": 1, "design": [1.0]})          # the record the file holds
    w.write({"iteration": 2, "design": [2.0]})
    w.close()
    assert [r["iteration"] for r in read_history(h)] == [1, 2]
    g = tmp_path / "g.jsonl"
    g.write_text('{"iteration": 1, "design": [1.0]}')
    w = HistoryWriter(g, resume=True)
    w.write({"iteration": 1, "design": [1.0]})
    w.write({"iteration": 2, "design": [2.0]})
    w.close()
    assert [r["iteration"] for r in read_history(g)] == [1, 2]
