"""One table of the core's status codes for both languages: flexmbs.core.Status is the GA_*
parameters of fortran/generalized_alpha.f90 and flexmbs.core.SolverStatus the LS_* of
fortran/linear_solver.f90, name for name and value for value (read from the Fortran source)."""
import pathlib
import re

import pytest

from flexmbs.core import SolverStatus, Status

FORTRAN = pathlib.Path(__file__).resolve().parents[1] / "fortran"


def _parameters(source, prefix):
    text = (FORTRAN / source).read_text(encoding="utf-8")
    return {m.group(1): int(m.group(2)) for m in
            re.finditer(rf"integer, parameter :: {prefix}_(\w+) = (\d+)", text)}


@pytest.mark.parametrize("source, prefix, table", [("generalized_alpha.f90", "GA", Status),
                                                   ("linear_solver.f90", "LS", SolverStatus)])
def test_python_status_table_is_the_fortran_one(source, prefix, table):
    """Every Fortran code has its Python member (same name without the prefix, same value),
    and nothing more."""
    fortran = _parameters(source, prefix)
    assert fortran, f"no {prefix}_ parameters found in fortran/{source}"
    assert {m.name: int(m) for m in table} == fortran
