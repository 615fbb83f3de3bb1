"""One Problem evaluated from several threads at once: every evaluation is its own design's.

A design's sections belong to the call (Mechanism.design_model), never to the problem's shared
model, so threads evaluating different designs of one Problem must each get exactly (bit for
bit) what the same design gives evaluated alone in one thread.
"""
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from flexmbs.problem import Problem

#: eight four-bar designs (mm) inside the bounds of cases/fourbar.toml, all different
DESIGNS = [[40.0 + 5 * k, 60.0 + 3 * k, 20.0 + 2 * k] for k in range(8)]


def _key(ev):
    return (ev.values["mass"], ev.values["deviation_A"].copy(), ev.d_objective.copy())


def test_one_problem_from_four_threads_gives_each_design_its_single_threaded_values():
    """32 evaluations of 8 designs of one four-bar Problem from 4 threads: each design's mass,
    deviation history and mass gradient equal (exactly) its evaluation alone, one thread."""
    prob = Problem("fourbar", overrides={"time.t_end": 0.04})
    alone = [_key(prob.evaluate(x, gradient=True)) for x in DESIGNS]
    order = [k % len(DESIGNS) for k in range(32)]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda k: _key(prob.evaluate(DESIGNS[k], gradient=True)), order))
    wrong = [k for k, g in zip(order, got)
             if not (g[0] == alone[k][0] and np.array_equal(g[1], alone[k][1])
                     and np.array_equal(g[2], alone[k][2]))]
    assert not wrong, f"{len(wrong)} of 32 threaded evaluations differ from their design's"
    # the designs differ: a mix-up could not go unseen
    assert len({a[0] for a in alone}) == len(DESIGNS)


def test_evaluating_leaves_the_shared_model_alone():
    """An evaluation of another design does not change the problem's model: its element
    properties stay those of the start design (set at construction)."""
    prob = Problem("fourbar", overrides={"time.t_end": 0.04})
    before = prob.mechanism.model.element_properties().copy()
    prob.evaluate(DESIGNS[3], gradient=False)
    np.testing.assert_array_equal(prob.mechanism.model.element_properties(), before)
