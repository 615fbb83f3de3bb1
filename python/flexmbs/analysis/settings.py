"""SimulationSettings: the one object holding how `simulate` integrates, iterates, solves and
checks (the integrator's, Newton's, the linear solver's and the run's settings), and the two
small groups of what a single run is asked to compute (InitialConditions, DesignDerivatives).

The split: a *setting* is a choice of method or accuracy that the same study keeps from run to
run and that a case file can state ([time] and [solver], flexmbs.model.description); it is
validated once, recorded whole in every Result (Result.settings) and in the JSON output, and
covered by the fingerprints of stored results. The *requests* of a run depend on the design
or on the caller's purpose rather than on the method: the initial state (q0, qd0: a design's
[initial] deformation), the design derivatives (the design's property derivatives and which
coordinates to differentiate), the adjoint's tape or checkpoints, and a non-uniform step grid
chosen by flexmbs.analysis.adaptive. They stay arguments of `simulate`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from flexmbs.analysis.validity import ValidityLimits
from flexmbs.errors import ModelError
from flexmbs.resources import memory_limit as _memory_limit

__all__ = ["SimulationSettings", "RunSettings", "InitialConditions", "DesignDerivatives",
           "NEWTON", "LINEAR_SOLVERS", "STARTS", "check_newton_settings", "check_flag"]

#: Newton strategies (SimulationSettings.newton).
NEWTON = ("full", "reuse", "auto")
#: Linear solvers (SimulationSettings.solver).
LINEAR_SOLVERS = ("auto", "dense", "klu")
#: Starts of a run (SimulationSettings.start).
STARTS = ("rest", "static")


_MISSING = object()
_ABSENT = object()


def _real(v):
    return (isinstance(v, (int, float, np.floating, np.integer))
            and not isinstance(v, (bool, np.bool_)))


def check_newton_settings(rho_inf, tol, max_iter, max_cuts):
    """The numeric settings of the integrator and Newton: typed ModelErrors naming the
    setting, its value and its range."""
    if not (_real(rho_inf) and 0.0 <= rho_inf <= 1.0):
        raise ModelError(f"rho_inf must lie in [0, 1], got {rho_inf!r}")
    if not (_real(tol) and math.isfinite(tol) and tol > 0):
        raise ModelError(f"tol must be > 0 and finite, got {tol!r}")
    for name, v, least in (("max_iter", max_iter, 1), ("max_cuts", max_cuts, 0)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < least:
            raise ModelError(f"{name} must be an integer >= {least}, got {v!r}")


def check_flag(name, value):
    """ModelError unless value is True or False."""
    if not isinstance(value, (bool, np.bool_)):
        raise ModelError(f"{name} must be True or False, got {value!r}")


def _check_choice(name, value, allowed):
    if not isinstance(value, str) or value not in allowed:
        words = ", ".join(map(repr, allowed[:-1])) + f" or {allowed[-1]!r}"
        raise ModelError(f"{name} must be {words}, got {value!r}")


@dataclass(frozen=True)
class SimulationSettings:
    """How `flexmbs.simulate` integrates, iterates, solves and checks a run (one table of
    every setting; the case file's [time] and [solver] tables set them, docs/case-format.md).

    ============  ===========  =======================================================
    field         default      meaning
    ============  ===========  =======================================================
    rho_inf       0.5          generalized-alpha's spectral radius at infinite frequency,
                               in [0, 1] (1: no numerical damping; eqs. 3-6)
    start         'rest'       'rest': the reference configuration (or q0) moving with the
                               rigid velocity field the drives impose at t = 0; 'static':
                               static equilibrium under the loads at t = 0
    newton        'auto'       Newton strategy 'auto', 'full' or 'reuse' (eq. 7; see
                               flexmbs.analysis.simulate.simulate)
    tol           1e-10        Newton tolerance on max|dq| / max(1, max|q_ref|, element
                               length), > 0
    max_iter      20           Newton iterations per step, >= 1
    max_cuts      6            step halvings before a step fails, >= 0
    solver        'auto'       linear solver 'auto', 'dense' (LAPACK LU) or 'klu'
                               (SuiteSparse KLU; 'auto' takes KLU)
    kscale        None         k of eq. (1), > 0; None: the mean diagonal of the iteration
                               matrix
    penalty       None         p of eq. (1), > 0; None: as kscale
    polish        False        with newton 'auto'/'reuse': every step converged to the
                               rounding level (what the discrete adjoint needs)
    validity      'warn'       checks of the result: 'warn', 'error', 'off' or a
                               flexmbs.analysis.validity.ValidityLimits (strain, drift and
                               energy limits); a mode string is kept as its ValidityLimits
    memory_limit  None         bytes the run may take (checked before it runs); None:
                               FLEXMBS_MEMORY_LIMIT, else the memory available; math.inf:
                               no check
    store         'all'        coordinates kept at every step: 'all' or a list of node ids
                               or Body objects
    ============  ===========  =======================================================

    Every field is validated when the object is made: a ModelError names the field, the
    value and what is allowed. The object is immutable; `replace(**changes)` gives a
    validated copy with some fields changed, `to_dict()` its JSON-able form.
    """
    rho_inf: float = 0.5
    start: str = "rest"
    newton: str = "auto"
    tol: float = 1e-10
    max_iter: int = 20
    max_cuts: int = 6
    solver: str = "auto"
    kscale: float | None = None
    penalty: float | None = None
    polish: bool = False
    validity: object = "warn"
    memory_limit: float | None = None
    store: object = "all"

    def __post_init__(self):
        check_newton_settings(self.rho_inf, self.tol, self.max_iter, self.max_cuts)
        _check_choice("start", self.start, STARTS)
        if not isinstance(self.newton, str) or self.newton not in NEWTON:
            raise ModelError(f"newton must be one of {', '.join(map(repr, NEWTON))}, "
                             f"got {self.newton!r}")
        _check_choice("solver", self.solver, LINEAR_SOLVERS)
        for name in ("kscale", "penalty"):
            v = getattr(self, name)
            if v is not None and not (_real(v) and math.isfinite(v) and v > 0):
                raise ModelError(f"{name} must be a positive finite number or None "
                                 f"(automatic), got {v!r}")
        check_flag("polish", self.polish)
        object.__setattr__(self, "validity", ValidityLimits.coerce(self.validity))
        if self.memory_limit is not None:
            _memory_limit(self.memory_limit)       # ModelError naming memory_limit
        store = self.store
        if isinstance(store, str):
            if store != "all":
                raise ModelError(f"store must be 'all' or a list of nodes/bodies, got {store!r}")
        elif isinstance(store, (list, tuple, np.ndarray)):
            object.__setattr__(self, "store", tuple(
                int(s) if isinstance(s, (int, np.integer)) and not isinstance(s, bool) else s
                for s in store))
        else:
            raise ModelError(f"store must be 'all' or a list of nodes/bodies, got {store!r}")

    @classmethod
    def coerce(cls, value):
        """SimulationSettings from simulate's `settings` argument: an instance, a dict of its
        fields (to_dict's output among them: validity as a table of ValidityLimits's fields,
        memory_limit 'inf'), or None (the defaults)."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            value = dict(_known(cls, value, "settings"))
            # to_dict's JSON forms: validity as its limits' table, memory_limit 'inf'
            if isinstance(value.get("validity"), dict):
                value["validity"] = ValidityLimits(**_known(ValidityLimits, value["validity"],
                                                            "settings validity"))
            if isinstance(value.get("memory_limit"), str) and \
                    value["memory_limit"].strip().lower() == "inf":
                value["memory_limit"] = math.inf
            return cls(**value)
        raise ModelError(f"settings must be a SimulationSettings, a dict of its fields or None, "
                         f"got {type(value).__name__}")

    def replace(self, **changes):
        """A validated copy with `changes` (field names) applied."""
        _known(type(self), changes, "SimulationSettings.replace")
        return dataclasses.replace(self, **changes)

    def to_dict(self):
        """The settings as JSON-able values: validity as its limits' dict, store as 'all' or
        a list of node ids (a Body as its name), memory_limit None when unset and 'inf'
        when disabled."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "validity":
                v = dataclasses.asdict(v)
            elif f.name == "store" and not isinstance(v, str):
                v = [getattr(s, "name", s) if not isinstance(s, (int, np.integer)) else int(s)
                     for s in v]
            elif f.name == "memory_limit" and v is not None and not math.isfinite(v):
                v = "inf"
            elif isinstance(v, (np.floating, np.integer, np.bool_)):
                v = v.item()
            out[f.name] = v
        return out

    #: the keys of the former dict Result.settings (the deprecated dict reading)
    _DICT_KEYS = ("h", "t_end", "rho_inf", "start", "solver", "newton", "tol", "max_iter",
                  "max_cuts", "kscale", "penalty", "q0", "qd0", "polish", "steps")

    def _as_dict(self, key, default=_MISSING):
        """The deprecated dict reading of Result.settings: the value the former dict held
        under key (kscale and penalty 0.0 when automatic; q0, qd0 the run's initial state,
        steps its non-uniform step grid or None), with a DeprecationWarning naming the
        attribute that replaces it."""
        import warnings
        where = {"q0": "Result.initial.q0", "qd0": "Result.initial.qd0",
                 "steps": "Result.steps"}.get(key, f"Result.settings.{key}")
        warnings.warn(f"Result.settings[{key!r}] is deprecated: use {where} "
                      "(Result.settings is a SimulationSettings)", DeprecationWarning,
                      stacklevel=3)
        run = getattr(self, "_run", {})
        if key in self._DICT_KEYS and key in run:
            return run[key]
        if key in self._DICT_KEYS and key not in ("q0", "qd0", "steps") and hasattr(self, key):
            v = getattr(self, key)
            return float(v or 0.0) if key in ("kscale", "penalty") else v
        if default is _MISSING:
            raise KeyError(key)
        return default

    def __getitem__(self, key):
        """Deprecated: the former dict Result.settings; use the attribute."""
        return self._as_dict(key)

    def get(self, key, default=None):
        """Deprecated: the former dict Result.settings' get; use the attribute."""
        return self._as_dict(key, default)

    def __contains__(self, key):
        """Deprecated: a key of the former dict Result.settings."""
        return self._as_dict(key, _ABSENT) is not _ABSENT


@dataclass(frozen=True)
class RunSettings(SimulationSettings):
    """The settings of one run as `Result.settings` records them: SimulationSettings with
    'auto' solver and newton resolved to what ran (solver 'dense' or 'klu'), and the run's
    step h (s) and end time t_end (s)."""
    h: float | None = None
    t_end: float | None = None


def _known(cls, values, where):
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ModelError(f"{where}: unknown setting(s) {', '.join(unknown)}; the settings are "
                         f"{', '.join(sorted(names))}")
    return values


@dataclass(frozen=True)
class InitialConditions:
    """The initial state of a run (simulate(initial=...)): coordinates q0 (default: the
    reference configuration) and velocities qd0 (default: the velocity field of the start,
    SimulationSettings.start), arrays of ndof numbers each, or None."""
    q0: object = None
    qd0: object = None


@dataclass(frozen=True)
class DesignDerivatives:
    """The design derivatives a run is asked for (simulate(derivatives=...)).

    properties : array (5, nel, nv): d[EA, kGA, EI, rhoA, rhoI]/dp of every element for nv
        design variables p; Result.dq holds dq/dp.
    dofs : coordinates (0-based) whose derivatives are kept (default: the stored ones).
    constraint_forces : also d(mu)/dp of every constraint row in Result.dmu (nt, nc, nv).
    A request without properties asks for nothing (constraint_forces=True then is a
    ModelError of simulate).
    """
    properties: object = None
    dofs: object = None
    constraint_forces: bool = False

    @classmethod
    def coerce(cls, value):
        """DesignDerivatives from simulate's `derivatives` argument: an instance, an array
        of the properties' derivatives alone, or None."""
        if value is None or isinstance(value, cls):
            return value
        return cls(properties=value)
