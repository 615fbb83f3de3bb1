"""The fully coupled method (paper sections 4 and 5.4) on any problem (docs/case-format.md).

`optimize_fully(problem)` minimizes the problem's objective subject to its constraints
(`flexmbs.problem.Evaluation.constraints` g <= 0, normalised so that 0 is the limit, one row
per time step for ``over = "every_step"``) and the design variables' bounds. Every iteration
simulates the current design and differentiates it exactly (`Problem.evaluate`, direct
differentiation).

The optimizer loops are those of `flexmbs.optimizers.loops` (`_run_mma`, `_run_sqp`,
`_run_slsqp`, `_Monitor`, the KKT test): this module adapts a Problem to them
(`ScaledProblem`):

- design variables scaled by the start, x = p / p_start (x = 1 at the start, the bounds
  p_lower / p_start .. p_upper / p_start);
- objective scaled by its value at the start, f = F(p) / |F(p_start)|;
- constraints as Problem gives them (already relative), Jacobian scaled with x;
- one simulation per design (a cache keyed on the design); trial designs are simulated with
  their gradients, since a trial is most often accepted.

Stopping test (`flexmbs.optimizers.loops`): the paper's, relative objective change between two iterations
< `objective_rel_change` (1e-3) and constraint violation max(0, max g) <= `constraint_violation`
(flexmbs.problem.FEASIBILITY_TOL, 1e-6), together with the first-order test (relative KKT residual < `kkt_tol`, 1e-3, over
the constraints within `active_tol` of their limit and the bounds touched); a run whose design
stops changing for 5 iterations ends as not converged.

Long runs: ``progress=True`` shows a tqdm bar; with ``history=FILE`` every analysis is
recorded, and ``resume=True`` continues an interrupted run from FILE by replaying them
(docs/optimizers.md, "Long runs").

>>> from flexmbs.optimize import optimize_fully
>>> res = optimize_fully("slider_crank_press")                     # doctest: +SKIP
>>> res.design, res.objective, res.max_violation                  # doctest: +SKIP
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.methods.result import OptimizationResult, open_history
from flexmbs.methods.verified import finish
from flexmbs.model.description import Mass
from flexmbs.model.fingerprint import fingerprint, run_options
from flexmbs.model.options import (build, from_keywords, FullyOptions, MMAOptions,
                                   NLoptOptions, OPTIMIZER_OPTIONS, SLSQPOptions, SQPOptions)
from flexmbs.optimizers.library import _choose, run_nlopt
from flexmbs.optimizers.loops import _Monitor, _run_mma, _run_slsqp, _run_sqp
from flexmbs.optimizers.mma import MMA
from flexmbs.problem import Evaluation, is_feasible, load_problem
from flexmbs.progress import check_progress, describe_iteration, reporter

__all__ = ["optimize_fully", "ScaledProblem", "OPTIMIZERS", "RUNS", "choose_optimizer",
           "MANY_VARIABLES"]

#: Optimizers: GCMMA (hand-written, default), the trust-region SQP and plain scipy SLSQP
#: (`loops`), and NLopt's MMA, CCSAQ and SLSQP (flexmbs.optimizers.library, docs/optimizers.md).
OPTIMIZERS = ("mma", "sqp", "slsqp", "nlopt-mma", "nlopt-ccsaq", "nlopt-slsqp")
#: optimize_fully(optimizer='auto') takes the trust-region SQP below this many design
#: variables and the hand-written MMA from it (docs/optimizers.md, "Many variables": with 64
#: element-wise variables the SQP's BFGS matrix was 0.6496 kg and infeasible at 100
#: iterations where MMA reached 0.2689 kg; with 128, MMA 0.2674 kg feasible at every
#: iteration, NLopt's CCSAQ 0.3007 kg at 150 iterations, KKT residual 1.0)
MANY_VARIABLES = 32


def _mma(P, mon, x0, o, name):
    _run_mma(P, mon, x0, MMA(P.lower, P.upper, **o.mma_keywords()), max_inner=o.max_inner)
    return {}


def _sqp(P, mon, x0, o, name):
    _run_sqp(P, mon, x0, radius0=o.trust_radius, radius_max=o.max_trust_radius,
             fidelity=o.model_fidelity)
    return {}


def _slsqp(P, mon, x0, o, name):
    _run_slsqp(P, mon, x0, ftol=o.ftol)
    return {}


def _nlopt(P, mon, x0, o, name):
    return run_nlopt(P, mon, x0, name, screen=o.screen, log_scale=o.log_scale,
                     initial_step=o.initial_step, max_restarts=o.max_restarts,
                     params=dict(o.params), feasibility_phase=o.feasibility_phase)[1]


#: optimizer -> (its options class, run(P, monitor, x0, its options, optimizer) -> details);
#: its options are FullyOptions' field OPTIMIZER_OPTIONS[optimizer] (flexmbs.model.options)
RUNS = {"mma": (MMAOptions, _mma), "sqp": (SQPOptions, _sqp), "slsqp": (SLSQPOptions, _slsqp),
        "nlopt-mma": (NLoptOptions, _nlopt), "nlopt-ccsaq": (NLoptOptions, _nlopt),
        "nlopt-slsqp": (NLoptOptions, _nlopt)}
assert set(RUNS) == set(OPTIMIZERS) == set(OPTIMIZER_OPTIONS)
assert all(FullyOptions.model_fields[OPTIMIZER_OPTIONS[name]].annotation is kind
           for name, (kind, _) in RUNS.items())


def choose_optimizer(optimizer, nv):
    """(optimizer, why) for optimize_fully's `optimizer` and nv design variables: 'auto' is
    'sqp' below MANY_VARIABLES variables and 'mma' from there; any other name as given."""
    if optimizer != "auto":
        return optimizer, f"{optimizer} (as asked)"
    chosen = "sqp" if nv < MANY_VARIABLES else "mma"
    return chosen, (f"{chosen} (auto: {nv} design variable{'s' * (nv != 1)}; sqp below "
                    f"{MANY_VARIABLES}, mma from there)")


def _mass(problem, design, values):
    """The design's mass (Problem.design_mass), None for a problem-like object without one."""
    f = getattr(problem, "design_mass", None)
    return None if f is None else f(design, values)


