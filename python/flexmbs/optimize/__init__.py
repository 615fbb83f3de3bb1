"""Optimization of mechanism components: the weakly coupled method (ESL cycles, paper 5.3)
and the objects shared with the fully coupled method.

    optimize_weakly        weakly coupled cycles (weakly.py)
    optimize_problem_weakly  the same on any general-format Problem (problem_weakly.py)
    optimize_fully         fully coupled dynamic response optimization (fully.py)
    optimize_problem       the fully coupled method on a general-format Problem (problem_fully.py;
                           NLopt optimizers in library.py, docs/optimizers.md)
    multistart             optimize_problem from N quasi-random starts (multistart.py)
    OptimizationResult     result of either method (result.py)
    HistoryWriter          per-cycle/iteration JSON-lines history written as the run goes
    read_history           read such a file back
"""
from flexmbs.optimize.fully import optimize_fully
from flexmbs.optimize.problem_fully import optimize_problem
from flexmbs.optimize.result import HistoryWriter, OptimizationResult, read_history
from flexmbs.optimize.weakly import optimize_weakly
from flexmbs.optimize.problem_weakly import optimize_problem_weakly
from flexmbs.optimize.multistart import multistart

__all__ = ["optimize_weakly", "optimize_problem_weakly", "optimize_fully", "optimize_problem",
           "multistart", "OptimizationResult", "HistoryWriter", "read_history"]
