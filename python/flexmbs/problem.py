"""A sizing problem: design variables, responses, objective and constraints of a described
mechanism; `Problem.evaluate(x)` gives every value and its gradient for a design.

>>> from flexmbs.problem import Problem
>>> prob = Problem("fourbar")              # cases/fourbar.toml; or a path, a dict, a Description
>>> ev = prob.evaluate([69.85, 87.61, 37.22])                 # Table 3, weakly coupled design
>>> round(ev.values["mass"], 2), round(ev.values["deviation_A"].max() * 1e3, 2)   # kg, mm
(20.7, 0.98)

Gradients are exact (direct differentiation of the discrete generalized-alpha equations in the
Fortran core, one extra multi-right-hand-side solve per step); only the coordinates the
responses need are stored and differentiated, the multipliers' derivatives (motor torques,
joint reactions) are asked for only when such a response is evaluated, and nothing is
differentiated when ``gradient=False``. ``evaluate(x, method="adjoint")`` computes the gradients
of the objective and constraint rows by the discrete adjoint instead (docs/adjoint.md): 2.2-3
simulations in all whatever the number of variables (measured from 4 to 2048);
``method="auto"`` picks it when the variables outnumber the aggregated rows
(`Problem.gradient_method`).
"""
from __future__ import annotations

import time as _time
import warnings
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from flexmbs.analysis.accuracy import estimate_errors, needs_fourth_level
from flexmbs.analysis.modes import modal_check
from flexmbs.analysis.adaptive import choose_steps, subdivide
from flexmbs.analysis.adjoint import (adjoint_gradient, adjoint_memory, checkpoint_interval,
                                      checkpoint_memory)
from flexmbs.analysis.simulate import CHECKPOINT_PART, TAPE_PART, memory_estimate, simulate
from flexmbs.analysis.settings import DesignDerivatives, InitialConditions, SimulationSettings
from flexmbs.analysis.validity import ValidityLimits
from flexmbs.errors import CaseError, ModelError, ResourceError, SettingWarning
from flexmbs.model.casefile import description_from_dict, read_description
from flexmbs.model.description import Beam, Deviation, Description, Mass, Station
from flexmbs.model.mechanism import Mechanism
from flexmbs.output import max_gradient_warning, resolution, run_statistics
from flexmbs.output import units as unit_table
from flexmbs.resources import CaseLimit, format_bytes, limit_hint, limit_source, memory_limit
from flexmbs.responses.aggregate import aggregate, aggregate_weights
from flexmbs.responses.kinds import kind_of
from flexmbs.responses.station import locate

__all__ = ["Problem", "Evaluation", "load_problem", "simulation_settings", "constraint_rows",
           "GRADIENT_METHODS", "FEASIBILITY_TOL", "is_feasible"]

#: The one feasibility tolerance of flexmbs: a design is feasible when its largest normalised
#: constraint value g (relative to the limits, g <= 0 asked) is <= FEASIBILITY_TOL. Evaluation,
#: the command line's summaries, every optimizer's verdict and stopping test and the
#: reproduction's checks use it (docs/json-output.md).
FEASIBILITY_TOL = 1e-6


def is_feasible(max_violation, tol=None):
    """A largest constraint value g is feasible: None (no constraint) or g <= tol
    (FEASIBILITY_TOL unless given)."""
    return max_violation is None or float(max_violation) <= (FEASIBILITY_TOL if tol is None
                                                             else tol)

#: Gradient methods of Problem.evaluate (see Problem.gradient_method).
GRADIENT_METHODS = ("direct", "adjoint", "auto")
#: 'auto' takes the adjoint when the variables outnumber the aggregated functionals this many
#: times, and are at least ADJOINT_MIN_VARIABLES: below, direct differentiation's extra
#: right-hand sides (the factorization is Newton's) cost less than the adjoint's forward run
#: with every state stored and its factorization per step
ADJOINT_MARGIN = 4
ADJOINT_MIN_VARIABLES = 16     # docs/adjoint.md 4e: direct is faster below 8-16 variables


#: The part of an adjoint's MemoryEstimate (Problem.memory_estimate) holding the per-step
#: partials of the backward pass (flexmbs.analysis.adjoint.adjoint_memory).
ADJOINT_PART = "adjoint's per-step partials"
#: The part of a checkpointed adjoint's MemoryEstimate holding one segment's tape (the
#: checkpoints are flexmbs.analysis.simulate.CHECKPOINT_PART; flexmbs.analysis.adjoint.checkpoint_memory).
SEGMENT_PART = "adjoint's segment tape"
_DEFAULT = object()      # memory_estimate(checkpoints=...): the problem's


#: what an object needs to stand for a Problem in the optimizers (e.g. an analytic test problem)
PROBLEM_INTERFACE = ("evaluate", "variables", "lower", "upper", "start", "description",
                     "mechanism")


def load_problem(case, overrides=None):
    """A Problem from a case: a path, the name of a shipped case (cases/), a dict or a
    Description; a Problem, or an object with its interface (PROBLEM_INTERFACE), as it is
    when no overrides are given."""
    if not overrides and (isinstance(case, Problem)
                          or all(hasattr(case, a) for a in PROBLEM_INTERFACE)):
        return case
    return Problem(case, overrides=overrides)


def _description(case, overrides=None):
    if isinstance(case, Problem):
        case = case.description
    if isinstance(case, Description):
        if overrides:
            case = case.model_dump(by_alias=True, exclude_unset=True)
        else:
            return case
    if isinstance(case, dict):
        return description_from_dict(case, overrides=overrides)
    if isinstance(case, (str, Path)):
        return read_description(case, overrides)
    raise CaseError(f"a problem needs a case file path, a case name, a dict or a Description, "
                    f"got {type(case).__name__}")


