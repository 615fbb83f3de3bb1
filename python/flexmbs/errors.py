"""Exceptions raised by flexmbs. Every message names the input or the time step at fault."""

__all__ = ["FlexmbsError", "ModelError", "SimulationError", "CaseError", "ResourceError",
           "InvalidResultError", "Interrupted", "ValidityWarning", "SettingWarning"]


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


class ResourceError(FlexmbsError, MemoryError):
    """A run would not fit (memory or disk), or an allocation in the core failed.

    Raised before the run where an estimate shows it cannot fit, with the estimate and what to
    change (fewer stored outputs, a coarser step, fewer elements, the KLU solver).

    Attributes
    ----------
    required : float or None
        Bytes the run needs (estimate), or the size of the failed allocation.
    available : float or None
        Bytes available (memory or disk) when the estimate was compared.
    """

    def __init__(self, message, *, required=None, available=None):
        super().__init__(message)
        self.required = required
        self.available = available


class InvalidResultError(FlexmbsError, RuntimeError):
    """A simulation converged numerically but its result lies outside the model's validity
    (e.g. axial strains far beyond a linear-elastic material's range); the message names the
    check, the body or element, the value and the limit."""


class Interrupted(KeyboardInterrupt):
    """A run ended on request before it finished: Ctrl-C (SIGINT), SIGTERM on the command line
    (`signal` names it), or the cancel flag of a compiled run set by another thread
    (flexmbs.core.run_interruptible). A KeyboardInterrupt, so that every cleanup written for
    Ctrl-C runs for it too; nothing of the unfinished run is returned or stored.

    Attributes
    ----------
    signal : int or None
        The signal that ended the run (signal.SIGINT, signal.SIGTERM), or None.
    time : float or None
        Simulated time (s) the compiled run had reached.
    """

    def __init__(self, message="interrupted", *, signal=None, time=None):
        super().__init__(message)
        self.signal = signal
        self.time = time


class ValidityWarning(UserWarning):
    """A result is suspicious but not certainly wrong (a validity check near its limit)."""


class SettingWarning(UserWarning):
    """A setting is allowed but likely not what was meant (e.g. a static start, which assumes
    rest, with a drive already moving at t = 0); the message says what to change."""
