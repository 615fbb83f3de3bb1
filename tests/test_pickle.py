"""A Problem sent to another process: pickled and unpickled (a spawn process pool, a Dask
cluster of processes), it evaluates a design to the same numbers, bit for bit, as the Problem
it was copied from (the same description, laws and compiled model: the same arithmetic)."""
from __future__ import annotations

import concurrent.futures
import multiprocessing
import pickle

import numpy as np
import pytest

from flexmbs.model.casefile import available_cases
from flexmbs.problem import Problem

CASES = sorted(available_cases())


def _short(case):
    """The shipped case cut to three time steps (the laws and the model are the case's)."""
    prob = Problem(case)
    return Problem(case, overrides={"time.t_end": 3 * prob.description.time.grid_h})


def _numbers(ev):
    """Every number of an evaluation: objective, constraints, every response's values and,
    with gradients, the objective's gradient and the constraints' Jacobian."""
    extra = [] if ev.jacobian is None else [ev.d_objective, ev.jacobian]
    return [np.atleast_1d(np.asarray(v, float)) for v in
            [ev.objective, ev.constraints] + [ev.values[k] for k in sorted(ev.values)] + extra]


def _assert_same(a, b):
    assert len(a) == len(b)
    for u, v in zip(a, b):
        assert u.shape == v.shape and np.array_equal(u, v, equal_nan=True)


@pytest.mark.parametrize("case", CASES)
def test_pickled_problem_evaluates_bit_for_bit(case):
    """pickle.loads(pickle.dumps(problem)) of every shipped case (three time steps) gives the
    objective, constraints and response values of evaluate(start) equal bit for bit to the
    original's, and so do the gradients when the original had evaluated (and compiled its
    model) before being pickled."""
    prob = _short(case)
    copy = pickle.loads(pickle.dumps(prob))
    _assert_same(_numbers(copy.evaluate(gradient=False)), _numbers(prob.evaluate(gradient=False)))
    first = _numbers(prob.evaluate())
    _assert_same(_numbers(pickle.loads(pickle.dumps(prob)).evaluate()), first)


def _evaluate_numbers(prob):
    return _numbers(prob.evaluate(gradient=False))


def test_problem_evaluated_in_a_spawned_process_bit_for_bit():
    """One evaluation of the four-bar (three time steps) in a ProcessPoolExecutor with the
    'spawn' start method (a fresh interpreter: the Problem travels pickled) equals the serial
    evaluation bit for bit."""
    prob = _short("fourbar")
    with concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn")) as pool:
        remote = pool.submit(_evaluate_numbers, prob).result(timeout=300)
    _assert_same(remote, _evaluate_numbers(prob))