@dataclass
class Evaluation:
    """Every response of one design, with gradients w.r.t. the design (user units).

    values[name]: (nt,) history or a float; gradients[name]: (nt, nv) or (nv,) (None without
    gradients). objective, d_objective: the objective's value and gradient. constraints: the
    normalised constraint values g <= 0 (one per time step for 'every_step'; then the linear
    smoothness rows of element-wise design variables), jacobian (ng, nv), constraint_names
    (the response of each row; 'VARIABLE max_step' for a smoothness row).
    """
    x: np.ndarray
    t: np.ndarray
    values: dict
    gradients: dict
    objective: float | None
    d_objective: np.ndarray | None
    constraints: np.ndarray
    jacobian: np.ndarray | None
    constraint_names: list
    stats: dict = field(default_factory=dict)
    wall_time: float = 0.0
    #: how the gradients were computed: 'direct' (forward differentiation, every history's
    #: gradient), 'adjoint' (the aggregated rows only: gradients of histories are None) or
    #: None without gradients
    gradient_method: str | None = None
    #: the simulation itself (flexmbs.analysis.simulate.Result) when evaluate was asked to store
    #: coordinates (store='all' or nodes), else None
    result: object = field(default=None, repr=False)
    #: with evaluate(..., error=True): {response: flexmbs.analysis.accuracy.ErrorEstimate} of each
    #: value (a history: of its maximum, with point-wise errors), else None
    errors: dict | None = None
    #: with error=True: the objective's ErrorEstimate, and {response: ErrorEstimate} of each
    #: constrained response's largest normalised value g (relative to its limit)
    objective_error: object = None
    constraint_errors: dict | None = None
    #: CPU seconds of the process during the evaluation (with wall_time)
    cpu_time: float = 0.0
    #: the design variables' names (the order of x) and, as `flexmbs.output.units` and
    #: `flexmbs.output.resolution`, the units of every number and the discretisation used
    #: (set by Problem.evaluate; empty for an Evaluation made otherwise)
    variables: list = field(default_factory=list)
    units: dict = field(default_factory=dict)
    resolution: dict = field(default_factory=dict)

    @property
    def feasible(self):
        """All constraints hold: the largest g <= FEASIBILITY_TOL."""
        return is_feasible(self.max_violation if self.constraints.size else None)

    def gradient_warnings(self):
        """Sentences on the gradients of the histories' maxima that are not differentiable
        (two peaks within flexmbs.output.PEAK_TIE_REL of each other with other gradients:
        `flexmbs.output.max_gradient_warning`)."""
        out = []
        for name, v in self.values.items():
            g = self.gradients.get(name)
            if g is not None and np.ndim(v) == 1:
                w = max_gradient_warning(name, v, g, self.t,
                                         (self.units.get("responses") or {}).get(name))
                if w:
                    out.append(w)
        return out

    @property
    def max_violation(self):
        """Largest constraint value (<= 0 when feasible)."""
        return float(self.constraints.max()) if self.constraints.size else -np.inf

    def to_json(self):
        """A JSON-serialisable dict (histories as their maximum and time of maximum), its
        keys documented in docs/json-output.md."""
        out = {"design": self.x.tolist(), "objective": self.objective,
               "feasible": self.feasible,
               "max_violation": self.max_violation if self.constraints.size else None,
               "feasibility_tol": FEASIBILITY_TOL,
               "variables": list(self.variables), "units": dict(self.units),
               "resolution": dict(self.resolution),
               "run": run_statistics(self.stats, self.wall_time, self.cpu_time),
               "warnings": self.gradient_warnings(),
               "responses": {}}
        for k, v in self.values.items():
            g = self.gradients.get(k)
            if np.ndim(v) == 0:
                out["responses"][k] = {"value": float(v),
                                       "gradient": None if g is None else np.asarray(g).tolist()}
            else:
                j = int(np.argmax(v))
                out["responses"][k] = {"max": float(v[j]), "t_at_max": float(self.t[j]),
                                       "gradient_of_max": None if g is None else g[j].tolist()}
            if self.errors is not None and k in self.errors:
                # of the value, or of the history's maximum
                out["responses"][k]["error"] = self.errors[k].to_json()
        if self.errors is not None:
            out["objective_error"] = (None if self.objective_error is None
                                      else self.objective_error.to_json())
            out["constraint_errors"] = {k: e.to_json()
                                        for k, e in (self.constraint_errors or {}).items()}
        if self.d_objective is not None:
            out["d_objective"] = self.d_objective.tolist()
        # the constraint rows g <= 0 and their gradients (with the adjoint, the only gradients
        # there are besides the objective's)
        out["constraints"] = np.asarray(self.constraints, float).tolist()
        out["constraint_names"] = list(self.constraint_names)
        out["jacobian"] = None if self.jacobian is None else np.asarray(self.jacobian).tolist()
        out["gradient_method"] = self.gradient_method
        return out


