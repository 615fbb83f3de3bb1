"""flexmbs: planar flexible multibody simulation and structural optimization of mechanisms.

Public API (explicit):
    Problem, load_problem        a described mechanism with its design variables, responses,
                                 objective and constraints (problem.py; case files: casefile.py,
                                 docs/case-format.md)
    optimize_weakly, optimize_fully, OptimizationResult   the two methods (optimize/)
    Model, Body                  build a mechanism by hand (model.py)
    Material, Circle, Tube, Rectangle, GivenSection   sections (sections.py)
    TimeLaw                      motor and load laws with derivatives (laws.py)
    simulate, Result             generalized-alpha simulation (simulate.py)
    SimulationSettings, InitialConditions, DesignDerivatives   simulate's settings object and
                                 the requests of one run (settings.py)
    simulate_with_error, verify, convergence_check   time-discretisation error estimates,
                                 designs verified at converged resolution (accuracy.py)
    check_tangent, check_iteration_matrix, taylor_test   derivative checkers (checks.py)
    FlexmbsError, ModelError, SimulationError, CaseError, ResourceError,
    InvalidResultError, Interrupted, ValidityWarning, SettingWarning   exceptions and
                                 warnings (errors.py)
    FEASIBILITY_TOL              the one feasibility tolerance (problem.py)
"""
from flexmbs.analysis.accuracy import convergence_check, simulate_with_error, verify
from flexmbs.analysis.checks import check_iteration_matrix, check_tangent, taylor_test
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings
from flexmbs.analysis.simulate import Result, simulate
from flexmbs.errors import (CaseError, FlexmbsError, Interrupted, InvalidResultError, ModelError,
                            ResourceError, SettingWarning, SimulationError, ValidityWarning)
from flexmbs.model.arrays import Body, Model
from flexmbs.model.laws import TimeLaw
from flexmbs.model.sections import Circle, GivenSection, Material, Rectangle, Tube
from flexmbs.optimize import OptimizationResult, optimize_fully, optimize_weakly
from flexmbs.problem import FEASIBILITY_TOL, Problem, load_problem
from flexmbs.version import __version__

__all__ = [
    "__version__",
    "Problem", "load_problem", "optimize_weakly", "optimize_fully", "OptimizationResult",
    "Model", "Body", "Material", "Circle", "Tube", "Rectangle", "GivenSection", "TimeLaw",
    "simulate", "Result", "SimulationSettings", "InitialConditions", "DesignDerivatives",
    "simulate_with_error", "verify", "convergence_check",
    "check_tangent", "check_iteration_matrix", "taylor_test",
    "FlexmbsError", "ModelError", "SimulationError", "CaseError", "ResourceError",
    "InvalidResultError", "Interrupted", "ValidityWarning", "SettingWarning", "FEASIBILITY_TOL",
]
