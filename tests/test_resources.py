"""Memory safety: every allocation of the core returns a status that becomes a
ResourceError naming what was allocated and its size (the interpreter survives), and a run
that cannot fit is refused before it starts, quickly, with the estimate and what to change.

Sources of the expected values: the sizes are exact counts (8 bytes per double, 4 per pivot:
dense LU of n unknowns = 8 n^2 + 4 n bytes; outputs q, qd, qdd = 3 x 8 x stored coordinates x
time points); the measured peak is Python's own allocation tracer (tracemalloc), independent of
the estimate.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap
import time
import tomllib
import tracemalloc

import pytest

import flexmbs as fx
from flexmbs.cli.main import main as cli_main
from flexmbs.errors import ResourceError
from flexmbs.model.casefile import case_path
from flexmbs.problem import Problem
from flexmbs.resources import estimate_memory
from flexmbs.analysis.settings import SimulationSettings

ALU = fx.Material(E=72e9, nu=0.3, rho=2700)
SIM = sys.modules["flexmbs.analysis.simulate"]


def clamped_beam(elements, order=2):
    m = fx.Model()
    b = m.add_beam("b", (0.0, 0.0), (1.0, 0.0), elements, material=ALU,
                   section=fx.Tube.with_wall_ratio(0.05, 0.1), order=order)
    m.clamp(b.first)
    m.set_gravity(0.0, -9.81)
    return m, b


def test_dense_allocation_failure_in_core_is_a_resource_error():
    """Dense LU of a 40 005-unknown model (12.8 GB) in a process whose address space is limited
    (RLIMIT_AS: the allocation fails deterministically, whatever the machine's memory and
    overcommit policy): the Fortran allocation fails, the core returns status 9 with the exact
    size asked for, 8 n^2 + 4 n bytes, and Python raises ResourceError naming it and the KLU
    alternative; the interpreter survives. With the default limit the same run is refused
    before the core, by the estimate."""
    script = textwrap.dedent("""
        import math, resource
        import flexmbs as fx
        from flexmbs.errors import ResourceError
        vm = 0
        for line in open("/proc/self/status"):
            if line.startswith("VmSize:"):
                vm = int(line.split()[1]) * 1024
        resource.setrlimit(resource.RLIMIT_AS, (vm + 3 * 2**30, resource.RLIM_INFINITY))
        m = fx.Model()
        b = m.add_beam("b", (0, 0), (1, 0), 13333, material=fx.Material(E=72e9, nu=0.3, rho=2700),
                       section=fx.Tube.with_wall_ratio(0.05, 0.1), order=1)
        m.clamp(b.first)                        # 3 x 13334 coordinates + 3 rows = 40005 unknowns
        try:
            fx.simulate(m, 1e-4, 1e-4, solver="dense", store=[b.last])
        except ResourceError as e:
            print("ESTIMATE", e.required, "|", e)
        try:
            fx.simulate(m, 1e-4, 1e-4, solver="dense", store=[b.last], memory_limit=math.inf)
        except ResourceError as e:
            print("CORE", e.required, "|", e)
        print("ALIVE")
    """)
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = {ln.split(" ", 1)[0]: ln for ln in p.stdout.splitlines()}
    assert "ALIVE" in lines
    n = 40005
    est = lines["ESTIMATE"]
    assert "solver='klu'" in est and "needs about" in est
    assert float(est.split()[1]) >= 2 * 8.0 * n * n          # values + LU factors
    core = lines["CORE"]
    assert float(core.split()[1]) == 8.0 * n * n + 4.0 * n   # exact: n^2 doubles + n pivots
    assert "dense LU of 40005 unknowns: 12.8 GB" in core and "solver='klu'" in core


def test_fine_step_refused_before_the_grid_is_built():
    """h = 1e-9 over 0.65 s (6.5e8 time points): refused in well under a second (building the
    grid alone would take seconds and 5 GB), with the estimate in the message. The stored
    outputs alone are 3 x 8 x 30 x 6.5e8 = 468 GB, beyond any machine's memory."""
    model = Problem("robot_2dof").mechanism.model
    t0 = time.perf_counter()
    pattern = r"(time points|time steps).*(GB|TB)|(GB|TB).*time points"
    with pytest.raises(ResourceError, match=pattern) as ei:
        fx.simulate(model, 0.65, 1e-9)
    assert time.perf_counter() - t0 < 1.0
    assert ei.value.required >= 40.0 * 6.5e8
    with pytest.raises(ResourceError, match="more than the core's"):   # beyond 32-bit steps
        fx.simulate(model, 100.0, 1e-9)


