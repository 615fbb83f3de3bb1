"""Multi-start fully coupled optimization of a general-format problem.

`multistart(case, starts=N)` draws N starting designs with a quasi-random sampler
(scipy.stats.qmc: scrambled Sobol or Latin hypercube), runs `optimize_fully` from each one
through the batch layer (`flexmbs.batch.run_batch`: serially, on local worker processes or on
a Dask cluster), re-checks every local optimum's feasibility by a fresh simulation in this
process, and returns the best feasible design, every local optimum (objective, violation) and
how many starts reached the best (objective within `best_tolerance`, 0.3 %, of it).

An adaptive case (time.h = "auto", flexmbs.analysis.adaptive) is re-adapted between the
starts: each start's run chooses its step grid at its own start design and keeps it frozen
while the optimizer differentiates (`start_problem`; the start's record states it, `grid`),
each local optimum is re-checked on a grid chosen at itself (`recheck_grid`), and the best is
verified on a grid chosen at it (docs/accuracy.md, "Error-controlled steps").

Starting designs: variable i is drawn in [lower_i, upper_i] (the design bounds, or the narrower
`start_range`), uniformly, or log-uniformly where upper_i / lower_i > 10 (bounds spanning a
decade or more, such as 15-500 mm diameters: a uniform draw would put 97 % of the starts above
30 mm).

>>> from flexmbs.methods.multistart import multistart
>>> res = multistart("fourbar", starts=8, workers=2)                        # doctest: +SKIP
>>> res.best["objective"], res.reached_best                              # doctest: +SKIP
"""
from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flexmbs.analysis.accuracy import describe_verification
from flexmbs.batch import check_dask, run_batch, StoredResult
from flexmbs.errors import ModelError, ResourceError, SimulationError
from flexmbs.files import jsonable, save_figure
from flexmbs.methods.fully import choose_optimizer, optimize_fully
from flexmbs.methods.result import OptimizationResult
from flexmbs.methods.verified import check_verify, finish, objective_unit
from flexmbs.model.fingerprint import fingerprint
from flexmbs.model.options import build, from_keywords, FullyOptions, MultistartOptions
from flexmbs.problem import load_problem
from flexmbs.progress import check_progress, describe_start
from flexmbs.resources import format_bytes, limit_source, memory_limit

__all__ = ["multistart", "start_designs", "sample_memory", "check_sample_memory",
           "MultistartResult", "SAMPLERS", "start_job", "start_problem"]

#: quasi-random samplers of the starting designs
SAMPLERS = ("sobol", "lhs")


#: Bytes per drawn design beside its values (the screening's sort key and index, Python
#: objects) and arrays of its values (the sampler's points, the scaled designs, temporaries).
SAMPLE_OVERHEAD_BYTES = 250
SAMPLE_ARRAYS = 4


#: Bytes a start keeps besides its drawn design until the multi-start returns: its job
#: (start, options), its fingerprint for the store and its result record and optimum
#: (`.venv/bin/python benchmarks/multistart_memory.py` at commit ad02520: 9670 bytes on the
#: four-bar)
START_RECORD_BYTES = 10_000


def sample_memory(count, nv, records=0):
    """Bytes (rough upper bound) of `count` drawn designs of `nv` variables and their
    screening (start_designs and multistart's candidates), plus `records` bytes per design
    (START_RECORD_BYTES for the starts a multi-start runs)."""
    return float(count) * (SAMPLE_ARRAYS * 8.0 * nv + SAMPLE_OVERHEAD_BYTES + records)


def check_sample_memory(count, nv, name="starts", records=0):
    """ResourceError naming `name` when `count` designs of `nv` variables (`sample_memory`,
    with `records` bytes per design) do not fit in the memory limit
    (flexmbs.resources.memory_limit)."""
    need, avail = sample_memory(count, nv, records), memory_limit()
    if need > avail:
        option = {"starts": "--starts", "candidates": "--candidates"}.get(name, name)
        what = " and their runs' records" if records else ""
        raise ResourceError(f"{name} = {count} ({option} on the command line): {count} designs "
                            f"of {nv} variables{what} need about {format_bytes(need)}, more "
                            f"than {limit_source()} ({format_bytes(avail)}); draw fewer",
                            required=need, available=avail)


