"""Exceptions raised by flexmbs. Every message names the input or the time step at fault."""

__all__ = ["FlexmbsError", "ModelError", "SimulationError", "CaseError"]


class FlexmbsError(Exception):
    """Base class of all flexmbs errors."""


class ModelError(FlexmbsError, ValueError):
    """A mechanism, a section, a law or a setting is invalid (raised before any simulation)."""


class CaseError(ModelError):
    """A case file is malformed or incomplete; the message names the file and the key."""


class SimulationError(FlexmbsError, RuntimeError):
    """The simulation could not proceed.

    Attributes
    ----------
    time : float or None
        Time (s) of the step that failed.
    residual : float or None
        Last scaled Newton increment (or residual) at failure.
    iterations : int or None
        Newton iterations done on the failed step.
    code : int
        Status code of the Fortran core.
    """

    def __init__(self, message, *, time=None, residual=None, iterations=None, code=None):
        super().__init__(message)
        self.time = time
        self.residual = residual
        self.iterations = iterations
        self.code = code
