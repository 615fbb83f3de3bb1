"""flexmbs: planar flexible multibody simulation and structural optimization of mechanisms.

Public API (explicit):
    Model, Body                  build a mechanism (model.py)
    Material, Circle, Tube, Rectangle, GivenSection   sections (sections.py)
    TimeLaw                      motor and load laws with derivatives (laws.py)
    simulate, Result             generalized-alpha simulation (simulate.py)
    check_tangent, check_iteration_matrix, taylor_test   derivative checkers (checks.py)
    load_case, Case              the paper's mechanisms from cases/*.toml (cases.py)
    FlexmbsError, ModelError, SimulationError, CaseError, ResourceError,
    InvalidResultError, ValidityWarning   exceptions and warnings (errors.py)
"""
from flexmbs.cases import Case, load_case
from flexmbs.checks import check_iteration_matrix, check_tangent, taylor_test
from flexmbs.errors import (CaseError, FlexmbsError, InvalidResultError, ModelError,
                            ResourceError, SimulationError, ValidityWarning)
from flexmbs.laws import TimeLaw
from flexmbs.model import Body, Model
from flexmbs.sections import Circle, GivenSection, Material, Rectangle, Tube
from flexmbs.simulate import Result, simulate

__all__ = [
    "Model", "Body", "Material", "Circle", "Tube", "Rectangle", "GivenSection", "TimeLaw",
    "simulate", "Result", "check_tangent", "check_iteration_matrix", "taylor_test",
    "FlexmbsError", "ModelError", "SimulationError", "CaseError", "ResourceError",
    "InvalidResultError", "ValidityWarning", "load_case", "Case",
]
__version__ = "0.1.0"