def start_designs(lower, upper, starts, sampler="sobol", seed=0):
    """(starts, nv) starting designs in the box [lower, upper] (user units).

    Uniform in each variable, log-uniform where upper / lower > 10 (and lower > 0). The same
    seed gives the same designs.

    Raises
    ------
    ModelError
        starts < 1, an unknown sampler, or lower > upper.
    """
    from scipy.stats import qmc

    lower = np.atleast_1d(np.asarray(lower, float))
    upper = np.atleast_1d(np.asarray(upper, float))
    if isinstance(starts, bool) or not isinstance(starts, (int, np.integer)) or starts < 1:
        raise ModelError(f"starts must be a positive integer, got {starts!r}")
    if sampler not in SAMPLERS:
        raise ModelError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
                             or seed < 0):
        raise ModelError(f"seed must be an integer >= 0 (or None), got {seed!r}")
    if lower.shape != upper.shape or np.any(~np.isfinite(lower)) or np.any(upper < lower):
        raise ModelError(f"start range: lower {lower.tolist()} and upper {upper.tolist()} must "
                         f"be finite, of the same length, with lower <= upper")
    check_sample_memory(starts, lower.size)
    nv = lower.size
    if sampler == "sobol":
        eng = qmc.Sobol(d=nv, scramble=True, seed=seed)
        with warnings.catch_warnings():       # balance is best at powers of 2; any n is valid
            warnings.simplefilter("ignore", UserWarning)
            u = eng.random(int(starts))
    else:
        u = qmc.LatinHypercube(d=nv, seed=seed).random(int(starts))
    log = (lower > 0) & (upper > 10 * lower)
    x = lower + u * (upper - lower)
    if np.any(log):
        ll, lu = np.log(lower[log]), np.log(upper[log])
        x[:, log] = np.exp(ll + u[:, log] * (lu - ll))
    return np.clip(x, lower, upper)


class StartResult(StoredResult):
    """A stored result of `start_job` (a start whose simulation failed has design None)."""
    start: list[float]
    design: list[float] | None
    objective: float | None
    max_violation: float | None
    converged: bool
    simulations: int
    wall_time_s: float
    reason: str | None = None
    grid: dict | None = None


#: simulations one choice of an adaptive grid runs (its two pilots, flexmbs.analysis.adaptive)
PILOT_SIMULATIONS = 2


def adaptive(problem):
    """True when `problem` (a Problem) has error-controlled steps (time.h = "auto")."""
    return hasattr(problem, "adapt") and bool(
        getattr(getattr(problem.description, "time", None), "adaptive", False))


def _own(problem, case):
    """`problem`, or a copy of it when it is the caller's `case` (its grid is left alone)."""
    if problem is not case:
        return problem
    return type(problem)(problem.description, gradient_method=problem.default_gradient_method,
                         checkpoints=problem.adjoint_checkpoints)


def start_problem(case, start):
    """(problem, grid) a start runs on: the case loaded (flexmbs.problem.load_problem); for an
    adaptive case (time.h = "auto") a problem of its own whose step grid is chosen at the start
    design `start` and frozen for the start's run (Problem.adapt; the grid is a deterministic
    function of the description and the start), and grid its summary (Problem.grid_summary:
    steps, tol, rtol, h_min, h_max); grid None for a fixed step."""
    problem = load_problem(case)
    if not adaptive(problem):
        return problem, None
    problem = _own(problem, case)
    problem.adapt(start)
    return problem, problem.grid_summary()


