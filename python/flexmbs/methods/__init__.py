"""The two optimization methods over a flexmbs.problem.Problem: the weakly coupled method,
equivalent static load cycles (weakly.py, esl.py, cycles.py), and the fully coupled method,
dynamic response optimization (fully.py), also from many starts at once (multistart.py); every
run ends by verifying its design at converged resolution (verified.py) and returns an
OptimizationResult with its history (result.py).

Built on flexmbs.problem and flexmbs.optimizers.
"""
