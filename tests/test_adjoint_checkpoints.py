"""Checkpointing of the discrete adjoint's forward run (docs/adjoint.md section 3b): the full
state at every K-th time point instead of the tape of every state; the backward pass re-runs
each segment from its checkpoint with the tape and carries the adjoint state from one segment
to the previous one (flexmbs.analysis.adjoint, fortran/adjoint.f90 ga_adjoint with j_start / adj_in /
adj_out, fortran/generalized_alpha.f90 ga_simulate with ckpt / x_start)."""
import json

import numpy as np
import pytest

from flexmbs.analysis.adjoint import (adjoint_gradient, checkpoint_interval, checkpoint_memory,
                             simulate_for_adjoint)
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings
from flexmbs.analysis.simulate import CHECKPOINT_PART, TAPE_PART, simulate
from flexmbs.errors import ModelError, ResourceError
from flexmbs.problem import ADJOINT_PART, SEGMENT_PART, Problem


def _rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _robot(start, t_end=0.1):
    p = Problem("robot_2dof", {"time.t_end": t_end, "time.start": start})
    mech = p.mechanism
    model = mech.set_design(mech.start)
    q0, qd0 = mech.initial_state()
    kw = dict(settings=SimulationSettings(rho_inf=p.description.time.rho_inf, start=start,
                                          newton="full"),
              initial=InitialConditions(q0=q0, qd0=None if start == "static" else qd0))
    return model, mech.element_property_derivatives(mech.start), kw


def _seeds(run, model, seed):
    """Two functionals: random weights on every coordinate and force at every step, and a
    random final value."""
    nt, nc = run.t.size, run.mu.shape[1]
    rng = np.random.default_rng(seed)
    gq = np.zeros((nt, model.ndof, 2))
    gq[:, :, 0] = rng.standard_normal((nt, model.ndof))
    gq[-1, :, 1] = rng.standard_normal(model.ndof)
    gmu = np.zeros((nt, nc, 2))
    gmu[:, :, 0] = rng.standard_normal((nt, nc))
    return gq, gmu


@pytest.mark.parametrize("start", ["static", "rest"])
def test_checkpointed_gradient_equals_the_full_tape(start):
    """Robot (0.1 s, 200 steps, full Newton) from static equilibrium and from rest: the
    gradients of a weighted sum over every coordinate and force and of a final value with
    checkpoints every 1, 7, 15 (= ceil(sqrt(200)), 'auto') and 500 (one segment) time points
    equal the full tape's to 1e-12 relative: the segments re-run from their checkpoints
    repeat the first run's Newton iterations (measured: identical to the last bit); the
    stored outputs of the checkpointed run are the full run's."""
    model, dprop, kw = _robot(start)
    full = simulate_for_adjoint(model, 0.1, 5e-4, **kw)
    gq, gmu = _seeds(full, model, 5)
    ref = adjoint_gradient(model, full, dprop, gq, gmu)
    for k in (1, 7, "auto", 500):
        run = simulate_for_adjoint(model, 0.1, 5e-4, checkpoints=k, **kw)
        assert run.tape is None and run.checkpoints["every"] == (15 if k == "auto" else k)
        assert np.array_equal(run.q, full.q)
        got = adjoint_gradient(model, run, dprop, gq, gmu)
        for f in range(2):
            assert _rel(got[:, f], ref[:, f]) < 1e-12, (k, f)


def test_checkpointed_gradient_with_step_cuts():
    """Slider-crank press (0.05 s, at most 2 Newton iterations per step: some 300 cuts,
    tests/test_adjoint.py::test_step_cuts): with checkpoints every 3 and 10 time points (a
    segment's tape, room for 8 or a quarter more sub-steps, overflows and is re-run with
    room for every cut) the gradients equal the full tape's to 1e-12 relative (measured:
    identical) and the full tape's equal direct differentiation's (1e-8, test_step_cuts)."""
    p = Problem("slider_crank_press", {"time.t_end": 0.05})
    mech = p.mechanism
    model = mech.set_design(mech.start)
    dprop = mech.element_property_derivatives(mech.start)
    kw = dict(settings=SimulationSettings(newton="full", max_iter=2, validity="off", tol=1e-12))
    full = simulate_for_adjoint(model, 0.05, 5e-4, **kw)
    assert full.stats["step_cuts"] > 100
    gq, gmu = _seeds(full, model, 7)
    ref = adjoint_gradient(model, full, dprop, gq, gmu)
    for k in (3, 10):
        run = simulate_for_adjoint(model, 0.05, 5e-4, checkpoints=k, **kw)
        assert run.stats["step_cuts"] == full.stats["step_cuts"]
        got = adjoint_gradient(model, run, dprop, gq, gmu)
        for f in range(2):
            assert _rel(got[:, f], ref[:, f]) < 1e-12, (k, f)


