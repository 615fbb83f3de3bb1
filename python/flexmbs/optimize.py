"""Optimization of mechanism components, on any problem (`flexmbs.problem.Problem`, a case
file or the name of a shipped case):

    optimize_weakly        the weakly coupled method: ESL cycles (paper 5.3; weakly.py)
    optimize_fully         the fully coupled method: dynamic response optimization
                           (paper 4, 5.4; fully.py, optimizer loops in loops.py)
    multistart             optimize_fully from N quasi-random starts, in parallel (multistart.py)
    OptimizationResult     result of either method (result.py)
    HistoryWriter          per-cycle/iteration JSON-lines history written as the run goes
    read_history           read such a file back
    FullyOptions, SQPOptions, MMAOptions, SLSQPOptions, NLoptOptions, WeaklyOptions,
    MultistartOptions      the options of the methods and optimizers (flexmbs.model.options)
"""
from flexmbs.methods.fully import optimize_fully
from flexmbs.methods.multistart import multistart
from flexmbs.methods.result import HistoryWriter, OptimizationResult, read_history
from flexmbs.methods.weakly import optimize_weakly
from flexmbs.model.options import (FullyOptions, MMAOptions, MultistartOptions, NLoptOptions,
                                   SLSQPOptions, SQPOptions, WeaklyOptions)

__all__ = ["optimize_weakly", "optimize_fully", "multistart", "OptimizationResult",
           "HistoryWriter", "read_history", "FullyOptions", "SQPOptions", "MMAOptions",
           "SLSQPOptions", "NLoptOptions", "WeaklyOptions", "MultistartOptions"]