def _units(problem):
    """The unit of every design component (Mechanism.units; problem-like objects without a
    mechanism: their description's variables)."""
    units = getattr(getattr(problem, "mechanism", None), "units", None)
    return list(units) if units is not None else [v.unit for v in problem.description.design]


def _deviation(problem, values):
    """The constrained deviation history (Problem.constrained_deviation), or None."""
    f = getattr(problem, "constrained_deviation", None)
    return None if f is None else f(values)


@dataclass
class ScaledEvaluation:
    """One design of a ScaledProblem: scaled design x, objective f and constraints g with
    their x-gradients (df, dg; dg None until computed), and the Problem's Evaluation."""
    x: np.ndarray
    design: np.ndarray
    f: float
    df: np.ndarray | None
    g: np.ndarray
    dg: np.ndarray | None
    evaluation: object

    @property
    def violation(self):
        """Constraint violation max(0, max g) (0 without constraints)."""
        return float(max(0.0, self.g.max())) if self.g.size else 0.0


class ScaledProblem:
    """A `flexmbs.problem.Problem` scaled for the optimizers of fully.py.

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    scale : (nv,) array, optional
        x = p / scale; default the problem's start design.
    replay : list of dict, optional
        Analyses recorded by an interrupted run (history records' ``evaluations``): an
        analysis of the same scaled design (bitwise) with the same gradient flag is taken from
        them, in order, instead of simulating (resume).
    log : bool, default False
        Keep every analysis for the history (`take_log`).

    Attributes
    ----------
    lower, upper : scaled bounds; simulations : Problem.evaluate calls (one simulation each);
    gradient_evaluations : those with gradients; evaluations : distinct designs analysed;
    sensitivity : 'direct' (trial designs are evaluated with their gradients);
    replayed : analyses taken from `replay` (counted in `simulations` too, so that the
    resumed run's records and limits are those of the interrupted one).
    """

    sensitivity = "direct"

    def __init__(self, problem, scale=None, replay=None, log=False):
        self.problem = problem
        self.nv = len(problem.variables)
        if self.nv == 0:
            raise ModelError("the case has no [[design]] variables: nothing to optimize")
        if problem.description.objective is None:
            raise ModelError("the case has no [objective]: nothing to minimize")
        if scale is not None:
            try:
                scale = problem.mechanism.design_values(scale)
            except ModelError:
                raise ModelError(f"scale must be {self.nv} positive finite numbers (the design "
                                 f"scale, x = p / scale, in the variables' units), got "
                                 f"{scale!r}") from None
        scale = problem.start if scale is None else scale
        self.scale = np.asarray(scale, float)
        self.lower = problem.lower / self.scale
        self.upper = problem.upper / self.scale
        self.simulations = 0
        self.evaluate_time_s = 0.0          # wall time spent in Problem.evaluate
        self.gradient_evaluations = 0
        self.evaluations = 0
        self._cache = {}
        self._order = []
        self._cache_size = 32
        # resume: recorded analyses (design, gradient flag) -> Evaluation, used in order
        self.replayed = 0
        self._replay = {}
        for entry in replay or ():
            key = (np.asarray(entry["x"], float).tobytes(), bool(entry["gradient"]))
            self._replay.setdefault(key, []).append(entry)
        self._log = [] if log else None
        # the objective's scale: its value at x = 1 (that evaluation is kept, rescaled)
        self.f_ref = 1.0
        ev = self.evaluate(np.ones(self.nv), gradient=True)
        self.f_ref = abs(ev.f) or 1.0
        ev.f /= self.f_ref
        ev.df = ev.df / self.f_ref

    @property
    def objective_hessian(self):
        """Hessian of the scaled objective at the start (the SQP's first matrix): exact for a
        mass objective (a quadratic function of the section sizes needs no simulation:
        central differences of its exact gradient), the identity scaled by the gradient's
        size otherwise. The mass of a tube, 4 rho L t (D - t), is indefinite in (D, t): its
        eigenvalues are replaced by their absolute values, floored at 1e-3 times the largest
        (the QP needs a positive definite matrix; for solid sections nothing changes)."""
        if getattr(self, "_hessian", None) is None:
            H = self.mass_hessian()
            if H is not None:
                w, V = np.linalg.eigh(H)
                w = np.abs(w)
                w = np.maximum(w, 1e-3 * w.max() if w.max() > 0 else 1.0)
                self._hessian = (V * w) @ V.T
            else:
                g0 = self.evaluate(np.ones(self.nv), gradient=True).df
                self._hessian = np.eye(self.nv) * max(float(np.abs(g0).max()), 1e-12)
        return self._hessian

    def mass_hessian(self):
        """The exact Hessian of a mass objective (scaled) at the start, symmetrized: central
        differences (step 1e-4) of its exact gradient, no simulation; None when the objective
        is not a mass."""

        prob = self.problem
        r = prob._resp[prob.description.objective.response]
        if not isinstance(r, Mass):
            return None

        def grad(x):
            p = self.design(x)
            return prob._response(r, p, None, True)[1] * self.scale / self.f_ref
        H = np.zeros((self.nv, self.nv))
        for i in range(self.nv):
            e = np.zeros(self.nv)
            e[i] = 1e-4
            H[:, i] = (grad(1.0 + e) - grad(1.0 - e)) / 2e-4
        return 0.5 * (H + H.T)

    def design(self, x):
        """The design (user units) of a scaled design."""
        return np.asarray(x, float) * self.scale

    def to_x(self, design):
        """The scaled design of a design in user units."""
        return np.asarray(design, float) / self.scale

    def evaluate(self, x, gradient=True):
        """The scaled design x analysed (cached: one simulation per design)."""
        x = np.clip(np.asarray(x, float), self.lower, self.upper)
        key = x.tobytes()
        ev = self._cache.get(key)
        if ev is None or (gradient and ev.dg is None):
            if ev is None:
                self.evaluations += 1
            ev = self._analyse(x, gradient)
            if key not in self._cache:
                self._order.append(key)
            self._cache[key] = ev
            if len(self._order) > self._cache_size:
                self._cache.pop(self._order.pop(0), None)
        return ev

    def _analyse(self, x, gradient):
        p = self.design(x)
        self.simulations += 1
        recorded = self._replay.get((x.tobytes(), bool(gradient)))
        if recorded:
            ev = _evaluation_from_log(recorded.pop(0), p)
            self.replayed += 1
        else:
            want = gradient
            if gradient and callable(getattr(self.problem, "used_responses", None)):
                # only the objective's and the constraints' gradients: responses that are
                # only reported are not differentiated
                want = "used"
            t0 = time.perf_counter()
            try:
                ev = self.problem.evaluate(p, gradient=want)
            finally:
                self.evaluate_time_s += time.perf_counter() - t0
        if self._log is not None:
            self._log.append(_log_entry(x, gradient, ev))
        if gradient:
            self.gradient_evaluations += 1
        df = (None if ev.d_objective is None else
              np.asarray(ev.d_objective) * self.scale / self.f_ref)
        dg = None if ev.jacobian is None else np.asarray(ev.jacobian) * self.scale[None, :]
        return ScaledEvaluation(x=x, design=p, f=float(ev.objective) / self.f_ref, df=df,
                                g=np.asarray(ev.constraints, float), dg=dg, evaluation=ev)

    def take_log(self):
        """The analyses since the last call (history records keep them, file only, so that a
        resumed run replays them): a dict {'evaluations': [...]} or None when not logging."""
        if not self._log:
            return None
        out, self._log = self._log, []
        return {"evaluations": out}

    # ------------------------------------------------------------------ history records
    def active_constraints(self, ev, active_tol):
        """{response: 1-based rows of its constraint block within active_tol of the limit}
        (for ``over = "every_step"`` the rows are the time steps)."""
        out = {}
        names = ev.evaluation.constraint_names
        rows = {}
        for j, name in enumerate(names):
            rows.setdefault(name, []).append(j)
        for name, idx in rows.items():
            g = ev.g[idx]
            out[name] = (np.flatnonzero(g >= -active_tol) + 1).tolist()
        return out

    def _max_deviation(self, values):
        dev = _deviation(self.problem, values)
        return None if dev is None else float(dev.max())

    def record_fields(self, ev, active_tol):
        """The problem's part of a history record: design, objective, violation, largest
        value of every response, active constraints."""
        e = ev.evaluation
        return dict(design=ev.design, objective=float(e.objective),
                    mass_kg=_mass(self.problem, ev.design, e.values),
                    max_deviation_m=self._max_deviation(e.values),
                    max_violation=ev.violation,
                    responses={k: float(np.max(v)) for k, v in e.values.items()},
                    active_steps=self.active_constraints(ev, active_tol))

    def record_tail(self, ev, active_tol):
        return {}