@pytest.mark.parametrize("start", ["static", "rest"])
def test_problem_with_checkpoints_automatic_newton(start):
    """Problem(checkpoints=...) with the case's automatic Newton (robot, 0.1 s, KS of the
    deviation): the Jacobian and objective gradient with checkpoints every 7 time points and
    every ceil(sqrt(N)) ('auto') equal the full tape's to 1e-9 relative (the step after a
    checkpoint takes a fresh iteration matrix in the first run too, so the re-run repeats its
    iterations; the first run itself then differs from the unchecked one within the Newton
    tolerance: measured 1e-12 on the gradients), and the evaluation reports the interval."""
    ov = {"time.t_end": 0.1, "time.start": start, "constraints.0.over": "ks"}
    p = Problem("robot_2dof", ov)
    ref = p.evaluate(p.start, method="adjoint")
    assert ref.stats["adjoint_checkpoints"] is None
    for k in (7, "auto"):
        q = Problem("robot_2dof", ov, checkpoints=k)
        ev = q.evaluate(q.start, method="adjoint")
        assert ev.stats["adjoint_checkpoints"] == (15 if k == "auto" else 7)
        assert ev.constraints == pytest.approx(ref.constraints, rel=1e-9)
        assert _rel(ev.jacobian, ref.jacobian) < 1e-9