def test_cli_fine_step_refused_before_the_run(monkeypatch, capsys):
    """`flexmbs simulate robot_2dof --h 1e-9` exits with status 2 and a one-line ResourceError
    before any time grid is allocated (the limit set through FLEXMBS_MEMORY_LIMIT, the
    documented setting). Timing is a benchmark's business, not a test's."""
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "16G")
    assert cli_main(["simulate", "robot_2dof", "--h", "1e-9"]) == 2
    err = capsys.readouterr().err
    assert "ResourceError" in err and "650000001 time points" in err and "coarser step h" in err


def test_many_elements_refused_with_the_estimate():
    """The robot case (cases/robot_2dof.toml) with 20 000 elements per arm (240 012 unknowns,
    1301 time points) under a 2 GB limit: refused before the core with the estimate, which is
    at least the stored outputs 3 x 8 x 240 006 x 1301 bytes (7.5 GB), and the advice to store
    fewer outputs. The motors get a ramp law instead of the rigid reference's angles: the
    reference's position analysis of a 240 006-coordinate model alone takes minutes
    (measured 168 s) and is not what is tested here."""
    with open(case_path("robot_2dof"), "rb") as f:
        data = tomllib.load(f)
    for body in data["bodies"][:2]:
        body["elements"] = 20000
    for drive in data["drives"]:
        drive["law"] = {"type": "ramp_to_speed", "speed": 1.0, "ramp_s": 0.3}
    del data["paths"]
    t0 = time.perf_counter()
    mech = Problem(data).mechanism
    with pytest.raises(ResourceError, match=r"240012 unknowns.*store fewer outputs") as ei:
        fx.simulate(mech.model, mech.t_end, mech.h, settings=SimulationSettings(memory_limit=2e9))
    assert time.perf_counter() - t0 < 10.0   # the model's sections in Python, not the run
    assert ei.value.required >= 3 * 8.0 * 240006 * 1301
    assert ei.value.available == 2e9


def test_memory_limit_is_validated():
    """memory_limit must be a positive number of bytes; FLEXMBS_MEMORY_LIMIT likewise."""
    model, _ = clamped_beam(2)
    with pytest.raises(fx.ModelError, match="memory_limit must be a positive number.*-1"):
        fx.simulate(model, 1e-3, 5e-4, settings=SimulationSettings(memory_limit=-1))


def test_estimate_within_factor_two_of_measured_peak(monkeypatch):
    """The robot of the paper over 0.65 s, all coordinates stored: the estimate lies within a
    factor 2 of the peak of Python's allocations during the run (tracemalloc; the outputs
    dominate) and is at least the bytes of the Result arrays (numpy nbytes)."""
    model = Problem("robot_2dof").mechanism.model
    model.compile()
    seen = {}

    def spy(**kw):
        seen["est"] = estimate_memory(**kw)
        return seen["est"]

    monkeypatch.setattr(SIM, "estimate_memory", spy)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        r = fx.simulate(model, 0.65, 5e-4, settings=SimulationSettings(start="static"))
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    total = seen["est"].total
    nbytes = sum(a.nbytes for a in (r.t, r.q, r.qd, r.qdd, r.mu))
    assert total >= nbytes
    assert 0.5 <= total / peak <= 2.0, (total, peak)


def test_large_model_beyond_the_stack_runs():
    """The core's work vectors live on the stack (-fstack-arrays): a 90 006-unknown cantilever
    in a process whose stack is 2 MB needs about 4.6 MB there and crashed (SIGSEGV) when called
    directly; simulate now runs the core in a helper thread with a large enough stack. Checked
    against the closed form of a Timoshenko cantilever under its own weight, tip deflection
    w = q L^4 / (8 EI) + q L^2 / (2 kGA) with L = 1 m, q = rhoA g (the 3-node elements are exact
    for it: measured agreement 3e-8)."""
    script = textwrap.dedent("""
        import flexmbs as fx
        from flexmbs.model.sections import section_properties
        alu = fx.Material(E=72e9, nu=0.3, rho=2700)
        sec = fx.Tube.with_wall_ratio(0.05, 0.1)
        m = fx.Model()
        b = m.add_beam("b", (0.0, 0.0), (1.0, 0.0), 15000, material=alu, section=sec)
        m.clamp(b.first)
        m.set_gravity(0.0, -9.81)
        r = fx.simulate(m, 1e-4, 1e-4, start="static", store=[b.last])
        EA, kGA, EI, rhoA, rhoI = section_properties(sec, alu)
        q = rhoA * 9.81
        print("RESULT", r.stats["unknowns"], r.q[0][1], -(q / (8 * EI) + q / (2 * kGA)))
    """)

    def small_stack():
        import resource
        hard = resource.getrlimit(resource.RLIMIT_STACK)[1]
        resource.setrlimit(resource.RLIMIT_STACK, (2 * 2**20, hard))

    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                       preexec_fn=small_stack)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    n, w, w_exact = p.stdout.split("RESULT")[1].split()
    assert int(n) == 90006
    assert abs(float(w) / float(w_exact) - 1) < 1e-5