def start_job(case, start, optimizer, options):
    """One start (a batch job: plain data in, JSON out): `optimize_fully(case, start,
    optimizer=optimizer, options=options)` summarised (options: FullyOptions as plain data); an
    adaptive case runs on a grid chosen at the start (`start_problem`, the record's `grid`)."""
    grid = None
    try:
        problem, grid = start_problem(case, start)
        # each start's local optimum is not verified: multistart verifies the best one
        res = optimize_fully(problem, start, optimizer=optimizer,
                             options=dict(options or {}, verify=False))
    except SimulationError as exc:
        # a start whose own simulation fails (e.g. a very flexible design): no local optimum
        return dict(start=[float(v) for v in start], design=None, objective=None,
                    max_violation=None, converged=False, simulations=1, wall_time_s=0.0,
                    optimizer_share=float("nan"), grid=grid,
                    reason=f"the start's simulation failed: {exc}", error=str(exc))
    pilots = 0 if grid is None else PILOT_SIMULATIONS
    return dict(start=[float(v) for v in start], design=[float(v) for v in res.design],
                objective=float(res.objective), max_violation=float(res.max_violation),
                converged=bool(res.converged), reason=res.reason,
                simulations=int(res.simulations) + pilots, wall_time_s=float(res.wall_time_s),
                optimizer_share=float(res.details.get("optimizer_share", float("nan"))),
                grid=grid)


start_job.result_schema = StartResult


@dataclass
class MultistartResult:
    """Outcome of `multistart`.

    Attributes
    ----------
    case, variables, units, optimizer, sampler : what was run.
    best : the lightest feasible local optimum (dict: start, design, objective, max_violation
        (re-checked), converged, simulations, ...), None when no start ended feasible.
    optima : every start's local optimum, in the order of the starts (same keys; max_violation
        re-checked by a fresh simulation, `feasible` added; a start whose own simulation
        failed has design None and its `reason`; an adaptive case's start has `grid`, the
        summary of the grid it ran on, chosen at its start (Problem.grid_summary: steps, tol,
        rtol, h_min, h_max), and `recheck_grid`, the grid its re-check ran on).
    reached_best : how many starts ended feasible within best_tolerance of the best objective.
    best_tolerance : relative (0.003). wall_time_s. simulations : all starts' simulations and
        the re-checks.
    details : seed, candidates, verification, start_lower/start_upper, options, multistart
        (its options, with feasibility_tol).

    Every optimum has ``h``: the step its objective and max_violation were simulated on (the
    case's; the best after a continuation on a finer step: that step). `to_dict` repeats the
    best's verdicts at the top level (`VERDICTS`, docs/json-output.md).
    """
    case: str
    variables: list
    units: list
    optimizer: str
    sampler: str
    best: dict | None
    optima: list
    reached_best: int
    best_tolerance: float
    wall_time_s: float
    simulations: int
    details: dict = field(default_factory=dict)

    #: the verdicts of the best local optimum repeated at the top level of `to_dict`
    VERDICTS = ("design", "objective", "max_violation", "feasible", "converged", "reason",
                "verified", "verified_h", "h")

    @property
    def converged(self):
        """The best local optimum's run passed its stopping test (False without a feasible
        local optimum)."""
        return self.best is not None and bool(self.best["converged"])

    @property
    def feasible(self):
        """A feasible local optimum was found (the best one: its max_violation <=
        feasibility_tol, re-simulated)."""
        return self.best is not None and bool(self.best["feasible"])

    @property
    def verified(self):
        """The best design's verification verdict (None: not verified, or no best)."""
        v = None if self.best is None else self.best.get("verification")
        return None if not v else bool(v["verified"])

    def verdicts(self):
        """{key: value} of `VERDICTS`: the best local optimum's (None, False when there is
        none); feasibility_tol the multi-start's."""
        b = self.best or {}
        v = b.get("verification") or {}
        return dict(design=b.get("design"), objective=b.get("objective"),
                    max_violation=b.get("max_violation"), feasible=self.feasible,
                    converged=self.converged,
                    reason=b.get("reason", "no start ended feasible"),
                    verified=self.verified, verified_h=v.get("h"), h=b.get("h"))

    @property
    def design(self):
        return None if self.best is None else np.asarray(self.best["design"])

    @property
    def objective(self):
        return None if self.best is None else self.best["objective"]

    def spread(self):
        """(lightest, heaviest) objective of the feasible local optima (None without any)."""
        f = [o["objective"] for o in self.optima if o["feasible"]]
        return (min(f), max(f)) if f else None

    def to_dict(self, history=True):
        d = dict(method="fully", multistart=True, case=self.case, variables=self.variables,
                 units=self.units, optimizer=self.optimizer, sampler=self.sampler,
                 starts=len(self.optima), best=self.best, optima=self.optima,
                 reached_best=self.reached_best, best_tolerance=self.best_tolerance,
                 feasible_starts=sum(o["feasible"] for o in self.optima),
                 wall_time_s=self.wall_time_s, simulations=self.simulations)
        d.update(self.verdicts())
        d.update(self.details)
        return jsonable(d)

    def to_json(self, indent=None):
        return json.dumps(self.to_dict(), indent=indent)

    def summary(self):
        n = len(self.optima)
        unit = self.details.get("objective_unit")
        unit = f" {unit}" if unit else ""
        lines = [f"fully coupled, {n} starts ({self.sampler}), optimizer {self.optimizer}, "
                 f"case {self.case}: {sum(o['feasible'] for o in self.optima)} of {n} ended "
                 f"feasible (re-simulated)"]
        if self.best is None:
            lines.append("  no feasible design found")
        else:
            b = self.best
            p = ", ".join(f"{n} = {v:.5g}{' ' + u if u else ''}"
                          for n, v, u in zip(self.variables, b["design"], self.units))
            lines.append(f"  best design {p}")
            at = "" if b.get("h") is None else f" at h = {b['h']:.4g} s"
            lines.append(f"  objective {b['objective']:.6g}{unit}{at}, "
                         f"{'feasible' if b['feasible'] else 'INFEASIBLE'}: max violation "
                         f"{b['max_violation']:.1e} (the largest g above 0, g relative to the "
                         f"limits); {'converged' if b['converged'] else 'NOT converged'} "
                         f"({b['reason']})")
            lines.append(f"  {self.reached_best} of {n} starts reached it (within "
                         f"{self.best_tolerance * 100:.1f} %)")
            ver = describe_verification(dict(self.best, objective_unit=self.details.get(
                "objective_unit")))
            if ver:
                lines.append(f"  {ver}")
        for k, o in enumerate(self.optima):
            if o.get("design") is None:
                lines.append(f"  start {k}: {o['reason']}")
                continue
            grid = o.get("grid")
            lines.append(f"  start {k}: objective {o['objective']:.6g}{unit}, max violation "
                         f"{o['max_violation']:.1e}, {o['simulations']} simulations"
                         + ("" if grid is None else f", {grid['steps']} steps (grid chosen at "
                            f"the start, {_tolerance(grid)})")
                         + ("" if o["feasible"] else "  INFEASIBLE"))
        lines.append(f"  {self.simulations} simulations, {self.wall_time_s:.1f} s")
        return "\n".join(lines)

    def plot(self, path, limit_m=None):
        """Figure: each start's local optimum (objective; infeasible ones marked)."""
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for k, o in enumerate(self.optima):
            if o.get("design") is None:
                continue
            ax.plot(k, o["objective"], "o" if o["feasible"] else "x",
                    color="C0" if o["feasible"] else "C3")
        ax.set_xlabel("start")
        unit = self.details.get("objective_unit")
        ax.set_ylabel(f"objective of the local optimum{f' [{unit}]' if unit else ''}")
        ax.set_yscale("log")
        ax.set_title("multi-start: local optima (x: infeasible)")
        ax.grid(True, alpha=0.3)
        try:
            return save_figure(fig, path, dpi=120)
        finally:
            plt.close(fig)


