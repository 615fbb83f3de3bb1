"""The discrete adjoint on element-wise designs: the memory of its forward tape and
backward pass against the number of steps, its refusal under a memory limit, and a property
test of adjoint = direct differentiation over random designs (docs/adjoint.md, section 3).
"""
import functools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flexmbs.analysis.simulate import TAPE_PART
from flexmbs.problem import ADJOINT_PART, Problem


def _counts(p):
    cm = p.mechanism.model.compile()
    return cm.ndof, cm.nc, cm.nel


@pytest.mark.parametrize("case", ["robot_2dof_tapered_tubes", "slider_crank_press_tapered"])
def test_adjoint_memory_grows_linearly_with_the_steps(case):
    """Problem.memory_estimate(method='adjoint') at 400 and 800 steps (t_end 0.2 s and 0.4 s,
    h = 5e-4): the tape holds 3 ndof + nc numbers and its step h and grid index (1.5) per
    column, with room for a quarter more sub-steps than steps (N + 1 + N/4 columns, as
    docs/adjoint.md section 3 states), and the backward pass ndof + nc partials per time point
    and aggregated functional (nf = 2: the KS rows); so doubling the steps adds exactly
    8 (5/4) N (3 ndof + nc + 1.5) + 8 N nf (ndof + nc) bytes, nothing of it depending on the
    number of variables. Direct differentiation's estimate has no tape."""
    est, sizes = {}, {}
    for n in (400, 800):
        p = Problem(case, {"time.t_end": n * 5e-4})
        assert p.mechanism.t.size == n + 1 and p.gradient_functionals() == 2
        est[n] = p.memory_estimate(method="adjoint")
        sizes[n] = _counts(p)
        assert TAPE_PART not in p.memory_estimate(method="direct").parts
    ndof, nc, nel = sizes[400]
    assert sizes[800] == sizes[400]
    for n in (400, 800):
        assert est[n].parts[TAPE_PART] == pytest.approx(
            8.0 * (n + 1 + n // 4) * (3 * ndof + nc + 1.5), rel=1e-14)
    d_tape = est[800].parts[TAPE_PART] - est[400].parts[TAPE_PART]
    d_adj = est[800].parts[ADJOINT_PART] - est[400].parts[ADJOINT_PART]
    assert d_tape == pytest.approx(8.0 * 1.25 * 400 * (3 * ndof + nc + 1.5), rel=1e-14)
    assert d_adj == pytest.approx(8.0 * 400 * 2 * (ndof + nc), rel=1e-14)


def test_memory_limit_checkpoints_the_adjoint(monkeypatch):
    """robot_2dof_tapered (16 diameters, 0.05 s, KS deviation): direct differentiation stores
    the derivatives of the 6 coordinates of A and the tip (16 x 6 per step), the adjoint the
    tape of all 3 ndof + nc (~300 per step), so its estimate is the larger one
    (Problem.memory_estimate). Under FLEXMBS_MEMORY_LIMIT halfway (geometric mean) between
    the two, evaluate(method='adjoint') no longer refuses (it did before checkpointing): it
    keeps checkpoints instead of the tape (docs/adjoint.md 3b; the refusal when even they do
    not fit: tests/test_adjoint_checkpoints.py) and its gradient equals direct
    differentiation's to 1e-8 relative, as the full tape's does."""
    p = Problem("robot_2dof_tapered", {"time.t_end": 0.05, "constraints.0.over": "ks"})
    direct = p.memory_estimate(method="direct").total
    adjoint = p.memory_estimate(method="adjoint").total
    assert adjoint > 1.2 * direct
    limit = int(np.sqrt(direct * adjoint))
    monkeypatch.setenv("FLEXMBS_MEMORY_LIMIT", str(limit))
    ev = p.evaluate(p.start, method="adjoint")
    assert ev.gradient_method == "adjoint" and ev.stats["adjoint_checkpoints"] >= 10
    ref = p.evaluate(p.start, method="direct")
    assert ref.gradient_method == "direct"
    assert np.abs(ev.jacobian - ref.jacobian).max() < 1e-8 * np.abs(ref.jacobian).max()


_CASES = ["robot_2dof_tapered_tubes", "slider_crank_press_tapered"]


@functools.lru_cache(maxsize=None)
def _problem(case, t_end, **overrides):
    return Problem(case, {"time.t_end": t_end, **overrides})


@settings(max_examples=6, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(case=st.sampled_from(_CASES), t_end=st.sampled_from([0.02, 0.035, 0.05]),
       u=st.lists(st.floats(0.0, 1.0), min_size=64, max_size=64))
def test_adjoint_equals_direct_on_random_designs(case, t_end, u):
    """Property: on random designs within the bounds (every component drawn between its lower
    and upper bound, the max_step rows free to be violated) of the tapered press (10 rod
    diameters, 5-60 mm) and the hollow tapered robot (64 diameters and walls), over 0.02 to
    0.05 s, the constraint rows agree to the Newton tolerance accumulated over the steps and
    the adjoint Jacobian of the KS rows equals direct differentiation's to 1e-8
    relative per row (the Newton tolerance at 1e-12 for both, as in
    tests/test_adjoint.py::test_stress_responses: the two differ by the tangent taken one
    Newton iteration apart)."""
    p = _problem(case, t_end, **{"solver.tol": 1e-12})
    lo, hi = p.mechanism.lower, p.mechanism.upper
    x = lo + np.asarray(u[:lo.size]) * (hi - lo)
    direct = p.evaluate(x, gradient="used", method="direct")
    adj = p.evaluate(x, gradient="used", method="adjoint")
    assert adj.gradient_method == "adjoint"
    # the two forward runs (direct differentiation's, and the adjoint's, whose states are
    # polished further for its tape) each stop within the Newton tolerance per step: their
    # values may drift apart by up to that tolerance once per step, accumulated over the run
    # (relative to the limits, as the rows are)
    steps = p.mechanism.t.size - 1
    assert adj.constraints == pytest.approx(direct.constraints, rel=1e-10, abs=1e-12 * steps)
    for i, name in enumerate(direct.constraint_names):
        scale = np.abs(direct.jacobian[i]).max()
        assert scale > 0, name
        assert np.abs(adj.jacobian[i] - direct.jacobian[i]).max() <= 1e-8 * scale, name