class Problem:
    """Design variables + responses + objective + constraints of a described mechanism.

    Parameters
    ----------
    case : path, str, dict or Description
        A case file, the name of a shipped case (``"fourbar"``, see
        `flexmbs.model.casefile.available_cases`), a parsed case dict or a Description.
    overrides : dict, optional
        Case keys to replace before validation, by dotted path, e.g.
        ``{"time.t_end": 0.66, "bodies.arm1.elements": 8}`` (`flexmbs.model.casefile.apply_overrides`).
    gradient_method : {'direct', 'adjoint', 'auto'}, default 'direct'
        How `evaluate` computes gradients unless told otherwise (its `method`): what an
        optimizer calling evaluate(x, gradient=True) gets.
    checkpoints : None, 'auto' or int, default None
        The adjoint's forward run (docs/adjoint.md 3b): None keeps the tape of every state
        when it fits in the memory limit and checkpoints otherwise (every K time points, K
        the largest that fits: `flexmbs.analysis.adjoint.checkpoint_interval`); 'auto' always
        checkpoints, every ceil(sqrt(N)) of N steps (about the least memory); K (>= 1) every
        K time points (a K beyond the N steps: the initial state only, as K = N).
        Checkpointing costs about one more forward run.

    Notes
    -----
    Evaluation is re-entrant: `evaluate` and `simulate` put a design's sections into a model
    of their own (Mechanism.design_model, sharing the structure, its compiled arrays and KLU
    analysis), never into the problem's shared `mechanism.model`, so several threads may
    evaluate different designs of one Problem at once and each gets its design's values.
    A Problem can be pickled (its laws are module-level callables, its compiled model is
    rebuilt after unpickling), so a spawned process pool or a Dask cluster of processes can
    take one; the copy evaluates a design to the same numbers, bit for bit
    (tests/test_pickle.py).
    """

    def __init__(self, case, overrides=None, gradient_method="direct", checkpoints=None):
        self.description = _description(case, overrides)
        self.mechanism = Mechanism(self.description)
        self._resp = {r.name: r for r in self.description.responses}
        _check_method(gradient_method, "gradient_method")
        self.default_gradient_method = gradient_method
        _check_checkpoints(checkpoints)
        self.adjoint_checkpoints = checkpoints
        #: the SimulationSettings of every run of the problem, from the case's [time] and
        #: [solver] (`simulation_settings`); a run sets its store (and the adjoint's polish)
        self.settings = simulation_settings(self.description)
        self._refined = {}
        # the frozen step grid of an adaptive case (time.h = "auto"): chosen once, under the
        # mechanism's lock of its lazily built parts (re-entrant: the pilots build them too)
        self._steps = None
        self._grid_info = {}

    # ------------------------------------------------------------------ adaptive steps
    def steps(self):
        """The non-uniform step grid (times) of an adaptive case (time.h = "auto"), None for a
        fixed step. Chosen by flexmbs.analysis.adaptive.choose_steps at the start design when first
        needed and then frozen: every design runs on the same grid, so that the responses are
        smooth in the design and their derivatives exact, and a problem built anew (a batch's
        worker) has the same grid whichever design it simulates first. `adapt(x)` chooses it
        at another design."""
        if not self.description.time.adaptive:
            return None
        if self._steps is None:
            with self.mechanism._lazy:
                if self._steps is None:
                    self._steps = self._choose(None)
        return self._steps

    def adapt(self, x=None, info=None):
        """Choose the step grid of an adaptive case afresh at design x (between restarts of
        an optimization, or to verify a result) and freeze it; returns it. `info`: as
        flexmbs.analysis.adaptive.choose_steps's."""
        if not self.description.time.adaptive:
            raise ModelError('adapt: the case has a fixed step (time.h is a number, not "auto")')
        with self.mechanism._lazy:
            self._steps = self._choose(x, info)
            self._refined = {}
        return self._steps

    def _choose(self, x, info=None):
        info = {} if info is None else info
        steps = choose_steps(self, x, info=info)
        self._grid_info = info
        return steps

    def values_on(self, x, steps):
        """The response histories (name -> value) of design x simulated on the step grid
        `steps` (times; outputs on the response grid), without gradients: the pilot runs of
        flexmbs.analysis.adaptive."""
        mech = self.mechanism
        x = mech.start if x is None else mech.design_values(x)
        timed = self._timed()
        if not timed:
            return {}
        model, t_end, h, kw = self._run(x, False, timed, None, steps=steps)
        result = simulate(model, t_end, h, **kw)
        return {n: self._response(self._resp[n], x, result, False, model=model)[0] for n in timed}

    def refined(self, factor):
        """The same problem with the time step h / factor (factor a power of two; built once
        per factor and kept): the finer levels of error estimates and verifications
        (flexmbs.analysis.accuracy)."""
        if (isinstance(factor, bool) or not isinstance(factor, (int, np.integer))
                or factor < 1 or factor & (factor - 1)):
            raise ModelError(f"refined: factor must be a power of two (1, 2, 4, ...), "
                             f"got {factor!r}")
        if factor == 1:
            return self
        if factor not in self._refined:
            ts = self.description.time
            if ts.adaptive:
                # the frozen step grid with every step divided, outputs on a grid as fine
                fine = Problem(self.description, overrides={"time.output": ts.grid_h / factor,
                                                            "time.t_end": self.mechanism.t_end},
                               gradient_method=self.default_gradient_method,
                               checkpoints=self.adjoint_checkpoints)
                fine._steps = subdivide(self.steps(), factor)
            else:
                fine = Problem(self.description, overrides={"time.h": ts.h / factor,
                                                            "time.t_end": self.mechanism.t_end},
                               gradient_method=self.default_gradient_method,
                               checkpoints=self.adjoint_checkpoints)
            self._refined[factor] = fine
        return self._refined[factor]

    def grid_summary(self):
        """What an adaptive case's frozen grid is (a record's `grid`): steps (its number),
        tol, rtol, h_min and h_max (s, its shortest and longest step), and as the pilots
        estimate it (flexmbs.analysis.adaptive.choose_steps): estimated_error (the responses'
        error in tolerances, at most 1 when the tolerance is reached), tolerance_reached, and
        saturated (the fraction of the run where the tolerance asks for steps shorter than
        the shortest allowed, shortest_step); None for a fixed step."""
        steps = self.steps()
        if steps is None:
            return None
        ts, dh = self.description.time, np.diff(steps)
        out = dict(steps=int(dh.size), tol=ts.tol, rtol=ts.rtol, h_min=float(dh.min()),
                   h_max=float(dh.max()))
        info = self._grid_info
        if "estimated_error" in info:
            out.update(estimated_error=info["estimated_error"],
                       tolerance_reached=bool(info["estimated_error"] <= 1.0),
                       saturated=info["saturated"], shortest_step=info["shortest_step"])
        return out

    def refined_mesh(self):
        """(the same problem with twice the elements of every beam, None), or (None, why
        not): element-wise design variables are tied to the elements (flexmbs.analysis.accuracy's
        convergence check)."""
        d = self.description
        elementwise = [v.name for v in d.design if v.elementwise]
        if elementwise:
            return None, (f"element-wise design variables ({', '.join(elementwise)}) are "
                          f"tied to the elements")
        beams = {b.name: b.elements for b in d.bodies if isinstance(b, Beam)}
        if not beams:
            return None, "the case has no beam"
        return Problem(d, overrides={f"bodies.{n}.elements": 2 * e for n, e in beams.items()},
                       gradient_method=self.default_gradient_method,
                       checkpoints=self.adjoint_checkpoints), None

    # ------------------------------------------------------------------ design space
    @property
    def variables(self):
        return list(self.mechanism.variables)

    @property
    def lower(self):
        return self.mechanism.lower.copy()

    @property
    def upper(self):
        return self.mechanism.upper.copy()

    @property
    def start(self):
        return self.mechanism.start.copy()

    # ------------------------------------------------------------------ simulation
    def point(self, body, at):
        """A body's named point as its node id, or a station {body, s}
        (flexmbs.model.description.Station) as a flexmbs.responses.station.StationPoint: the
        points the response kinds read (flexmbs.responses.kinds)."""
        if isinstance(at, Station):
            return locate(self.mechanism.model, at.body, at.s)
        return self.mechanism.node[(body, at)]

    def _kind(self, r):
        """The ResponseKind of response r (flexmbs.responses.kinds, by its description class)."""
        kind = kind_of(r)
        if kind is None:
            raise ModelError(f"response {r.name!r}: type {r.type!r} cannot be evaluated")
        return kind

    def _timed(self):
        """The names of the responses that are histories of a simulation (not a mass)."""
        return [n for n, r in self._resp.items() if self._kind(r).timed]

    def _nodes_needed(self, names):
        nodes = set()
        for n in names:
            r = self._resp[n]
            nodes.update(self._kind(r).nodes(self, r))
        return sorted(nodes)

    def _needs_forces(self, names):
        return any(self._kind(self._resp[n]).forces for n in names)

    def _run(self, x, gradient, responses, store, differentiate=None, tape=False,
             checkpoints=None, steps=None):
        """(model, t_end, h, keywords of `simulate`) of a simulation of design x (see
        `simulate`); steps: a step grid instead of the problem's (`steps`)."""
        mech = self.mechanism
        x = mech.start if x is None else mech.design_values(x)
        model = mech.design_model(x)      # this call's sections: the shared model untouched
        names = list(self._resp) if responses is None else list(responses)
        diff = names if differentiate is None else list(differentiate)
        nodes = self._nodes_needed(names)
        ts = self.description.time
        forces = self._needs_forces(diff)
        dnodes = self._nodes_needed(diff)
        differentiated = bool(mech.variables) and (
            bool(tape or checkpoints) or (gradient and bool(dnodes or forces)))
        settings = self.settings
        q0, qd0 = mech.start_state(x, gradient=differentiated,      # [initial], if any
                                     static=partial(_static_state, h=ts.grid_h,
                                                    settings=settings))
        kw = dict(initial=InitialConditions(q0=q0, qd0=None if ts.start == "static" else qd0))
        if tape:     # the discrete adjoint's forward run: every state kept, converged fully
            kw.update(tape=True)
            settings = settings.replace(polish=True)
        elif checkpoints:     # ... or the full state every `checkpoints` time points
            kw.update(checkpoints=int(checkpoints))
            settings = settings.replace(polish=True)
        if store is None:
            # only what the responses read: the multipliers (motor torques, joint reactions)
            # are kept at every step anyway, so without a node to read one node's coordinates
            # are enough (the core keeps at least one coordinate)
            store = nodes if nodes else [0]
        kw["settings"] = settings.replace(store=store)
        if steps is None:
            steps = self.steps()
        if steps is not None:
            kw["steps"] = steps
        if gradient and (dnodes or forces) and mech.variables:
            # the core needs at least one sensitivity coordinate: node 0's when only the
            # multipliers' derivatives are wanted
            dofs = np.array([3 * n + k for n in (dnodes or [0]) for k in range(3)])
            kw["derivatives"] = DesignDerivatives(
                properties=mech.element_property_derivatives(x), dofs=dofs,
                constraint_forces=forces)
        return model, mech.t_end, mech.h, kw

    def animate(self, result, path, *, evaluation=None, **options):
        """Write a simulated motion of this problem (`simulate(x, store='all')`) as a film,
        .gif or .mp4 (flexmbs.visual.animation.animate: every body, the deflection magnified
        over the rigid reference, coloured by a response, the constrained histories of
        `evaluation` underneath). Returns flexmbs.visual.animation.Animation."""
        from flexmbs.visual.animation import animate      # matplotlib: loaded when drawing
        return animate(self, result, path, evaluation=evaluation, **options)

    def to_vtk(self, result, path, *, frames=None):
        """Write a simulated motion of this problem (`simulate(x, store='all')`) as a ParaView
        time series, a .pvd file and a folder of .vtu frames (flexmbs.visual.export.to_vtk).
        Returns (pvd path, vtu paths, steps)."""
        from flexmbs.visual.export import to_vtk           # meshio: loaded when exporting
        return to_vtk(self, result, path, frames=frames)

    def simulate(self, x=None, *, gradient=False, responses=None, store=None,
                 differentiate=None, tape=False, checkpoints=None):
        """Simulate design x (default: start); with gradient=True the design derivatives of
        the coordinates the responses need (all responses, or `responses`; or only those of
        the responses named in `differentiate`), and those of the constraint multipliers
        (Result.dmu) if a torque or reaction response is among them.

        store: None (default) keeps only the coordinates the responses read (the points of
        deviation responses, the nodes of stressed beams; one node when only motor torques or
        joint reactions are asked, which come from the multipliers); 'all' or a list of nodes
        as in `flexmbs.analysis.simulate`. tape=True: the discrete adjoint's forward run (every
        (sub-)step's converged state kept, Newton converged fully: flexmbs.analysis.adjoint);
        checkpoints=K instead: the full state at every K-th time point only (its segments
        are re-run by flexmbs.analysis.adjoint.adjoint_gradient).

        The result's `design_model` is the model of design x that was simulated
        (Mechanism.design_model: the problem's shared model is not changed, so that several
        threads may simulate different designs of one problem at once)."""
        model, t_end, h, kw = self._run(x, gradient, responses, store, differentiate, tape,
                                        checkpoints)
        result = simulate(model, t_end, h, **kw)
        result.design_model = model
        result.design = np.array(
            self.mechanism.start if x is None else self.mechanism.design_values(x), float)
        return result

    def memory_estimate(self, x=None, gradient=True, *, responses=None, store=None,
                        method=None, checkpoints=_DEFAULT):
        """The memory (flexmbs.resources.MemoryEstimate) of the simulation that
        `evaluate(x, gradient, method)` runs (gradient and method as there; of
        `simulate(x, ...)` with `responses` or `store`),
        without running it; None when no response needs a simulation. What is stored over
        the time grid is the responses' coordinates only (see `simulate`). With gradients by
        the adjoint: its forward run's (the tape of every step, flexmbs.analysis.simulate.TAPE_PART)
        and the backward pass's per-step partials (ADJOINT_PART, flexmbs.analysis.adjoint.adjoint_memory);
        checkpointed (when the tape does not fit, or as `checkpoints` asks: as Problem's
        checkpoints, default the problem's), the checkpoints (flexmbs.analysis.simulate.CHECKPOINT_PART)
        and one segment's tape (SEGMENT_PART) instead of the tape
        (flexmbs.analysis.adjoint.checkpoint_memory); est.checkpoints tells the interval (None: the
        tape of every state)."""
        if responses is None:
            responses = self._timed()
            if not responses and store is None:
                return None
        want = self._gradient_names(gradient) if self.mechanism.variables else []
        if want and self.gradient_method(method) == "adjoint":
            return self._adjoint_plan(x, responses, store, checkpoints)[1]
        model, t_end, h, kw = self._run(x, bool(want), responses, store,
                                        [n for n in responses if n in want])
        return memory_estimate(model, t_end, h, **kw)

    # ------------------------------------------------------------------ responses
    def _response(self, r, x, result, gradient, dprop=None, model=None):
        """Value and gradient (or None) of response r at design x on simulation `result`;
        dprop: mechanism.element_property_derivatives(x) when already computed (Mass);
        model: the model of design x (mechanism.design_model(x)) when already made."""
        kind = self._kind(r)
        if model is None and kind.design_model:
            model = self.mechanism.design_model(x)
        return kind.value(self, r, x, result, gradient, model, dprop)

    def _partials(self, r, x, result, model, nc):
        """Value (nt,) of a history response r on the adjoint's forward run and its partials
        at every step, all steps at once, as `Partials`: with respect to the coordinates it
        reads, the constraint multipliers and (a stress, through its section depth) the
        design variables (its kind's `partials`)."""
        return self._kind(r).partials(self, r, x, result, model, nc)

    def used_responses(self):
        """Names of the responses the objective and the constraints use."""
        d = self.description
        used = ([d.objective.response] if d.objective is not None else []) + \
            [c.response for c in d.constraints]
        return [n for n in self._resp if n in used]

    def _gradient_names(self, gradient):
        """The responses whose gradients `evaluate(gradient=...)` asks for."""
        if isinstance(gradient, str):
            if gradient != "used":
                raise ModelError(f"gradient must be True, False, 'used' or a list of response "
                                 f"names, got {gradient!r}")
            return self.used_responses()
        if isinstance(gradient, (list, tuple, set, frozenset)):
            unknown = [g for g in gradient if g not in self._resp]
            if unknown:
                raise ModelError(f"gradient: unknown response(s) {unknown!r}; the responses are "
                                 f"{', '.join(self._resp)}")
            return [n for n in self._resp if n in gradient]
        return list(self._resp) if gradient else []

    def gradient_functionals(self):
        """Number of aggregated time functionals of the objective and the constraints (rows of
        a history aggregated over time, 'every_step' rows counting one per time step): the
        right-hand sides of an adjoint pass."""
        t = self.mechanism.t
        n = 0
        obj = self.description.objective
        if obj is not None and self._kind(self._resp[obj.response]).timed:
            n += 1
        for c in self.description.constraints:
            if not self._kind(self._resp[c.response]).timed:
                continue
            bounds = (c.upper is not None) + (c.lower is not None)
            n += bounds * (t.size if c.over == "every_step" else 1)
        return n

    def gradient_method(self, method=None):
        """The method `evaluate` uses for gradients: 'direct' or 'adjoint'; 'auto' takes the
        adjoint when the design variables outnumber the aggregated functionals
        (`gradient_functionals`) by ADJOINT_MARGIN times and at least ADJOINT_MIN_VARIABLES;
        None: the problem's default_gradient_method."""
        if method is None:
            method = self.default_gradient_method
        _check_method(method)
        if method != "auto":
            return method
        nv, nf = len(self.mechanism.variables), self.gradient_functionals()
        if nf and nv >= ADJOINT_MIN_VARIABLES and nv > ADJOINT_MARGIN * nf:
            return "adjoint"
        return "direct"

    def gradient_method_reason(self, method=None):
        """The method `gradient_method` takes and why, for people: e.g. "adjoint (auto: 64
        design variables, 2 aggregated rows)"."""
        chosen = self.gradient_method(method)
        given = self.default_gradient_method if method is None else method
        if given != "auto":
            return f"{chosen} (as asked)"
        nv, nf = len(self.mechanism.variables), self.gradient_functionals()
        rule = (f"the adjoint from {ADJOINT_MIN_VARIABLES} variables and more than "
                f"{ADJOINT_MARGIN} x the aggregated rows")
        return (f"{chosen} (auto: {nv} design variable{'s' * (nv != 1)}, {nf} aggregated "
                f"row{'s' * (nf != 1)}; {rule})")

    def evaluate(self, x=None, gradient=True, method=None, store=None, error=False):
        """Every response, the objective and the constraints at design x (user units).

        gradient : True (every response's gradient), False (none: nothing is differentiated),
            'used' (those of the objective's and the constraints' responses) or a list of
            response names: only those gradients are computed, and the simulation
            differentiates only the coordinates and multipliers they read. d_objective and
            the constraints' jacobian are given when the gradients they need are.
        method : {'direct', 'adjoint', 'auto'} or None (the problem's gradient_method,
            'direct' unless given)
            How gradients are computed (`gradient_method`): direct differentiation (the
            gradient of every history, Evaluation.gradients), or the discrete adjoint
            (flexmbs.analysis.adjoint: the objective's and constraints' rows only, for 2.2-3
            simulations in all whatever the number of variables; the histories'
            gradients are None). Evaluation.gradient_method tells which was used.
        store : None (default: only the coordinates the responses read) or as `simulate`'s
            ('all', or a list of nodes): those coordinates are kept too, and the run is
            returned in Evaluation.result (one simulation for the responses and for a plot or
            a file of the motion). Given when no response needs a simulation (a case without
            responses, or with mass responses only), the motion is simulated all the same.
        error : False (default), True or 2
            True: also estimate every value's time-discretisation error (flexmbs.analysis.accuracy:
            the design simulated again at h/2 and h/4, without gradients; about 6 more
            simulations' time; and at h/8, 8 more, when a value's changes fall but not
            clearly at second order) into Evaluation.errors, objective_error and
            constraint_errors, with a verdict on whether each value is in its asymptotic
            range; 2: h/2 only (about 2 more simulations' time, no verdict)."""
        if error is not False:
            return self._evaluate_with_error(x, gradient, method, store, error)
        t0, c0 = _time.perf_counter(), _time.process_time()
        return self._described(self._evaluate(x, gradient, method, store, t0), c0)

    def _described(self, ev, c0):
        """ev with its CPU time since c0, the variables' names, the units of its numbers and
        the resolution (flexmbs.output)."""
        ev.cpu_time = _time.process_time() - c0
        ev.variables = self.variables
        ev.units = unit_table(self)
        ev.resolution = resolution(self)
        return ev

    def _evaluate(self, x, gradient, method, store, t0):
        mech = self.mechanism
        x = mech.start if x is None else mech.design_values(x)
        want = self._gradient_names(gradient) if mech.variables else []
        gradient = bool(want)
        timed = self._timed()
        chosen = self.gradient_method(method)
        if gradient and timed and chosen == "adjoint":
            return self._evaluate_adjoint(x, timed, t0, store)
        # the motion is simulated when a response needs it, or when store= asks for it
        result = self.simulate(x, gradient=gradient and bool(timed), responses=timed,
                               store=store, differentiate=[n for n in timed if n in want]) \
            if timed or store is not None else None
        model = mech.design_model(x) if result is None else result.design_model
        values, grads = {}, {}
        for name, r in self._resp.items():
            values[name], grads[name] = self._response(r, x, result, name in want, model=model)
        t = mech.t
        f = df = None
        obj = self.description.objective
        if obj is not None:
            f, df = _scalar(values[obj.response], grads[obj.response], obj.over, None, t)
        with_jac = gradient and all(c.response in want for c in self.description.constraints)
        cons, jac, names, _ = constraint_rows(self.description, values, grads, t,
                                              len(mech.variables), with_jac)
        cons, jac, names = with_linear_rows(mech, x, cons, jac, names)
        return Evaluation(x=x, t=t, values=values,
                          gradients={k: v for k, v in grads.items() if k in want},
                          objective=f, d_objective=df if gradient else None, constraints=cons,
                          jacobian=jac, constraint_names=names,
                          stats=_stats(result),
                          wall_time=_time.perf_counter() - t0,
                          gradient_method="direct" if gradient else None,
                          result=None if store is None else result)

    def _evaluate_with_error(self, x, gradient, method, store, error):

        if error is True:
            levels = 3
        elif not isinstance(error, bool) and error in (2, 3):
            levels = int(error)
        else:
            raise ModelError(f"evaluate: error must be False, True (h, h/2, h/4) or 2 (h, h/2), "
                             f"got {error!r}")
        t0, c0 = _time.perf_counter(), _time.process_time()
        # every coordinate kept: the modes at states of the motion (flexmbs.analysis.modes)
        ev = self.evaluate(x, gradient=gradient, method=method,
                           store="all" if store is None else store)
        if not any(np.ndim(v) for v in ev.values.values()):
            ev.result = None if store is None else ev.result
            return ev            # nothing simulated: nothing has a time-discretisation error
        evs = [ev] + [self.refined(2 ** k).evaluate(ev.x, gradient=False)
                      for k in range(1, levels)]
        ts = self.description.time
        h = ts.grid_h
        # judged at the ladder's finest step (flexmbs.analysis.modes)
        unresolved = self.modal_check(ev.x, ev.result).unresolved(h / 2 ** (levels - 1),
                                                                    ts.rho_inf)
        if store is None:
            ev.result = None
        obj = self.description.objective
        seen = dict(unresolved=unresolved,
                    objective_response=None if obj is None else obj.response)
        est = estimate_errors(evs, [h / 2 ** k for k in range(levels)], **seen)
        if levels == 3 and needs_fourth_level([*est[0].values(), est[1], *est[2].values()]):
            # a ratio that falls but not clearly at second order: h/8 confirms or refutes it
            evs.append(self.refined(8).evaluate(ev.x, gradient=False))
            est = estimate_errors(evs, [h / 2 ** k for k in range(4)], **seen)
        ev.errors, ev.objective_error, ev.constraint_errors = est
        ev.wall_time = _time.perf_counter() - t0
        ev.cpu_time = _time.process_time() - c0
        return ev

    def modal_check(self, x=None, result=None, times=None):
        """The lowest vibration modes of design x at the start, the middle and the end of its
        motion, and which responses see them (flexmbs.analysis.modes.modal_check), from
        `result` when it kept every coordinate of that design's run, else from a run of
        its own. Responses that need no simulation (a mass) are left out."""
        full = result is not None and getattr(result, "design_model", None) is not None and \
            np.array_equal(result.dofs, np.arange(result.design_model.compile().ndof))
        if not full:
            result = self.simulate(x, store="all")
        nodes = {name: self._nodes_needed([name]) for name, r in self._resp.items()
                 if r.type != "mass"}
        ref = self.mechanism.reference
        rigid = (ref.q, ref.qd) if ref.q.shape == result.q.shape else None
        return modal_check(result.design_model, result, nodes, times, rigid=rigid)

    def _adjoint_plan(self, x, responses, store=None, checkpoints=_DEFAULT, run=None):
        """(K, MemoryEstimate) of the adjoint's runs: K None for the tape of every state,
        else the checkpoint interval (see Problem's `checkpoints`; as the problem's unless
        given). When nothing fits, K is ceil(sqrt(N)), about the least memory. run: the
        forward run's `_run(x, False, responses, store, tape=True)` when already made (the
        design is then set once per evaluation)."""
        if checkpoints is _DEFAULT:
            checkpoints = self.adjoint_checkpoints
        _check_checkpoints(checkpoints)
        if run is None:
            run = self._run(x, False, responses, store, tape=True)
        model, t_end, h, kw = run
        est = memory_estimate(model, t_end, h, **kw)
        cm = model.compile()
        # the integration steps: the response grid's, or those of a non-uniform step grid
        steps = kw.get("steps")
        nsteps = self.mechanism.t.size - 1 if steps is None else len(steps) - 1
        est.parts[ADJOINT_PART] = adjoint_memory(cm.ndof, cm.nc, nsteps + 1,
                                                 self.gradient_functionals(), cm.nel)
        if checkpoints is None:
            avail = memory_limit(self.settings.memory_limit)
            if est.total <= avail:
                est.checkpoints = None
                return None, est
            rest = est.total - est.parts[TAPE_PART]
            k = checkpoint_interval(model, nsteps, avail - rest) or \
                checkpoint_interval(model, nsteps)
        elif checkpoints == "auto":
            k = checkpoint_interval(model, nsteps)
        else:
            k = int(checkpoints)
        del est.parts[TAPE_PART]
        est.parts[CHECKPOINT_PART], est.parts[SEGMENT_PART] = checkpoint_memory(model, nsteps, k)
        est.checkpoints = k
        return k, est

    def _check_adjoint_memory(self, x, timed, run=None):
        """The checkpoint interval of the adjoint's forward run (None: the tape of every
        state; `_adjoint_plan`), or ResourceError, naming what to change, when its memory
        (the tape, or the checkpoints and one segment's tape, and the backward pass's
        per-step partials) exceeds the memory limit (the settings' memory_limit: [solver]
        memory_limit, else FLEXMBS_MEMORY_LIMIT, else the memory available)."""
        k, est = self._adjoint_plan(x, timed, run=run)
        limit = self.settings.memory_limit
        need, avail = est.total, memory_limit(limit)
        if need <= avail:
            return k
        nt, nf = self.mechanism.t.size, self.gradient_functionals()
        what = "the tape of every state" if k is None else \
            f"checkpoints every {k} time points, one segment's tape"
        raise ResourceError(
            f"evaluate(method='adjoint'): {what} and the per-step partials of "
            f"{nf} functionals over {nt} time points need about {format_bytes(need)} "
            f"({est.largest()}), more than {limit_source(limit)} ({format_bytes(avail)}): use "
            "method='direct' (gradient_method='direct', --gradient-method direct: no tape), a "
            "coarser step h or a shorter t_end, or fewer functionals (constraints aggregated "
            "over time, over = 'ks' or 'pnorm', instead of 'every_step': one per step)"
            + ("" if k is not None else ", or checkpoints ('auto' or an interval)")
            + f". {limit_hint(limit, setting='[solver] memory_limit')}",
            required=need, available=avail)

    def _evaluate_adjoint(self, x, timed, t0, store=None):
        """evaluate() with the gradients of the objective and constraint rows by the discrete
        adjoint (its forward run keeps the tape of every (sub-)step).

        The responses of the objective and the constraints are evaluated on the run with
        their partial derivatives at every step, all steps at once (`_partials`: with respect
        to the few coordinates each reads, the multipliers and, for a stress, the design
        directly). The aggregation weights of each row over time come from
        constraint_weights; weights times partials, scattered into (nt, ndof, rows) and
        (nt, nc, rows), are the adjoint's right-hand sides
        (flexmbs.analysis.adjoint.adjoint_gradient)."""
        mech = self.mechanism
        run = self._run(x, False, timed, store, tape=True)     # the design set once
        ckpt = self._check_adjoint_memory(x, timed, run)
        model, t_end, h, kw = run
        cm = model.compile()
        if ckpt is not None:      # the full state every ckpt time points instead of the tape
            kw = dict(kw, tape=False, checkpoints=int(ckpt))
        result = simulate(model, t_end, h, **kw)
        result.design = np.array(x, float)
        result.stats["adjoint_checkpoints"] = ckpt
        t = mech.t
        nt, nc, nv = t.size, result.mu.shape[1], len(mech.variables)
        dprop = mech.element_property_derivatives(x)
        used = set(self.used_responses())
        values, partials, grads = {}, {}, {}
        for name, r in self._resp.items():
            if not self._kind(r).timed:
                values[name], grads[name] = self._response(r, x, None, True, dprop, model)
                continue
            grads[name] = np.zeros((nt, nv))
            if name in used:
                values[name], partials[name] = self._partials(r, x, result, model, nc)
            else:
                values[name] = self._response(r, x, result, False, model=model)[0]
        cons, jac, names, _ = constraint_rows(self.description, values, grads, t, nv, True)
        obj = self.description.objective
        f = df = None
        if obj is not None:
            f, df = _scalar(values[obj.response], grads[obj.response], obj.over, None, t)
        wrows = constraint_weights(self.description, values, t)
        if obj is not None:
            wobj = _scalar_weights(values[obj.response], obj.over, t)
        rows = [(names[i], wrows[i]) for i in range(len(names))]
        if obj is not None:
            rows.append((obj.response, wobj))
        live = [k for k, (n, w) in enumerate(rows) if n in partials and np.any(w)]
        out = np.zeros((len(rows), nv))
        if live:
            gq = np.zeros((nt, cm.ndof, len(live)))
            gmu = np.zeros((nt, nc, len(live)))
            steps = np.arange(nt)[:, None, None]
            for n in dict.fromkeys(rows[k][0] for k in live):
                # every live row of response n at once: weights over time W (nt, rows)
                idx = np.array([i for i, k in enumerate(live) if rows[k][0] == n])
                W = np.column_stack([rows[live[i]][1] for i in idx])
                p = partials[n]
                seed = p.dq[:, :, None] * W[:, None, :]
                if p.dofs.ndim == 1:
                    gq[np.ix_(np.arange(nt), p.dofs, idx)] += seed
                else:
                    at = (steps, p.dofs[:, :, None], idx[None, None, :])
                    if (p.dofs[:, 1:] == p.dofs[:, :1]).any():
                        # a stress row padded to the widest element repeats its first
                        # coordinate: add every seed (np.add.at, 7x slower than +=)
                        np.add.at(gq, at, seed)
                    else:
                        gq[at] += seed
                if p.dmu is not None:
                    gmu[:, :, idx] += p.dmu[:, :, None] * W[:, None, :]
                if p.design is not None:
                    out[np.asarray(live)[idx]] += W.T @ p.design
            out[live] += adjoint_gradient(model, result, dprop, gq, gmu,
                                          memory_limit=self.settings.memory_limit).T
        jac = jac + out[:len(names)]
        if obj is not None:
            df = np.asarray(df, float) + out[-1]
        cons, jac, names = with_linear_rows(mech, x, cons, jac, names)
        return Evaluation(x=x, t=t, values=values,
                          gradients={n: (None if n in timed else g) for n, g in grads.items()},
                          objective=f, d_objective=df, constraints=cons, jacobian=jac,
                          constraint_names=names, stats=_stats(result),
                          wall_time=_time.perf_counter() - t0, gradient_method="adjoint",
                          result=None if store is None else result)


    # ------------------------------------------------------------------ summaries
    def design_mass(self, x, values=None):
        """Mass (kg) of design x: the objective's value when the objective is a mass response
        (taken from `values` when given), else the mass of every beam."""
        x = self.mechanism.design_values(x)
        obj = self.description.objective
        if obj is not None and isinstance(self._resp[obj.response], Mass):
            if values is not None and obj.response in values:
                return float(values[obj.response])
            return float(self._response(self._resp[obj.response], x, None, False)[0])
        return float(self._response(Mass(name="mass", type="mass"), x, None, False)[0])

    def constrained_deviation(self, values):
        """The step-by-step largest of the constrained deviation responses (m) in `values`
        (an Evaluation's values), or None when no deviation is constrained."""
        constrained = {c.response for c in self.description.constraints}
        devs = [np.asarray(values[r.name], float) for r in self.description.responses
                if isinstance(r, Deviation) and r.name in constrained and r.name in values]
        return np.max(devs, axis=0) if devs else None

    def deviation_limit(self):
        """The smallest upper limit (m) of the constrained deviation responses, or None."""
        limits = [c.upper for c in self.description.constraints
                  if c.upper is not None and isinstance(self._resp[c.response], Deviation)]
        return min(limits) if limits else None