def multistart(case, starts=None, *, options=None, fully=None, workers=None, dask=None,
               store=None, progress=None, resume=False, **keywords):
    """Run the fully coupled optimization from `starts` quasi-random starting designs.

    Parameters
    ----------
    case : a general-format case path or name, a dict or a Description (plain data, sent to
        the workers), or a Problem (its description is sent).
    starts : int, optional
        The number of starts (options.starts, default 8).
    options : flexmbs.model.options.MultistartOptions or dict, optional
        The multi-start's options (one table in `flexmbs.model.options.MultistartOptions` and
        docs/optimizers.md; default: the case's ``[optimize.multistart]`` table, else the
        defaults): starts, optimizer ('nlopt-mma': docs/optimizers.md, the most four-bar
        starts reached the light design with it, at a small optimizer share), sampler
        ('sobol' or 'lhs'), seed (the same seed gives the same starts), start_range ((lower,
        upper): the box the starts are drawn from, inside the bounds), candidates (draw this
        many designs, >= starts, simulate each once without gradients, and start from the
        `starts` feasible ones of lowest objective, then the least violated: no start in an
        infeasible basin that the optimizer cannot leave), best_tolerance (0.003: a start
        reached the best when it ended feasible within this relative objective),
        feasibility_tol (1e-6: largest re-checked violation of a feasible design), verify
        (verify the best design at converged resolution, as `optimize_fully`'s: when it is
        infeasible at the step that resolves it, the optimization continues from it at that
        step, in this process, and its result replaces the best: best['verification'],
        best['continued_from']; details['verification']).
    fully : flexmbs.model.options.FullyOptions or dict, optional
        The options of every start's `optimize_fully` (its verify is not used: multistart
        verifies the best design only); default: the case's ``[optimize]`` table. Another
        optimizer's table than that of the multi-start's optimizer is not used (a
        SettingWarning, before any start is drawn), or a ModelError when the call gives both
        `fully` and options.optimizer (not 'auto').
    workers, dask, store : as `flexmbs.batch.run_batch` (store: one JSON file per start, so
        an interrupted multi-start resumes where it stopped: starts already in the store are
        not run again, unless their fingerprint (flexmbs.model.fingerprint: the case as resolved,
        the start, the optimizer and its options, the flexmbs version; for an adaptive case
        that its grid is chosen at the start) differs: those run again, with a warning naming
        their file).
    progress : bool, text stream or callable, optional
        True: a tqdm bar on stderr (starts done, best feasible objective so far); a text
        stream: that bar on the stream; a callable: called with each finished start's summary
        (its job name under 'name'); None/False (default): nothing shown.
    resume : bool, default False
        Continue an interrupted multi-start from `store` (required): the starts found there
        are taken as they are. (A rerun with the same store does so anyway; resume=True
        only checks that a store is given.)
    **keywords
        Deprecated: multistart's and optimize_fully's options as keywords (optimizer=...,
        seed=..., max_iterations=...), with a DeprecationWarning naming the new spelling.

    Returns
    -------
    MultistartResult
    """

    t0 = time.perf_counter()
    if keywords:
        options, fully = _from_keywords(options, fully, keywords)
    opts = None if options is None else build(MultistartOptions, options, "options")
    run = None if fully is None else build(FullyOptions, fully, "fully")
    # the caller named the optimizer and gave the starts' options (as optimize_fully's rule)
    explicit = (run is not None and opts is not None and "optimizer" in opts.model_fields_set
                and opts.optimizer != "auto")
    check_progress(progress)
    check_dask(dask)
    if not isinstance(resume, bool):
        raise ModelError(f"resume must be True or False, got {resume!r}")
    if resume and store is None:
        raise ModelError("multistart: resume=True needs the store folder of the interrupted "
                         "run (store=FOLDER; command line: --store FOLDER)")
    problem = load_problem(case)
    section = getattr(getattr(problem, "description", None), "optimize", None)
    if opts is None:        # the case's [optimize.multistart] table when the call gives none
        opts = MultistartOptions() if section is None else section.multistart
    if run is None:
        run = FullyOptions() if section is None else section.fully()
    if starts is not None:
        opts = build(MultistartOptions, dict(opts.as_dict(), starts=starts), "starts")
    optimizer, starts, sampler, seed = opts.optimizer, opts.starts, opts.sampler, opts.seed
    # another optimizer's table: checked once, here, before any start is drawn (not in the
    # workers); the starts run with it at its defaults
    chosen, why = choose_optimizer(optimizer, len(problem.variables))
    if optimizer != "auto":
        why = f"{chosen} (the multi-start's optimizer)"
    run = run.check_optimizer(chosen, why, explicit)
    start_range, candidates, verify = opts.start_range, opts.candidates, opts.verify
    best_tolerance, feasibility_tol = opts.best_tolerance, opts.feasibility_tol
    # every start's options, as plain data for the workers (unverified: the best is verified)
    options = run.model_copy(update=dict(verify=False)).as_dict()
    if adaptive(problem):           # its grid is re-chosen at each optimum: not the caller's
        problem = _own(problem, case)
    lo, hi = problem.lower, problem.upper
    if start_range is not None:
        try:
            slo, shi = (problem.mechanism.design_values(v) for v in start_range)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"start_range must be (lower, upper) designs: {exc}") from None
        if np.any(slo < lo) or np.any(shi > hi):
            raise ModelError(f"start_range {np.asarray(slo).tolist()}..{np.asarray(shi).tolist()} "
                             f"must lie inside the bounds {lo.tolist()}..{hi.tolist()}")
        lo, hi = slo, shi
    # every start's job, fingerprint and result are kept to the end: refused at once when
    # they cannot fit in memory, before any start is drawn or run
    check_sample_memory(starts, lo.size, "starts", START_RECORD_BYTES)
    pre = 0
    if candidates is None:
        x0 = start_designs(lo, hi, starts, sampler, seed)
    else:
        if candidates < starts:
            raise ModelError(f"candidates must be an integer >= starts ({starts}), got "
                             f"{candidates!r}")
        check_sample_memory(candidates, lo.size, "candidates")
        cand = start_designs(lo, hi, candidates, sampler, seed)
        key = []
        for x in cand:
            try:
                ev = problem.evaluate(x, gradient=False)
            except SimulationError:
                key.append((2, np.inf, np.inf))
                continue
            g = np.asarray(ev.constraints, float)
            viol = float(max(0.0, g.max())) if g.size else 0.0
            key.append((int(viol > feasibility_tol), viol if viol > feasibility_tol else 0.0,
                        float(ev.objective)))
        pre = len(cand)
        x0 = cand[sorted(range(len(cand)), key=lambda k: key[k])[:starts]]
    # plain data for the workers: the case path, or the Description (picklable)
    if isinstance(case, (str, Path, dict)):
        payload = str(case) if isinstance(case, Path) else case
    elif hasattr(problem, "description") and type(problem).__name__ == "Problem":
        payload = problem.description
    else:
        payload = problem                          # a Problem-like object (pickled for workers)
    jobs = {f"start{k:03d}": dict(case=payload, start=x.tolist(), optimizer=optimizer,
                                  options=options) for k, x in enumerate(x0)}
    def best_so_far(results):
        f = [o["objective"] for o in results.values() if o.get("design") is not None
             and o.get("max_violation") is not None and o["max_violation"] <= feasibility_tol]
        return describe_start(min(f) if f else None)

    if progress is None or progress is False:
        show = False
    elif callable(progress) and not hasattr(progress, "write"):
        def show(name, value):
            progress(dict(value, name=name))
    else:
        show = progress
    # what each stored start answers: the description as resolved (overrides applied), the
    # start, the optimizer and its options; a stored start that differs is run again
    # (an adaptive case's start runs on the grid chosen at the start: said in the fingerprint,
    # so that a start stored with another grid runs again)
    grid_at = dict(grid="chosen at the start") if adaptive(problem) else {}
    fps = {name: fingerprint(problem.description, "multistart start",
                             dict(start=job["start"], optimizer=optimizer, options=options,
                                  **grid_at))
           for name, job in jobs.items()}
    out = run_batch(start_job, jobs, workers=workers, dask=dask, store=store,
                    progress=show, label="starts", describe=best_so_far, fingerprints=fps)
    optima = []
    sims = pre
    for name in jobs:
        o = dict(out[name])
        sims += int(o.get("simulations") or 0)
        if o.get("design") is None:                # the start's simulation failed
            o["feasible"] = False
            optima.append(o)
            continue
        # feasibility re-checked by a fresh simulation, here; an adaptive case's on a grid
        # chosen at the local optimum (so that every optimum is judged at its tolerance)
        sims += 1
        if adaptive(problem):
            problem.adapt(o["design"])
            o["recheck_grid"] = problem.grid_summary()
            sims += PILOT_SIMULATIONS
        ev = problem.evaluate(o["design"], gradient=False)
        g = np.asarray(ev.constraints, float)
        o["max_violation"] = float(max(0.0, g.max())) if g.size else 0.0
        o["objective"] = float(ev.objective)
        o["feasible"] = o["max_violation"] <= feasibility_tol
        o["h"] = case_step(problem)
        optima.append(o)
    feas = [o for o in optima if o["feasible"]]
    best = min(feas, key=lambda o: o["objective"]) if feas else None
    reached = 0 if best is None else sum(
        o["objective"] <= best["objective"] * (1 + best_tolerance) for o in feas)
    verification = None
    if best is not None:
        if adaptive(problem):            # verified on the grid chosen at the best design
            problem.adapt(best["design"])
            sims += PILOT_SIMULATIONS
        best, verification, extra = _verified_best(problem, best, optimizer, options, verify,
                                                   feasibility_tol)
        sims += extra
    desc = problem.description
    return MultistartResult(
        case=desc.case.name, variables=list(problem.variables),
        units=[getattr(v, "unit", "") for v in desc.design], optimizer=optimizer,
        sampler=sampler, best=best, optima=optima, reached_best=int(reached),
        best_tolerance=best_tolerance, wall_time_s=time.perf_counter() - t0,
        simulations=sims, details=dict(seed=seed, candidates=candidates,
                                       objective_unit=objective_unit(problem),
                                       feasibility_tol=feasibility_tol,
                                       verification=verification,
                                       start_lower=np.asarray(lo).tolist(),
                                       start_upper=np.asarray(hi).tolist(),
                                       options=options, multistart=opts.as_dict()))