def test_checkpoint_memory_grows_as_the_square_root_of_the_steps():
    """Problem.memory_estimate(method='adjoint', checkpoints='auto') of the robot over 0.5 s
    with N = 2500 and 4 N = 10000 steps (h = 2e-4 and 5e-5; not run): K = ceil(sqrt(N)) = 50
    and 100; the checkpoints hold 8 (N // K + 1) (5 ndof + nc + 3) bytes and one segment's
    tape 8 (K + 1 + max(8, K // 4)) (3 ndof + nc + 1.5) (docs/adjoint.md 3b), together 1.9
    to 2.1 times more at 4 N (sqrt(4) = 2), where the tape of every state grows 4 times
    (to 1 %); the per-step partials are the same with or without checkpoints."""
    est = {}
    for n in (2500, 10000):
        p = Problem("robot_2dof", {"time.t_end": 0.5, "time.h": 0.5 / n,
                                   "constraints.0.over": "ks"})
        cm = p.mechanism.model.compile()
        ndof, nc = cm.ndof, cm.nc
        est[n] = (p.memory_estimate(method="adjoint", checkpoints="auto"),
                  p.memory_estimate(method="adjoint", checkpoints=None))
        k = int(np.ceil(np.sqrt(n)))
        assert est[n][0].checkpoints == k and est[n][1].checkpoints is None
        assert est[n][0].parts[CHECKPOINT_PART] == pytest.approx(
            8.0 * (n // k + 1) * (5 * ndof + nc + 3), rel=1e-14)
        assert est[n][0].parts[SEGMENT_PART] == pytest.approx(
            8.0 * (k + 1 + max(8, k // 4)) * (3 * ndof + nc + 1.5), rel=1e-14)
        assert TAPE_PART not in est[n][0].parts
        assert est[n][0].parts[ADJOINT_PART] == est[n][1].parts[ADJOINT_PART]

    def ck(e):
        return e.parts[CHECKPOINT_PART] + e.parts[SEGMENT_PART]

    ratio = ck(est[10000][0]) / ck(est[2500][0])
    assert 1.9 < ratio < 2.1, ratio
    assert est[10000][1].parts[TAPE_PART] / est[2500][1].parts[TAPE_PART] == \
        pytest.approx(4.0, rel=0.01)


def test_memory_limit_checkpoints_then_refuses(monkeypatch):
    """robot_2dof (0.05 s, KS deviation, automatic Newton): its adjoint needs more with the
    tape of every state than with checkpoints every ceil(sqrt(N)) points, and that more than
    direct differentiation (Problem.memory_estimate). Under FLEXMBS_MEMORY_LIMIT halfway
    (geometric mean) between the tape's and the checkpoints' estimates, evaluate(method=
    'adjoint') runs with checkpoints (the largest interval that fits, at least
    ceil(sqrt(N))) and gives the full tape's gradient (1e-9 relative); halfway between the
    checkpoints' and direct differentiation's it raises ResourceError naming the checkpoints,
    the estimate and method='direct' (required and available set), and direct
    differentiation runs."""
    p = Problem("robot_2dof", {"time.t_end": 0.05, "constraints.0.over": "ks"})
    full = p.memory_estimate(method="adjoint").total
    least = p.memory_estimate(method="adjoint", checkpoints="auto").total
    direct = p.memory_estimate(method="direct").total
    assert full > 1.2 * least and least > 1.05 * direct
    ref = p.evaluate(p.start, method="adjoint")
    assert ref.stats["adjoint_checkpoints"] is None
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", str(int(np.sqrt(full * least))))
    est = p.memory_estimate(method="adjoint")
    assert est.checkpoints >= 10 and est.total <= np.sqrt(full * least)
    ev = p.evaluate(p.start, method="adjoint")
    assert ev.stats["adjoint_checkpoints"] == est.checkpoints
    assert _rel(ev.jacobian, ref.jacobian) < 1e-9
    limit = int(np.sqrt(least * direct))
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", str(limit))
    with pytest.raises(ResourceError, match=r"checkpoints every 10 time points.*need about "
                       r".*memory limit.*method='direct'") as info:
        p.evaluate(p.start, method="adjoint")
    assert info.value.required == pytest.approx(least) and info.value.available == limit
    ev = p.evaluate(p.start, method="direct")
    assert ev.gradient_method == "direct" and np.all(np.isfinite(ev.jacobian))


def test_checkpoint_bad_input():
    """Typed errors naming the argument and the value: checkpoints of 0, 'sqrt' or True
    (Problem, simulate_for_adjoint, simulate), checkpoints with a tape or design
    derivatives."""
    with pytest.raises(ModelError, match="checkpoints must be .*got 0"):
        Problem("robot_2dof", checkpoints=0)
    with pytest.raises(ModelError, match="checkpoints must be .*got 'sqrt'"):
        Problem("robot_2dof", checkpoints="sqrt")
    model, dprop, kw = _robot("rest", 0.01)
    with pytest.raises(ModelError, match="checkpoints must be .*got 'sqrt'"):
        simulate_for_adjoint(model, 0.01, 5e-4, checkpoints="sqrt", **kw)
    with pytest.raises(ModelError, match="checkpoints must be an integer >= 1.*got True"):
        simulate(model, 0.01, 5e-4, checkpoints=True)
    with pytest.raises(ModelError, match="checkpoints= is not allowed with tape=True"):
        simulate(model, 0.01, 5e-4, checkpoints=4, tape=True)
    with pytest.raises(ModelError, match=r"checkpoints= is not allowed .*design derivatives "
                                         r"\(DesignDerivatives.properties"):
        simulate(model, 0.01, 5e-4, derivatives=DesignDerivatives(properties=dprop), checkpoints=4)


def test_checkpoint_interval_fits_the_memory_given():
    """checkpoint_interval(model, N, available): the largest interval whose checkpoints and
    segment tape (checkpoint_memory) fit, at least ceil(sqrt(N)); None when ceil(sqrt(N))
    does not fit."""
    model, _, _ = _robot("rest", 0.01)
    n = 10000
    least = sum(checkpoint_memory(model, n, 100))
    assert checkpoint_interval(model, n) == 100
    assert checkpoint_interval(model, n, 0.99 * least) is None
    for avail in (least, 2 * least, 10 * least):
        k = checkpoint_interval(model, n, avail)
        assert k >= 100 and sum(checkpoint_memory(model, n, k)) <= avail
        assert k == n or sum(checkpoint_memory(model, n, k + 1)) > avail


def test_cli_checkpoints_give_the_gradient_of_the_full_tape(capsys):
    """`flexmbs evaluate ... --gradient --gradient-method adjoint --checkpoints 5 --json`: the constraint
    rows' gradients (the JSON's jacobian) equal those of the full tape (no --checkpoints) to
    1e-9 relative (the segments are re-run from exact states); a bad --checkpoints value is a
    usage error naming the option and the value."""
    from flexmbs.cli.main import main
    args = ["evaluate", "robot_2dof_tapered_tubes", "--set", "time.t_end=0.02",
            "--gradient", "--gradient-method", "adjoint", "--json"]
    assert main(args) == 0
    full = json.loads(capsys.readouterr().out)
    assert main(args + ["--checkpoints", "5"]) == 0
    ck = json.loads(capsys.readouterr().out)
    assert full["gradient_method"] == ck["gradient_method"] == "adjoint"
    a, b = np.array(full["jacobian"]), np.array(ck["jacobian"])
    assert a.shape == (len(full["constraint_names"]), 64)
    assert np.abs(a - b).max() <= 1e-9 * np.abs(a).max()
    assert main(args + ["--checkpoints", "0"]) == 2
    err = capsys.readouterr().err
    assert "--checkpoints" in err and "'0'" in err


def test_adjoint_evaluation_keeps_the_coordinates_asked():
    """evaluate(method='adjoint', store='all') returns its forward run in Evaluation.result
    with every coordinate (what `flexmbs simulate --gradient --out` saves), and storing them
    changes neither the constraints nor their adjoint gradients (1e-12 relative: what is
    stored is not what is solved)."""
    p = Problem("robot_2dof_tapered_tubes", {"time.t_end": 0.02})
    lean = p.evaluate(p.start, method="adjoint")
    full = p.evaluate(p.start, method="adjoint", store="all")
    assert lean.result is None
    assert full.result.q.shape[1] == p.mechanism.model.ndof
    assert np.abs(full.jacobian - lean.jacobian).max() <= 1e-12 * np.abs(lean.jacobian).max()
    assert np.abs(full.constraints - lean.constraints).max() <= 1e-12