def _runs(names):
    """Run-length form [[name, count], ...] of a list of names."""
    out = []
    for n in names:
        if out and out[-1][0] == n:
            out[-1][1] += 1
        else:
            out.append([n, 1])
    return out


def _log_entry(x, gradient, ev):
    """One analysis of a run, as written to its history (exact: JSON floats round-trip).
    Of every response only its largest value is kept, not its history: a replayed analysis
    feeds the optimizer its objective, constraints and their gradients, and the records the
    responses' largest values (record_fields); the histories were nine tenths of a file
    (1301 steps x each response, 85 of 98 kB per analysis of the 64-variable robot)."""
    values = {k: v if np.ndim(v) == 0 else (float(np.max(v)) if np.size(v) else None)
              for k, v in ev.values.items()}
    return dict(x=x, gradient=bool(gradient), objective=ev.objective,
                d_objective=ev.d_objective, constraints=ev.constraints,
                jacobian=_sparse_log(ev.jacobian), constraint_names=_runs(ev.constraint_names),
                values=values)


def _sparse_log(jac):
    """A Jacobian for the history: its nonzeros {"shape", "i", "j", "v"} when they are fewer
    than a third of its entries (the linear rows of smoothness limits are two nonzeros each:
    at 128 element-wise variables four fifths of the file were their zeros), else as is."""
    if jac is None:
        return None
    a = np.asarray(jac, float)
    if a.ndim != 2 or 3 * np.count_nonzero(a) >= a.size:
        return jac
    i, j = np.nonzero(a)
    return {"shape": list(a.shape), "i": i.tolist(), "j": j.tolist(), "v": a[i, j].tolist()}