def _from_keywords(options, fully, keywords):
    """(options, fully) of a call that gave them as keywords (deprecated): multistart's own
    (MultistartOptions' fields) and optimize_fully's."""
    own = {k: keywords.pop(k) for k in list(keywords) if k in MultistartOptions.model_fields}
    for bad in ("history", "progress"):
        if bad in keywords:
            raise ModelError(f"multistart: option {bad!r} is per run; give store=FOLDER to keep "
                             "each start's result")
    if own:
        options = from_keywords("multistart", MultistartOptions, options, own, stacklevel=4)
    if keywords:
        fully = from_keywords("multistart", FullyOptions, fully, keywords,
                              tables={"mma_options": "mma", "nlopt_options": "nlopt"},
                              stacklevel=4)
    return options, fully


def case_step(problem):
    """The step (s) `problem` simulates on (its time.grid_h), None for a problem without one."""
    h = getattr(getattr(getattr(problem, "description", None), "time", None), "grid_h", None)
    return None if h is None else float(h)


def _tolerance(grid):
    """'rtol 0.01' / 'tol 1e-05' / both, of a grid summary."""
    return ", ".join(f"{k} {grid[k]:g}" for k in ("tol", "rtol") if grid.get(k) is not None)


def _verified_best(problem, best, optimizer, options, verify, feasibility_tol):
    """(best, its verification as JSON or None, simulations run): the best local optimum
    verified at converged resolution, continued at the finer step when infeasible there
    (flexmbs.methods.verified)."""

    verify = check_verify(verify)
    if verify is False:
        return best, None, 0
    stub = OptimizationResult(
        method="fully", case=problem.description.case.name, variables=list(problem.variables),
        units=[], design=np.asarray(best["design"], float),
        start=np.asarray(best["start"], float), objective=float(best["objective"]),
        objective_name="", mass_kg=None, max_violation=best["max_violation"],
        max_deviation_m=None, iterations=0, inner_iterations=None, evaluations=0,
        simulations=0, converged=bool(best["converged"]), reason=str(best["reason"]),
        history=[], wall_time_s=0.0)
    res = finish(problem, stub, lambda fine, x: optimize_fully(
        fine, x, optimizer=optimizer, options=dict(options, verify=False)), verify)
    if res.verification is None:
        return best, None, 0
    best = dict(best, verification=res.details["verification"])
    if res is not stub:                 # continued on the finer step
        # the continued run's verdicts, on the step it ran on (its h)
        best.update(design=[float(v) for v in res.design], objective=float(res.objective),
                    max_violation=float(res.max_violation), converged=bool(res.converged),
                    feasible=bool(res.max_violation <= feasibility_tol),
                    h=res.details.get("h"),
                    reason=res.reason, continued_from=res.details["continued_from"])
    else:
        best["reason"] = res.reason             # with the verification's words, if any
    return best, best["verification"], int(res.simulations)