def test_memory_limit_environment_variable(monkeypatch):
    """FLEXMBS_MEMORY_LIMIT: '1k' is 1000 bytes (a small run is then refused, naming the limit);
    a word that is not a size is a ModelError naming the variable and the value."""
    model, _ = clamped_beam(2)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "1k")
    with pytest.raises(ResourceError, match=r"more than the memory limit \(1 kB\)") as ei:
        fx.simulate(model, 1e-3, 5e-4)
    assert ei.value.available == 1000.0
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "lots")
    with pytest.raises(fx.ModelError, match="FLEXMBS_MEMORY_LIMIT.*'lots'"):
        fx.simulate(model, 1e-3, 5e-4)
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "none")
    assert fx.simulate(model, 1e-3, 5e-4).q.shape == (3, model.ndof)


def test_case_memory_limit_reaches_the_adjoint_and_the_rigid_reference(monkeypatch):
    """[solver] memory_limit reaches every check of a Problem, not only simulate's: with no
    limit (FLEXMBS_MEMORY_LIMIT=none) the adjoint's plan keeps the tape of every state
    (checkpoints None); under a case limit of half that plan's estimate it checkpoints (an
    interval K) and its estimate fits the limit; a case limit of 1 MB refuses the adjoint's
    per-step partials (about 1 GB for fourbar), and one of 1 kB the rigid reference (336 kB),
    each message naming '[solver] memory_limit' as what sets the limit."""
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "none")
    free = Problem("fourbar", gradient_method="adjoint")
    k, est = free._adjoint_plan(free.start, free._timed())
    assert k is None
    half = Problem("fourbar", {"solver.memory_limit": est.total / 2}, gradient_method="adjoint")
    k, est_k = half._adjoint_plan(half.start, half._timed())
    assert k is not None and est_k.total < est.total
    small = Problem("fourbar", {"solver.memory_limit": 1e6}, gradient_method="adjoint")
    with pytest.raises(ResourceError, match=r"more than the memory limit \(1 MB\).*"
                                            r"\[solver\] memory_limit \(bytes\) sets the limit"):
        small.evaluate(small.start, gradient=True)
    tiny = Problem("fourbar", {"solver.memory_limit": 1e3})
    with pytest.raises(ResourceError, match=r"rigid reference.*more than the memory limit "
                                            r"\(1 kB\).*\[solver\] memory_limit"):
        tiny.mechanism.reference


def test_limit_hint_names_where_the_limit_came_from(monkeypatch):
    """The hint of a refused run names what set its limit: SimulationSettings(memory_limit=)
    for a limit given in Python, the environment variable FLEXMBS_MEMORY_LIMIT (and not the
    Python setting) for one from there, [solver] memory_limit for a case's."""
    model, _ = clamped_beam(2)
    with pytest.raises(ResourceError, match=r"SimulationSettings\(memory_limit=bytes\) sets"):
        fx.simulate(model, 1e-3, 5e-4, SimulationSettings(memory_limit=1e3))
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", "1k")
    with pytest.raises(ResourceError, match=r"\(1 kB\): .*\. FLEXMBS_MEMORY_LIMIT sets") as ei:
        fx.simulate(model, 1e-3, 5e-4)
    assert "SimulationSettings" not in str(ei.value)
    monkeypatch.delenv("FLEXMBS_MEMORY_LIMIT")
    p = Problem("fourbar", {"solver.memory_limit": 4e5, "time.t_end": 0.01})
    with pytest.raises(ResourceError, match=r"\[solver\] memory_limit \(bytes\) sets") as ei:
        p.evaluate(p.start, gradient=False)
    assert "SimulationSettings" not in str(ei.value)