def _stats(result):
    """An Evaluation's stats: the simulation's (Result.stats) with its wall_time (s); {}
    without a simulation."""
    return {} if result is None else dict(result.stats, wall_time=result.wall_time)


def _check_checkpoints(checkpoints, name="checkpoints"):
    ok = checkpoints is None or (isinstance(checkpoints, str) and checkpoints == "auto") or (
        isinstance(checkpoints, (int, np.integer)) and not isinstance(checkpoints, bool)
        and checkpoints >= 1)
    if not ok:
        raise ModelError(f"{name} must be None (checkpoints only when the tape does not fit), "
                         f"'auto' or an integer >= 1 (time points between checkpoints), got "
                         f"{checkpoints!r}")


def _check_method(method, name="method"):
    if not isinstance(method, str) or method not in GRADIENT_METHODS:
        raise ModelError(f"{name} must be one of {', '.join(map(repr, GRADIENT_METHODS))}, "
                         f"got {method!r}")


def _bounds(description):
    """(constraint, bound, sign, scale) of every bound of the description's constraints, in
    row order: the upper bound (sign 1) before the lower (sign -1); scale |bound| (1 for 0).
    The one normalisation of `constraint_rows` and `constraint_weights`."""
    for c in description.constraints:
        for bound, sign in ((c.upper, 1.0), (c.lower, -1.0)):
            if bound is not None:
                yield c, bound, sign, (abs(bound) if bound != 0 else 1.0)