def _array(v):
    if isinstance(v, dict):           # a sparse Jacobian (_sparse_log)
        a = np.zeros(v["shape"])
        a[np.asarray(v["i"], int), np.asarray(v["j"], int)] = np.asarray(v["v"], float)
        return a
    return None if v is None else np.asarray(v, float)


def _evaluation_from_log(entry, design):
    """The Evaluation of a recorded analysis (a resumed run's replay: no simulation)."""
    names = [n for n, k in entry["constraint_names"] for _ in range(k)]
    values = {k: (float("nan") if v is None else v) if not isinstance(v, list) else _array(v)
              for k, v in entry["values"].items()}
    jac = _array(entry["jacobian"])
    g = _array(entry["constraints"])
    if jac is not None and jac.size == 0:
        jac = jac.reshape(0, design.size)
    return Evaluation(x=np.asarray(design, float).copy(), t=None, values=values, gradients={},
                      objective=entry["objective"], d_objective=_array(entry["d_objective"]),
                      constraints=g, jacobian=jac, constraint_names=names,
                      stats={"replayed": True})


def optimize_fully(problem, x0=None, *, optimizer=None, options=None, history=None,
                   progress=None, resume=False, **keywords):
    """Minimize a problem's objective under its constraints with the fully coupled method.

    Parameters
    ----------
    problem : flexmbs.problem.Problem, or a case path, the name of a shipped case, a dict or
        a Description (then loaded with flexmbs.problem.load_problem).
    x0 : array, optional
        Starting design (the variables' units, within the bounds); default the case's start.
    optimizer : {'auto', 'mma', 'sqp', 'slsqp', 'nlopt-mma', 'nlopt-ccsaq', 'nlopt-slsqp'}, optional
        Default: the case's ``[optimize] optimizer``, else 'auto'.
        'auto' (`choose_optimizer`) takes the trust-region SQP below MANY_VARIABLES (32)
        design variables: over Tables 1, 2, 5, 6, 7, the four-bar, the three new examples
        and the robot at 0.1 and 0.3 s it met the paper's stopping test in every run, as
        light as the hand-written MMA or lighter, with 2-16 % of the run in the optimizer
        (docs/optimizers.md); and the hand-written MMA from 32 variables (element-wise
        sizing), where the SQP's BFGS matrix learns too slowly. The choice and its reason
        are in the result's details (optimizer, optimizer_reason). Svanberg's globally convergent MMA (`flexmbs.optimizers.mma`, with inner iterations),
        the trust-region SQP, or plain scipy SLSQP (no move limits), see
        `flexmbs.optimizers.loops`; or NLopt's MMA, CCSAQ or SLSQP on the design mapped to
        [0, 1] with the constraints as one vector constraint (`flexmbs.optimizers.library`;
        docs/optimizers.md compares them). The dispatch is the table `RUNS`.
    options : flexmbs.model.options.FullyOptions or dict, optional
        The stopping rules (max_iterations, max_simulations, objective_rel_change,
        constraint_violation, design_rel_change, kkt_tol, active_tol), the design scale,
        `verify`, and the optimizers' tables (sqp, mma, slsqp, nlopt); a dict may give an
        optimizer's option flat ({"trust_radius": 0.1}). One table each in
        `flexmbs.model.options` and docs/optimizers.md. An option of another optimizer than
        the one run is not used, with a SettingWarning naming it and the optimizer run; a
        ModelError when `optimizer` names the optimizer too (not 'auto'). Default: the case's
        ``[optimize]`` table, else the defaults. `verify` (default True) verifies the final
        design at converged resolution (`flexmbs.methods.verified`,
        `flexmbs.analysis.accuracy.verify`): re-simulated at h/2, h/4, ... until the
        objective and the constraints are known to 1e-3 (or the accuracy given); when it is
        infeasible there, the optimization continues at that step from the design (no
        history file) and the new design is verified in turn.
    **keywords
        Deprecated: the options as keywords (max_iterations=..., trust_radius=...,
        mma_options={...}, nlopt_options={...}, screen=..., verify=...), with a
        DeprecationWarning naming the options= spelling.
    history : str, path or HistoryWriter, optional
        One JSON line per iteration written as the run goes (iteration 0: the start); keys
        iteration, design, objective, mass_kg, max_violation, responses (largest value of
        each), active_steps, objective_rel_change, design_rel_change, kkt_residual,
        simulations, gradient_evaluations, wall_time_s (mma: mma_inner_iterations).
        With a file, each record also holds (file only, key ``evaluations``) every analysis
        made since the previous record: scaled design, objective, constraints, their
        gradients and each response's largest value, exact (JSON floats round-trip), for
        `resume`.
    progress : bool, text stream or callable, optional
        True: a tqdm bar on stderr (iteration, simulations, mass, constraint violation); a
        text stream: that bar on the stream; a callable: called with each history record.
        None/False (default): nothing shown (`flexmbs.progress`).
    resume : bool, default False
        Continue an interrupted run from its `history` file (required): the analyses it
        recorded are replayed when the optimizer asks for the same design again (bitwise
        the same scaled design: the optimizers are deterministic), so the run follows the
        interrupted one's path without simulating and goes on from where it stopped,
        appending to the file; it ends at the same optimum as an uninterrupted run. A
        missing file starts afresh. Run it with the same problem, start and options (a
        record that differs from the file's raises ModelError). details replayed_simulations
        counts the replayed analyses; `simulations` counts only those run.

    Returns
    -------
    flexmbs.optimize.OptimizationResult
        method 'fully'; verification (details['verification']; after a continuation,
        details['continued_from']: the coarse run); inner_iterations None; details:
        optimizer, options (the options used, `FullyOptions.record`), kkt_residual,
        paper_test_iteration, gradient_evaluations, scale, stopping (the settings),
        evaluate_time_s (inside Problem.evaluate), optimizer_share (1 - evaluate_time_s /
        wall_time_s); NLopt: nlopt_result, restarts, failed_simulations,
        feasibility_simulations, screened_rows, total_rows, screen.

    Raises
    ------
    ModelError
        Bad option (named), a start outside the bounds, no design variables or no objective.
    flexmbs.errors.SimulationError
        If the simulation of the start fails.
    """
    t0 = time.perf_counter()
    if keywords:
        options = from_keywords("optimize_fully", FullyOptions, options, keywords,
                                tables={"mma_options": "mma", "nlopt_options": "nlopt"})
    if optimizer is not None and (not isinstance(optimizer, str)
                                  or optimizer not in OPTIMIZERS + ("auto",)):
        raise ModelError(f"optimizer must be 'auto' or one of {', '.join(OPTIMIZERS)}, got "
                         f"{optimizer!r}")
    opts = None if options is None else build(FullyOptions, options)
    # the caller named the optimizer and gave the options: another optimizer's table is an
    # error; otherwise (the case's table, 'auto') it is set aside with a SettingWarning
    explicit = opts is not None and optimizer not in (None, "auto")
    check_progress(progress)
    if not isinstance(resume, bool):
        raise ModelError(f"resume must be True or False, got {resume!r}")
    problem = load_problem(problem)
    mech = problem.mechanism
    # the case's [optimize] table when the call gives none
    section = getattr(getattr(problem, "description", None), "optimize", None)
    if opts is None:
        opts = FullyOptions() if section is None else section.fully()
    if optimizer is None:
        optimizer = "auto" if section is None else section.optimizer
    optimizer, optimizer_reason = choose_optimizer(optimizer, len(problem.variables))
    opts = opts.check_optimizer(optimizer, optimizer_reason, explicit)
    verify = opts.verify
    table = getattr(opts, OPTIMIZER_OPTIONS[optimizer])
    used = opts.record(optimizer)
    p0 = problem.start if x0 is None else mech.design_values(x0)
    lo, hi = problem.lower, problem.upper
    bad = np.flatnonzero((p0 < lo * (1 - 1e-12)) | (p0 > hi * (1 + 1e-12)))
    if bad.size:
        i = int(bad[0])
        raise ModelError(f"x0: {problem.variables[i]} = {float(p0[i])!r} lies outside its "
                         f"bounds [{lo[i]:g}, {hi[i]:g}]")
    writer, own_writer = open_history(history, resume)
    # what a history answers: the options used (but the limits), the optimizer, the start
    writer.check_fingerprint(fingerprint(problem.description, "fully",
                                         run_options(dict(used, optimizer=optimizer, x0=p0))),
                             options=dict(used, optimizer=optimizer))
    replay = []
    for rec in writer.previous:
        replay += rec.pop("evaluations", None) or []
    try:
        P = ScaledProblem(problem, p0 if opts.scale is None else opts.scale, replay=replay,
                          log=writer.path is not None)
    except BaseException:
        if own_writer:
            writer.close()
        raise
    del replay
    progress = reporter(progress, total=opts.max_iterations, label="iterations",
                        describe=describe_iteration, position=lambda r: r["iteration"])
    mon = _Monitor(P, writer, progress, objective_rel_change=opts.objective_rel_change,
                   constraint_violation=opts.constraint_violation,
                   design_rel_change=opts.design_rel_change, kkt_tol=opts.kkt_tol,
                   active_tol=opts.active_tol, max_iterations=opts.max_iterations,
                   max_simulations=opts.max_simulations, t0=t0)
    try:
        lib_details = RUNS[optimizer][1](P, mon, P.to_x(p0), table, optimizer)
    finally:
        if own_writer:
            writer.close()
        if progress is not None:
            progress.close()
    if not mon.iterates:
        raise ModelError("the optimization recorded no iterate")
    if optimizer.startswith("nlopt"):
        last = _choose(mon)
    else:
        last = mon.iterates[-1]
    # the constraints of the final design re-checked by a fresh simulation (no cache)
    t_fresh = time.perf_counter()
    fresh = problem.evaluate(last.design, gradient=False)
    P.evaluate_time_s += time.perf_counter() - t_fresh
    P.simulations += 1
    desc = problem.description
    details = dict(optimizer=optimizer, optimizer_reason=optimizer_reason, options=used,
                   kkt_residual=mon.last_kkt,
                   paper_test_iteration=mon.paper_test_iteration,
                   gradient_evaluations=P.gradient_evaluations, scale=P.scale,
                   gradient_method=(problem.gradient_method()
                                    if hasattr(problem, "gradient_method") else None),
                   gradient_method_reason=(problem.gradient_method_reason()
                                           if hasattr(problem, "gradient_method_reason")
                                           else None),
                   stopping=dict(objective_rel_change=opts.objective_rel_change,
                                 constraint_violation=opts.constraint_violation,
                                 design_rel_change=opts.design_rel_change,
                                 kkt_tol=opts.kkt_tol, active_tol=opts.active_tol))
    if optimizer == "sqp":
        details.update(trust_radius=table.trust_radius, max_trust_radius=table.max_trust_radius,
                       model_fidelity=table.model_fidelity)
    details.update(lib_details)
    if optimizer == "mma":
        details["mma_inner_iterations"] = sum(r.get("mma_inner_iterations") or 0
                                              for r in writer.records)
    viol = float(max(0.0, fresh.constraints.max())) if fresh.constraints.size else 0.0
    dev = _deviation(problem, fresh.values)
    wall = time.perf_counter() - t0
    details["evaluate_time_s"] = P.evaluate_time_s
    if resume:
        details["replayed_simulations"] = P.replayed
    details["optimizer_share"] = max(0.0, 1.0 - P.evaluate_time_s / wall) if wall > 0 else 0.0
    converged = mon.converged and is_feasible(viol, opts.constraint_violation)
    reason = mon.reason or "stopped"
    if last is not mon.iterates[-1]:
        # the reason's numbers are the last iterate's: say which design is returned instead
        k = next(i for i, e in enumerate(mon.iterates) if e is last)
        reason += (f"; the design returned is iteration {k}'s, the "
                   + ("lightest feasible iterate" if last.violation < opts.constraint_violation
                      else f"least violated iterate (constraint violation {last.violation:.1e})"))
    if mon.converged and not converged:
        reason += f"; but the re-simulated final design violates a constraint by {viol:.1e}"
    result = OptimizationResult(
        method="fully", case=desc.case.name, variables=problem.variables,
        units=_units(problem), design=last.design.copy(), start=p0.copy(),
        objective=float(fresh.objective), objective_name=desc.objective.response,
        mass_kg=_mass(problem, last.design, fresh.values), max_violation=viol,
        max_deviation_m=None if dev is None else float(dev.max()),
        iterations=mon.iteration, inner_iterations=None, evaluations=P.evaluations,
        simulations=P.simulations - P.replayed, converged=converged, reason=reason,
        history=list(writer.records), wall_time_s=wall, details=details,
        t=None if dev is None else np.asarray(fresh.t), deviation=dev, evaluation=fresh)
    # a continuation on a finer step (flexmbs.methods.verified): the same options, unverified
    again = opts.model_copy(update=dict(verify=False))
    return finish(problem, result, lambda fine, x: optimize_fully(fine, x, optimizer=optimizer,
                                                                  options=again),
                  verify, coarse=fresh)
