"""Simulating a mechanism and judging the answer: generalized-alpha simulation and its Result
(simulate.py), design gradients by the adjoint method (adjoint.py), the validity checks of a
result (validity.py), time-discretisation error estimates and verification at converged
resolution (accuracy.py), and derivative checkers (checks.py).

Built on flexmbs.model.arrays and flexmbs.core; below flexmbs.responses and flexmbs.problem.
"""