def constraint_rows(description, values, gradients, t, nv, gradient=True):
    """The normalised constraint rows g <= 0 of a description from response values.

    values[name], gradients[name]: a response's history (nt,) or scalar and its gradient
    ((nt, nv), (nv,) or None). A bound b gives g = sign (r - b) / |b| (|b| = 1 for b = 0),
    aggregated over time as the constraint asks ('every_step': one row per step).

    Returns
    -------
    g : (ng,) values; jacobian : (ng, nv) or None; names : the response of each row;
    groups : (ng,) index of the (constraint, bound) each row comes from.
    """
    g_rows, j_rows, names, groups = [], [], [], []
    for c, bound, sign, s in _bounds(description):
        v, dv = values[c.response], gradients.get(c.response)
        # g = sign (r - bound) / |bound| <= 0, aggregated over time as asked
        r = sign * np.asarray(v, float) / s
        dr = None if dv is None or not gradient else sign * np.asarray(dv, float) / s
        if np.ndim(r):
            r, dr = aggregate(r, dr, c.over, parameter=c.parameter, t=t, window=c.window)
        g = np.atleast_1d(r) - sign * bound / s
        groups += [len(g_rows)] * g.size
        g_rows.append(g)
        names += [c.response] * g.size
        if dr is not None:
            j_rows.append(np.atleast_2d(dr))
    cons = np.concatenate(g_rows) if g_rows else np.zeros(0)
    jac = (np.vstack(j_rows) if j_rows else np.zeros((0, nv))) if gradient else None
    return cons, jac, names, np.asarray(groups, int)


def constraint_weights(description, values, t):
    """The weights over time of the rows of `constraint_rows`: (ng, nt), row i's gradient is
    weights[i] @ (the gradient of its response's history); zero rows for scalar responses.
    What the adjoint's right-hand sides need, without identity gradients (O(nt) per row)."""
    nt = np.asarray(t).size
    out = []
    for c, _, sign, s in _bounds(description):
        r = sign * np.asarray(values[c.response], float) / s
        if np.ndim(r):
            _, w = aggregate_weights(r, c.over, parameter=c.parameter, t=t, window=c.window)
            out.append((sign / s) * w.reshape(w.shape[0], nt, -1).sum(axis=2))
        else:
            out.append(np.zeros((1, nt)))
    return np.vstack(out) if out else np.zeros((0, nt))


def _scalar_weights(v, how, t):
    """The weights over time of `_scalar(v, dv, how, None, t)`'s gradient (zeros: a scalar)."""
    nt = np.asarray(t).size
    if np.ndim(v) == 0:
        return np.zeros(nt)
    if how == "final":
        w = np.zeros(nt)
        w[-1] = 1.0
        return w
    _, w = aggregate_weights(v, how, t=t)
    return w.reshape(nt, -1).sum(axis=1)


def with_linear_rows(mechanism, x, g, jacobian, names):
    """Constraint rows g, their Jacobian (or None) and names followed by the mechanism's
    linear rows (the smoothness limits of element-wise design variables,
    `Mechanism.linear_constraints`: constant Jacobian, no simulation)."""
    A, b, lin_names = mechanism.linear_constraints()
    if not lin_names:
        return g, jacobian, names
    g = np.concatenate([g, A @ np.asarray(x, float) - b])
    if jacobian is not None:
        jacobian = np.vstack([jacobian, A])
    return g, jacobian, list(names) + lin_names


def _scalar(v, dv, how, parameter, t):
    """A scalar of a response: itself (scalar responses), or max / ks / pnorm / final /
    integral (trapezoid rule over t) of a history, with its gradient."""
    if np.ndim(v) == 0:
        return float(v), dv
    if how == "final":
        return float(v[-1]), (None if dv is None else dv[-1])
    return aggregate(v, dv, how, parameter=parameter, t=t)


def simulation_settings(description):
    """The SimulationSettings of a case description: [time]'s rho_inf, start and newton (its
    deprecated reuse_jacobian as the newton it names) and [solver]'s fields (linear_solver
    is the settings' solver; validity with the limits it sets, ValidityLimits's others).
    A limit set against the other's default (a warning limit above the default failure
    limit) is a CaseError naming it."""
    ts, so = description.time, description.solver
    given = {f"{k}_{w}": getattr(so, f"{k}_{w}") for k in ("strain", "drift", "energy")
             for w in ("warn", "fail")}
    try:
        limits = ValidityLimits(mode=so.validity,
                                **{k: v for k, v in given.items() if v is not None})
    except ModelError as exc:
        raise CaseError(f"[solver]: {exc}") from None
    return SimulationSettings(rho_inf=ts.rho_inf, start=ts.start, newton=ts.newton_strategy,
                              tol=so.tol, max_iter=so.max_iter, max_cuts=so.max_cuts,
                              solver=so.linear_solver, kscale=so.kscale, penalty=so.penalty,
                              polish=so.polish, validity=limits,
                              memory_limit=(None if so.memory_limit is None
                                            else CaseLimit(so.memory_limit)))


def _static_state(model, q0, h, settings):
    """Every coordinate of the static equilibrium at t = 0 of a built model from q0 (the core's
    static start, one step h): the [initial] static_loads deformation (Mechanism.start_state),
    solved with the case's settings (its tolerance, linear solver, scaling...; start
    'static', every coordinate stored, no validity checks of the one step).
    The static start's own advice about drives moving at t = 0 is not the case's: it starts
    from 'rest' with this deformation."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SettingWarning)
        r = simulate(model, h, h, settings.replace(start="static", validity="off", store="all"),
                     initial=InitialConditions(q0=q0))
    return np.array(r.q[0], float)
