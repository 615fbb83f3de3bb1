"""Reproduce a study: the optimizations behind a paper's tables and figures, compared with
the published numbers.

A study (`flexmbs.paper.study`, ``docs/study-format.md``) declares, as data, each table (its case,
overrides, starting designs, methods, optimizer options, where its published numbers are, the
findings to check), each design-domain map and each figure. The shipped study is the paper's
(``cases/studies/paper.toml``); ``study=`` takes any other study file.

`reproduce(tables, out)` runs every optimization a table needs (each starting point x method
is one job of `flexmbs.batch.run_batch`: local worker processes by default, a Dask cluster when
an address is given), compares the results with the published numbers and returns a `Report`;
`flexmbs.paper.report.publish(report)` draws the figures and writes ``out/README.md``, a report a
reader can check without running anything. Every job's result is saved under ``out/jobs/``
as soon as it finishes, with the fingerprint of what it answers (flexmbs.model.fingerprint: its
case as resolved, its options); running the same command again skips what is done and still
answers the study (a job whose case file, overrides or options changed runs again, with a
warning naming its file). A table's
variants (extra rows with other options, or a multi-start, `flexmbs.paper.study.Variant`) run after
the table runs, stored under ``out/jobs/variants/``, and are reported as `VariantRow`s beside
the published optimum of their method, with their own checks (`variant_checks`).

The command line is ``flexmbs reproduce`` (flexmbs/cli/reproduce.py).

Examples
--------
>>> from flexmbs.paper.reproduce import reproduce
>>> from flexmbs.paper.report import publish
>>> report = publish(reproduce([1], "reproduction", workers=2))   # doctest: +SKIP
>>> row = report.rows[1][0]                                       # doctest: +SKIP
>>> row.method, row.mass_kg, row.paper["mass"], row.mass_difference   # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flexmbs.analysis.accuracy import describe_verification
from flexmbs.batch import check_dask, invalid_result, run_batch, stale_result, StoredResult
from flexmbs.errors import ModelError
from flexmbs.files import check_disk_space, check_writable, jsonable, read_stored, write_atomic
from flexmbs.methods.fully import optimize_fully
from flexmbs.methods.multistart import multistart as run_multistart
from flexmbs.methods.weakly import optimize_weakly
from flexmbs.paper.study import load_study, MapSpec, ROW_CHECKS, Run, Study, TableSpec, Variant
from flexmbs.problem import is_feasible, Problem
from flexmbs.sweep import job_fingerprint, max_deviation_job, MaxDeviationResult

# TABLES and MAPS (the shipped study's tables and maps) are read when first used (__getattr__)
__all__ = ["reproduce", "Report", "Row", "TableSpec", "Run", "paper_tables",
           "table_runs", "optimization_job", "map_jobs", "load_study", "Study",
           "MapSpec", "MapResult", "REGIONS", "Check", "table_checks", "paper_row",
           "build_rows", "design_spread", "active_steps_rows", "format_table",
           "format_active_steps", "simulate_paper_designs", "paper_design_text",
           "design_scan", "scan_key", "VariantRow", "variant_checks", "multistart_job",
           "variant_paper", "Variant"]


def __getattr__(name):
    """TABLES and MAPS: the tables and maps of the shipped study (read when first used)."""
    if name == "TABLES":
        return load_study().tables
    if name == "MAPS":
        return load_study().maps
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ============================================================================ published numbers
def paper_tables(study=None):
    """The published numbers of a study (dict, the JSON file its ``study.published`` names;
    default: the shipped study's ``paper_tables.json``)."""
    return load_study(study).published_data()


def _published(spec, data):
    node = data
    for key in spec.published:
        node = node[key]
    return node


# ============================================================================ runs and tables
def table_runs(numbers, study=None):
    """The distinct runs the given tables need, the costliest first: by the tables' ``cost``
    (the largest of the tables that share a run), then the fully coupled runs."""
    study = load_study(study)
    seen, cost = {}, {}
    for n in numbers:
        spec = study.tables[n]
        for r in spec.runs():
            seen.setdefault(r.name, r)
            cost[r.name] = max(cost.get(r.name, 0.0), spec.cost)
    return sorted(seen.values(), key=lambda r: (-cost[r.name], 0 if r.method == "fully" else 1))


class OptimizationJobResult(StoredResult):
    """A stored result of `optimization_job` (what the report reads; other keys allowed)."""
    design: list[float]
    mass_kg: float | None
    max_deviation_m: float | None
    max_violation: float | None = None
    iterations: int
    inner_iterations: int | None = None
    converged: bool
    reason: str
    wall_time_s: float
    simulations: int | None = None
    deviation_m: list[float] | None
    h_s: float
    history: list[dict] = []


class MultistartJobResult(StoredResult):
    """A stored result of `multistart_job` (what the report reads; other keys allowed)."""
    optima: list[dict]
    best: dict | None
    mass_kg: float | None
    design: list[float] | None
    max_deviation_m: float | None
    feasible: bool
    wall_time_s: float
    simulations: int | None = None
    reached_best: int | None = None


def _schema(variant):
    return OptimizationJobResult if variant.multistart is None else MultistartJobResult


def optimization_job(case, method, start, overrides=None, options=None):
    """Run one optimization; return its result as a JSON-ready dict.

    A top-level function, so that `run_batch` can send it to worker processes or a Dask
    cluster. The dict is `OptimizationResult.to_dict()` plus ``deviation_m`` (the final
    design's constrained deviation at every time step), ``h_s`` and ``case_overrides``.

    Parameters
    ----------
    case : str
        The name of a shipped case or a path to a case file.
    method : {'weakly', 'fully'}
    start : list of float
        Starting design (the variables' units).
    overrides : dict, optional
        Case keys to replace (`flexmbs.problem.Problem`), e.g. {'time.t_end': 0.66}.
    options : dict, optional
        The method's options (flexmbs.model.options: WeaklyOptions / FullyOptions' fields;
        the fully coupled method's may name its `optimizer`).
    """

    prob = Problem(case, overrides=overrides or None)
    if method not in ("weakly", "fully"):
        raise ModelError(f"method must be 'weakly' or 'fully', got {method!r}")
    # the published method as published, its optimum verified at converged resolution and
    # reported (a finding that holds only at the case's step is not reproduced), not continued
    options = dict(options or {})
    options.setdefault("verify", "check")
    if method == "fully":
        r = optimize_fully(prob, np.asarray(start, float), optimizer=options.pop("optimizer", None),
                           options=options)
    else:
        r = optimize_weakly(prob, np.asarray(start, float), options=options)
    d = r.to_dict()
    d["deviation_m"] = None if r.deviation is None else [float(v) for v in r.deviation]
    d["h_s"] = float(prob.description.time.grid_h)
    d["case_overrides"] = dict(overrides or {})
    d["case_name"] = case
    return d


def multistart_job(case, overrides=None, options=None, multistart=None, workers=None,
                   dask=None, store=None, progress=None):
    """Run a multi-start (`flexmbs.methods.multistart.multistart`: its starts through the
    batch layer, on `workers` local processes or a Dask scheduler, each stored in `store` as it
    finishes) and return its result as a JSON-ready dict: `MultistartResult.to_dict()` plus,
    for the best feasible design re-simulated here (at the step of its verification, when
    verified), ``mass_kg``, ``design``, ``max_deviation_m``, ``t_at_max_s``, ``limit_m`` and
    ``feasible``; ``mass_kg`` None when no start ended feasible.

    multistart : dict of multistart's settings (MultistartOptions' fields: starts, optimizer,
        sampler, seed, candidates, best_tolerance); options : FullyOptions' fields for every
        start (flexmbs.model.options).
    """

    ms = dict(multistart or {})
    prob = Problem(case, overrides=overrides or None)
    options = dict(options or {})
    ms.setdefault("verify", options.pop("verify", "check"))       # as optimization_job's
    res = run_multistart(prob, options=ms, fully=options, workers=workers, dask=dask,
                         store=store, progress=progress)
    d = res.to_dict()
    d.update(mass_kg=None, design=None, max_deviation_m=None, feasible=False,
             case_overrides=dict(overrides or {}), case_name=case)
    if res.best is not None:
        # at the step its verification settled on (the case's own when not verified, or
        # when its steps are error-controlled: time.h = "auto" takes no fixed step)
        ver = res.details.get("verification")
        fixed = ver and not prob.description.time.adaptive
        at = dict(overrides or {}, **({"time.h": ver["h"]} if fixed else {}))
        chk = max_deviation_job(case, res.best["design"], at or None)
        d.update(mass_kg=chk["mass_kg"], design=chk["design"],
                 max_deviation_m=chk["max_deviation_m"], t_at_max_s=chk["t_at_max_s"],
                 limit_m=chk["limit_m"], feasible=bool(res.best["feasible"]))
    return d


optimization_job.result_schema = OptimizationJobResult
multistart_job.result_schema = MultistartJobResult


# ============================================================================ design-domain maps
#: Regions of a map.
REGIONS = ("full", "zoom")


def map_jobs(spec, n, region="full"):
    """Jobs of `flexmbs.sweep.max_deviation_job` for a map: one simulation per grid point.

    Names carry the design (``p2-30.000-p4-25.000``), so grids of different resolutions or
    regions share the points they have in common in a store.
    """
    c = Problem(spec.case, overrides=dict(spec.overrides))
    names = list(c.variables)
    a, b = spec.grid(n, c.lower, c.upper, region, names)
    i, j = spec.indices(names)
    jobs = {}
    for va in a:
        for vb in b:
            p = np.array(c.start, float)
            for k, v in spec.fixed:
                p[names.index(k)] = v
            p[i], p[j] = va, vb
            name = f"{names[i]}-{va:.3f}-{names[j]}-{vb:.3f}"
            jobs[name] = dict(case=spec.case, design=[float(v) for v in p],
                              overrides=dict(spec.overrides), steps=[spec.step - 1])
    return jobs


@dataclass
class MapResult:
    """A computed map.

    Attributes
    ----------
    spec : MapSpec
    grids : dict region -> (a, b, at_step, maximum)
        a, b: values of the first (rows) and second (columns) mapped variable; at_step:
        (na, nb) deviation (m) at spec.step; maximum: (na, nb) maximum deviation over all steps.
    names : tuple of the mapped variables' names
    simulations : int
    wall_time_s : float
    indices : tuple of the mapped variables' indices in the design
    h_s : float
        The time step of the map's case (t = (step - 1) h).
    units : tuple of the mapped variables' units
    """
    spec: MapSpec
    grids: dict
    names: tuple
    simulations: int = 0
    wall_time_s: float = 0.0
    indices: tuple = (0, 1)
    h_s: float = 5e-4
    units: tuple = ("", "")


def _collect_map(spec, n, results, region):
    c = Problem(spec.case, overrides=dict(spec.overrides))
    names = list(c.variables)
    a, b = spec.grid(n, c.lower, c.upper, region, names)
    keys = list(map_jobs(spec, n, region))
    at = np.array([results[k]["deviation_at_steps_m"][0] for k in keys]).reshape(n, n)
    mx = np.array([results[k]["max_deviation_m"] for k in keys]).reshape(n, n)
    i, j = spec.indices(names)
    units = tuple(v.unit or "" for v in c.description.design)
    return (a, b, at, mx), (names[i], names[j]), (i, j), float(c.description.time.grid_h), \
        (units[i], units[j])


# ============================================================================ comparison
@dataclass
class Row:
    """One row of a table: a run of flexmbs beside the paper's numbers for it.

    Attributes
    ----------
    table : int
    run : Run
    paper : dict
        The published row ({'mass', 'iter', 'inner_iter', 'p'}, some None when missing; or
        {'converged': False, 'behaviour': ...}).
    result : dict
        `optimization_job`'s result.
    paper_design : dict or None
        The paper's published design simulated by flexmbs (`simulate_paper_designs`):
        mass_kg, max_deviation_m, t_at_max_s; None when the paper gives no design.
    """
    table: int
    run: Run
    paper: dict
    result: dict
    paper_design: dict | None = None

    method = property(lambda self: self.run.method)
    start_mm = property(lambda self: list(self.run.start_mm))
    mass_kg = property(lambda self: float(self.result["mass_kg"]))
    design_mm = property(lambda self: np.asarray(self.result["design"], float))
    iterations = property(lambda self: self.result["iterations"])
    inner_iterations = property(lambda self: self.result["inner_iterations"])
    converged = property(lambda self: bool(self.result["converged"]))
    reason = property(lambda self: self.result["reason"])
    max_deviation_m = property(lambda self: float(self.result["max_deviation_m"]))
    wall_time_s = property(lambda self: float(self.result["wall_time_s"]))

    @property
    def mass_difference(self):
        """(flexmbs - paper) / paper of the mass, or None."""
        m = self.paper.get("mass")
        return None if m is None else (self.mass_kg - m) / m

    @property
    def design_differences(self):
        """(flexmbs - paper) / paper of every design variable (None where not published)."""
        p = self.paper.get("p")
        if p is None:
            return [None] * len(self.design_mm)
        return [None if q is None else (v - q) / q for v, q in zip(self.design_mm, p)]

    @property
    def max_design_difference(self):
        d = [abs(v) for v in self.design_differences if v is not None]
        return max(d) if d else None

    def to_dict(self):
        return dict(table=self.table, method=self.method, start_mm=self.start_mm,
                    job=self.run.name, paper=self.paper,
                    flexmbs=dict(mass_kg=self.mass_kg, iterations=self.iterations,
                                 inner_iterations=self.inner_iterations,
                                 design_mm=self.design_mm.tolist(), converged=self.converged,
                                 reason=self.reason, max_deviation_m=self.max_deviation_m,
                                 simulations=self.result.get("simulations"),
                                 wall_time_s=self.wall_time_s),
                    mass_difference=self.mass_difference,
                    design_differences=self.design_differences,
                    paper_design_in_flexmbs=self.paper_design)


def verification_text(result):
    """One line on a run's verification at converged resolution (a single run's, or a
    multi-start's with its best start's continuation), or None when it was not verified."""
    best = result.get("best") or {}
    return describe_verification(dict(result, continued_from=result.get("continued_from")
                                      or best.get("continued_from")))


def verified_feasible(result):
    """A run's design holds at converged resolution (True when it was not verified: its own
    re-simulation is all there is)."""
    v = result.get("verification")
    return True if not v else bool(v["verified"] and v["feasible"])


def simulate_paper_designs(rows):
    """Simulate every published design of the rows with flexmbs (one simulation each) and set
    `Row.paper_design`: does the paper's optimum sit on its 1 mm constraint in flexmbs's model?
    """
    done = {}
    for r in rows:
        p = r.paper.get("p")
        if p is None or any(v is None for v in p):
            continue
        key = (r.run.case, r.run.overrides, tuple(p))
        if key not in done:
            done[key] = max_deviation_job(r.run.case, list(p), dict(r.run.overrides))
        r.paper_design = done[key]


def paper_design_text(row):
    """E.g. "the paper's design simulated by flexmbs: 2.9675 kg, maximum deviation 1.031 mm at
    0.3085 s (infeasible, 3.1 % above the limit)"; '' when the paper gives no design."""
    d = row.paper_design
    if not d:
        return ""
    rel = d["max_deviation_m"] / d.get("limit_m", 1e-3) - 1.0
    state = ("on its limit within 1 %" if abs(rel) <= 0.01 else
             f"feasible, {100 * -rel:.1f} % below the limit" if rel < 0 else
             f"infeasible, {100 * rel:.1f} % above the limit")
    return (f"the paper's design simulated by flexmbs: {d['mass_kg']:.4f} kg, maximum deviation "
            f"{d['max_deviation_m'] * 1e3:.3f} mm at {d['t_at_max_s']:.4f} s ({state})")


def scan_key(spec):
    """The key of a table's scan in `Report.extra` (and comparison.json)."""
    return f"table{spec.number}_{spec.scan.variable}_scan"


def design_scan(spec):
    """Maximum constrained deviation over one design variable of a table's case (its
    ``scan``: the variable, its values, and the other variables held at each of ``others``).

    Shows how strongly (and whether monotonically) the peak deviation depends on the design.
    Returns a list of dicts {NAME_UNIT: value for every variable, mass_kg, max_deviation_m,
    t_at_max_s}, e.g. {'p1_mm': 50.0, 'p2_mm': 15.0, ...}.
    """
    sc = spec.scan
    i = spec.index(sc.variable)
    keys = [f"{n}_{u}" if u else n for n, u in zip(spec.variables, spec.units)]
    out = []
    for rest in sc.others:
        for v in sc.values:
            design = [*rest[:i], v, *rest[i:]]
            r = max_deviation_job(spec.case, design, dict(spec.overrides) or None)
            row = {keys[i]: v}
            row.update({k: x for k, x in zip(keys, design) if k != keys[i]})
            row.update(mass_kg=r["mass_kg"], max_deviation_m=r["max_deviation_m"],
                       t_at_max_s=r["t_at_max_s"])
            out.append(row)
    return out


def paper_row(table, method, start_mm, data=None, study=None):
    """The published numbers of one row of a table (dict)."""
    study = load_study(study)
    spec = study.tables[table]
    if spec.kind != "rows":
        raise ModelError(f"table {table} is of kind {spec.kind!r}: it has no rows")
    data = study.published_data() if data is None else data
    tab = _published(spec, data)
    entry = tab[method]
    if isinstance(entry, list):
        starts = [list(map(float, s)) for s in tab["starts"]]
        entry = entry[starts.index(list(map(float, start_mm)))]
    return dict(entry)


def build_rows(table, results, data=None, study=None):
    """The rows of a table from the job results {job name: result}."""
    study = load_study(study)
    data = study.published_data() if data is None else data
    return [Row(table, r, paper_row(table, r.method, r.start_mm, data, study), results[r.name])
            for r in study.tables[table].runs()]


def design_spread(designs):
    """Largest relative spread of the design variables over several designs:
    max_i (max - min) / mean of p_i."""
    d = np.asarray(designs, float)
    return float(np.max((d.max(axis=0) - d.min(axis=0)) / d.mean(axis=0)))


@dataclass
class Check:
    """One published finding checked on flexmbs's results.

    ok: True (reproduced), False (not reproduced) or None (a number reported beside the
    paper's without a criterion, e.g. a local optimum).
    """
    table: int
    what: str
    paper: str
    flexmbs: str
    ok: bool | None

    @property
    def verdict(self):
        return {True: "ok", False: "DIFFERS", None: "reported"}[self.ok]


def _pct(v):
    return "-" if v is None else f"{100 * v:+.2f} %"


def _unit(spec):
    """' mm' when every design variable of the table is in mm ('' for mixed units)."""
    return f" {spec.units[0]}" if len(set(spec.units)) == 1 and spec.units[0] else ""


def _list(values, spec=".2f"):
    return "[" + ", ".join(format(v, spec) for v in values) + "]"


_COUNT = {2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight",
          9: "nine", 10: "ten"}


def _row_check(spec, c, r):
    """A check of type c on row r (a Check), or None when the row has nothing to compare."""
    n = spec.number
    start = "[" + ", ".join(f"{v:g}" for v in r.start_mm) + "]"
    tag = f"{r.method}, start {start}"
    conv = "" if r.converged else ", NOT converged"
    if c.type == "not_converged":
        return Check(n, f"{tag}: {c.what or 'does not converge'}",
                     c.paper or "does not converge",
                     ("converged" if r.converged else "not converged") + f" ({r.reason})",
                     not r.converged)
    if c.type == "mass_within":
        if r.paper.get("mass") is None:
            return None
        # a mass counts only when the run converged, to a design that holds at converged
        # resolution
        ver = "" if verified_feasible(r.result) else ", NOT verified feasible"
        return Check(n, f"{tag}: {c.what or f'converged, mass within {100 * c.rel:g} %'}",
                     c.paper or f"{r.paper['mass']:.3f} kg",
                     f"{r.mass_kg:.4f} kg ({_pct(r.mass_difference)}{conv}{ver})",
                     r.converged and abs(r.mass_difference) <= c.rel
                     and verified_feasible(r.result))
    if c.type == "design_within":
        if r.paper.get("mass") is None or not r.paper.get("p"):
            return None
        md = r.max_design_difference
        u = _unit(spec)
        return Check(n, f"{tag}: {c.what or f'every p_i within {100 * c.rel:g} %'}",
                     c.paper or _list(r.paper["p"]) + u,
                     _list(r.design_mm) + u + f" (largest {100 * md:.2f} %)", md <= c.rel)
    if c.type == "local_optimum_reported":
        if r.paper.get("mass") is None:
            return None
        u = _unit(spec)
        return Check(n, c.what or f"{r.method} coupled optimum ({c.note})",
                     c.paper or f"{r.paper['mass']:.3f} kg, " + _list(r.paper["p"]) + u,
                     f"{r.mass_kg:.3f} kg ({_pct(r.mass_difference)}), "
                     + _list(r.design_mm) + u, None)
    raise ModelError(f"unknown row check type {c.type!r}")    # pragma: no cover


def _table_check(spec, c, by):
    """A check of a table-level type c on the rows by method, or None when they are missing."""
    n = spec.number
    if c.type == "converges":
        if c.method not in by:
            return None
        r = by[c.method][0]
        it = r.paper.get("iter")
        return Check(n, c.what or f"{c.method} coupled converges",
                     c.paper or ("converged" + (f" in {it} iterations" if it else "")),
                     ("converged" if r.converged else "NOT converged")
                     + f" in {r.iterations} iterations", r.converged)
    if c.type in ("starts_agree_within", "starts_differ_more"):
        other = c.than if c.type == "starts_differ_more" else None
        rows = by.get(c.method, [])
        if len(rows) < 2 or (other is not None and len(by.get(other, [])) < 2):
            return None
        s = design_spread([r.design_mm for r in rows])
        ps = [r.paper.get("p") for r in rows]
        p = (f"spread {100 * design_spread(ps):.2f} %"
             if all(q and None not in q for q in ps) else "-")
        count = _COUNT.get(len(rows), str(len(rows)))
        if other is None:
            return Check(n, c.what or f"{c.method} coupled designs of the {count} starts agree "
                         f"within {100 * c.rel:g} %", c.paper or p, f"spread {100 * s:.2f} %",
                         s <= c.rel)
        so = design_spread([r.design_mm for r in by[other]])
        return Check(n, c.what or f"{c.method} coupled designs of the {count} starts differ by "
                     "more", c.paper or p, f"spread {100 * s:.2f} %", s > so)
    if c.type == "masses_ratio_at_least":
        if c.numerator not in by or c.denominator not in by:
            return None
        a, b = by[c.numerator][0], by[c.denominator][0]
        ratio = a.mass_kg / b.mass_kg
        pa, pb = a.paper.get("mass"), b.paper.get("mass")
        return Check(n, c.what or f"{c.denominator} coupled at least {c.ratio:g} x lighter than "
                     f"{c.numerator} coupled",
                     c.paper or ("-" if not (pa and pb) else f"{pa / pb:.1f} x"),
                     f"{ratio:.1f} x", ratio >= c.ratio)
    if c.type in ("variables_at_bound", "variables_off_bound"):
        if c.method not in by:
            return None
        r = by[c.method][0]
        idx = [spec.index(v) for v in c.variables]
        bounds = np.array([(spec.lower if c.bound == "lower" else spec.upper)[k] for k in idx])
        x = r.design_mm[idx]
        unit = spec.units[idx[0]]
        u = f" {unit}" if unit else ""
        names = " and ".join(c.variables)
        got = ", ".join(f"{v} = {x[k]:.2f}" for k, v in enumerate(c.variables)) + u
        b = bounds[0] if np.all(bounds == bounds[0]) else None
        if c.type == "variables_at_bound":
            ok = (x <= bounds * (1 + c.rel)) if c.bound == "lower" else (x >= bounds * (1 - c.rel))
            where = f"the {b:g}{u} bound" if b is not None else f"their {c.bound} bounds"
            return Check(n, c.what or f"{c.method} coupled: {names} at {where}",
                         c.paper or " = ".join(c.variables) + (f" = {b:g}{u}" if b is not None
                                                               else f" at the {c.bound} bound"),
                         got, bool(np.all(ok)))
        ok = (x > bounds * (1 + c.rel)) if c.bound == "lower" else (x < bounds * (1 - c.rel))
        side = "above" if c.bound == "lower" else "below"
        return Check(n, c.what or f"{c.method} coupled: {names} stay {side} the bound",
                     c.paper or f"{names} off the {c.bound} bound", got, bool(np.all(ok)))
    raise ModelError(f"unknown check type {c.type!r}")      # pragma: no cover


def table_checks(table, rows, study=None):
    """The checks of one table (list of Check): its study's checks on its rows.

    Row checks (`flexmbs.paper.study.ROW_CHECKS`) listed one after another form a group: each row
    in turn gets the group's checks that apply to its method; a table check applies once,
    where it is listed."""
    spec = load_study(study).tables[table] if not isinstance(table, TableSpec) else table
    by = {}
    for r in rows:
        by.setdefault(r.method, []).append(r)
    out, group = [], []

    def flush():
        for r in rows:
            for c in group:
                if c.methods is None or r.method in c.methods:
                    ck = _row_check(spec, c, r)
                    if ck is not None:
                        out.append(ck)
        group.clear()

    for c in spec.checks:
        if c.type in ROW_CHECKS:
            group.append(c)
            continue
        flush()
        ck = _table_check(spec, c, by)
        if ck is not None:
            out.append(ck)
    flush()
    return out


# ============================================================================ variants
def variant_paper(variant, data=None, study=None):
    """The published row of a variant's method (dict): the table's row from the variant's
    start, or from the table's first start when that is not a published start (a
    multi-start)."""
    study = load_study(study)
    spec = study.tables[variant.table]
    data = study.published_data() if data is None else data
    tab = _published(spec, data)
    entry = tab[variant.method]
    if isinstance(entry, list):
        starts = [list(map(float, s)) for s in tab["starts"]]
        start = list(variant.start_mm or spec.starts[0])
        entry = entry[starts.index(start) if start in starts else 0]
    return dict(entry)


@dataclass
class VariantRow:
    """An extra row of a table (`flexmbs.paper.study.Variant`) beside the published numbers of its
    method.

    result: `optimization_job`'s result (a single run) or `multistart_job`'s (a multi-start:
    the best feasible design, every start's local optimum under 'optima')."""
    variant: Variant
    paper: dict
    result: dict

    label = property(lambda self: self.variant.label)
    method = property(lambda self: self.variant.method)
    is_multistart = property(lambda self: self.variant.multistart is not None)

    @property
    def mass_kg(self):
        """The design's mass (a multi-start: the best feasible one's; None without any)."""
        m = self.result.get("mass_kg")
        return None if m is None else float(m)

    @property
    def design_mm(self):
        d = self.result.get("design")
        return None if d is None else np.asarray(d, float)

    @property
    def feasible(self):
        """The design is feasible: the run's own re-simulated verdict (``feasible``), else
        its maximum violation <= FEASIBILITY_TOL (flexmbs.problem); and, when the run was verified, feasible at converged
        resolution (`verified_feasible`)."""
        if not verified_feasible(self.result):
            return False
        if "feasible" in self.result and self.result["feasible"] is not None:
            return bool(self.result["feasible"])
        v = self.result.get("max_violation")
        return v is not None and is_feasible(v)

    @property
    def mass_difference(self):
        m = self.paper.get("mass")
        return None if m is None or self.mass_kg is None else (self.mass_kg - m) / m

    @property
    def design_differences(self):
        p, d = self.paper.get("p"), self.design_mm
        if d is None:
            return []
        if p is None:
            return [None] * len(d)
        return [None if q is None else (v - q) / q for v, q in zip(d, p)]

    def spread(self):
        """A multi-start's local optima: dict(starts, feasible, best, worst (feasible masses,
        kg), reached_best (within best_tolerance of the best), best_tolerance, within_paper
        {rel: count} is added by the checks); None for a single run."""
        if not self.is_multistart:
            return None
        opt = self.result.get("optima") or []
        f = [float(o["objective"]) for o in opt if o.get("feasible")]
        return dict(starts=len(opt), feasible=len(f), best=min(f) if f else None,
                    worst=max(f) if f else None,
                    reached_best=int(self.result.get("reached_best") or 0),
                    best_tolerance=float(self.result.get("best_tolerance") or 0.0))

    def within_paper(self, rel):
        """How many starts (a multi-start) or whether the run (1/0) ended feasible at most
        (1 + rel) x the published mass."""
        pm = self.paper.get("mass")
        if pm is None:
            return 0
        if self.is_multistart:
            return sum(1 for o in self.result.get("optima") or []
                       if o.get("feasible") and float(o["objective"]) <= pm * (1 + rel))
        return int(self.feasible and self.mass_kg is not None and self.mass_kg <= pm * (1 + rel))

    def status(self):
        """One line: converged / feasibility, deviation, simulations, time (and the spread)."""
        r = self.result
        dev = r.get("max_deviation_m")
        dev_txt = "-" if dev is None else f"{float(dev) * 1e3:.4f} mm"
        if self.is_multistart:
            sp = self.spread()
            tol = 100 * sp["best_tolerance"]
            head = (f"{sp['starts']} starts ({r.get('sampler')}, optimizer {r.get('optimizer')}"
                    + (f", the {sp['starts']} best of {r.get('candidates')} candidates"
                       if r.get("candidates") else "") + f"): {sp['feasible']} of "
                    f"{sp['starts']} ended feasible (re-simulated)")
            if sp["best"] is None:
                return head + f"; no feasible design; {r.get('simulations')} simulations, " \
                    f"{float(r.get('wall_time_s', 0.0)):.1f} s"
            return (head + f"; local optima {sp['best']:.4f}-{sp['worst']:.4f} kg; "
                    f"{sp['reached_best']} of {sp['starts']} within {tol:g} % of the best; "
                    f"maximum deviation of the best design {dev_txt}; {r.get('simulations')} "
                    f"simulations, {float(r.get('wall_time_s', 0.0)):.1f} s"
                    + self._verification())
        conv = "converged" if r.get("converged") else "not converged"
        return (f"{conv} ({r.get('reason')}); {'feasible' if self.feasible else 'INFEASIBLE'}, "
                f"maximum deviation {dev_txt}; {r.get('simulations')} simulations, "
                f"{float(r.get('wall_time_s', 0.0)):.1f} s" + self._verification())

    def _verification(self):
        ver = verification_text(self.result)
        return "" if ver is None else f"; {ver}"

    def to_dict(self):
        return dict(table=self.variant.table, key=self.variant.key, label=self.label,
                    method=self.method, job=self.variant.name, options=self.variant.options,
                    multistart=self.variant.multistart,
                    start_mm=None if self.variant.start_mm is None else list(self.variant.start_mm),
                    paper=self.paper,
                    flexmbs=dict(mass_kg=self.mass_kg,
                                 design_mm=None if self.design_mm is None
                                 else self.design_mm.tolist(),
                                 feasible=self.feasible,
                                 max_deviation_m=self.result.get("max_deviation_m"),
                                 converged=self.result.get("converged"),
                                 reason=self.result.get("reason"),
                                 iterations=self.result.get("iterations"),
                                 simulations=self.result.get("simulations"),
                                 wall_time_s=self.result.get("wall_time_s")),
                    spread=self.spread(), mass_difference=self.mass_difference,
                    design_differences=self.design_differences)


def _variant_check(c, v):
    """A check of a variant row (a Check)."""
    n = v.variant.table
    tag = f"variant {v.label}"
    pm = v.paper.get("mass")
    if c.type == "mass_at_most":
        what = "best feasible mass" if v.is_multistart else "mass"
        if v.mass_kg is None:
            return Check(n, f"{tag}: {c.what or f'{what} within {100 * c.rel:g} % of the paper or lighter'}",
                         c.paper or ("-" if pm is None else f"{pm:.3f} kg"),
                         "no feasible design", False)
        if pm is None:
            return None
        lim = pm * (1 + c.rel)
        # a mass counts only for a design that holds at converged resolution
        ver = "" if verified_feasible(v.result) else ", NOT verified feasible"
        return Check(n, f"{tag}: {c.what or f'{what} within {100 * c.rel:g} % of the paper or lighter'}",
                     c.paper or f"{pm:.3f} kg (at most {lim:.4f} kg)",
                     f"{v.mass_kg:.4f} kg ({_pct(v.mass_difference)}{ver})",
                     v.mass_kg <= lim and verified_feasible(v.result))
    if c.type == "feasible":
        dev = v.result.get("max_deviation_m")
        lim = v.result.get("limit_m")
        got = ("feasible" if v.feasible else "INFEASIBLE") + (
            "" if dev is None else f", maximum deviation {float(dev) * 1e3:.4f} mm"
            + ("" if lim is None else f" (limit {float(lim) * 1e3:g} mm)"))
        if v.is_multistart:
            sp = v.spread()
            got += f"; {sp['feasible']} of {sp['starts']} starts feasible"
        return Check(n, f"{tag}: {c.what or 'feasible (re-simulated)'}",
                     c.paper or "-", got, v.feasible)
    sp = v.spread()
    if c.type == "reached_by_at_least":
        if c.rel is None:
            k = sp["reached_best"]
            what = (f"at least {c.n} of {sp['starts']} starts reach the best design (within "
                    f"{100 * sp['best_tolerance']:g} %)")
        else:
            if pm is None:
                return None
            k = v.within_paper(c.rel)
            what = (f"at least {c.n} of {sp['starts']} starts feasible within {100 * c.rel:g} % "
                    f"of the paper or lighter")
        return Check(n, f"{tag}: {c.what or what}", c.paper or "-",
                     f"{k} of {sp['starts']}", k >= c.n)
    if c.type == "spread_reported":
        if sp["best"] is None:
            got = f"no feasible design from {sp['starts']} starts"
        else:
            got = (f"local optima {sp['best']:.4f}-{sp['worst']:.4f} kg; {sp['reached_best']} of "
                   f"{sp['starts']} within {100 * sp['best_tolerance']:g} % of the best"
                   + ("" if pm is None else f", {v.within_paper(sp['best_tolerance'])} within "
                      f"{100 * sp['best_tolerance']:g} % of the paper or lighter")
                   + f"; {sp['feasible']} of {sp['starts']} feasible")
        return Check(n, f"{tag}: {c.what or 'spread of the local optima'}",
                     c.paper or ("-" if pm is None else f"{pm:.3f} kg"), got, None)
    raise ModelError(f"unknown variant check type {c.type!r}")    # pragma: no cover


def variant_checks(rows):
    """The checks of variant rows (list of Check), each row's in its study's order."""
    out = []
    for v in rows:
        for c in v.variant.checks:
            ck = _variant_check(c, v)
            if ck is not None:
                out.append(ck)
    return out


def format_variants(rows, unit="mm"):
    """The terminal lines of a table's variant rows."""
    lines = []
    for v in rows:
        pm = v.paper.get("mass")
        d = v.design_mm
        p = "-" if d is None else _list(d) + (f" {unit}" if unit else "")
        m = "-" if v.mass_kg is None else f"{v.mass_kg:.4f} kg ({_pct(v.mass_difference)})"
        lines.append(f"variant {v.label} ({v.method} coupled, {v.variant.options_text}): "
                     f"flexmbs {m}, {p}; paper {_fmt(pm, '.3f')} kg")
        lines.append(f"    {v.status()}")
    return lines


# ============================================================================ text output
def _pct_text(v):
    """A relative difference in per cent with its sign ('+0.00' for a zero), '-' for None."""
    return "-" if v is None else f"{100 * v:+.2f}".replace("-0.00", "+0.00")


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def format_table(table, rows, checks=None, title="", names=None, unit="mm"):
    """The comparison of one table as text: for every row the paper, flexmbs and the
    difference in %, then the run's status, then the checks. names: of the design variables
    (default p1, p2, ...)."""
    nv = len(rows[0].design_mm)
    names = list(names) if names else [f"p{k + 1}" for k in range(nv)]
    lines = [f"Table {table}: {title}",
             f"{'':30s}{'mass kg':>9s}{'iter':>6s}{'inner':>7s}"
             + "".join(f"{n:>9s}" for n in names) + (f"   ({unit})" if unit else "")]
    for r in rows:
        start = "[" + ", ".join(f"{v:g}" for v in r.start_mm) + "]"
        lines.append(f"{r.method} coupled, start {start}")
        pp = r.paper.get("p") or [None] * nv
        if r.paper.get("mass") is None and r.paper.get("behaviour"):
            lines.append(f"    {'paper':26s}{r.paper['behaviour']}")
        if r.paper.get("mass") is not None or any(v is not None for v in pp):
            lines.append(f"    {'paper':26s}{_fmt(r.paper.get('mass'), '9.3f')}"
                         f"{_fmt(r.paper.get('iter'), '6d'):>6s}"
                         f"{_fmt(r.paper.get('inner_iter'), '7d'):>7s}"
                         + "".join(f"{_fmt(v, '9.2f'):>9s}" for v in pp))
        lines.append(f"    {'flexmbs':26s}{r.mass_kg:9.4f}{r.iterations:6d}"
                     f"{_fmt(r.inner_iterations, '7d'):>7s}"
                     + "".join(f"{v:9.2f}" for v in r.design_mm))
        if r.mass_difference is not None or r.paper.get("p"):
            dd = r.design_differences
            lines.append(f"    {'difference (%)':26s}{_pct_text(r.mass_difference):>9s}{'':13s}"
                         + "".join(f"{_pct_text(v):>9s}" for v in dd))
        if r.paper_design:
            lines.append(f"    {paper_design_text(r)}")
        lines.append(f"    flexmbs: {'converged' if r.converged else 'NOT converged'} "
                     f"({r.reason}); max deviation {r.max_deviation_m * 1e3:.4f} mm; "
                     f"{r.result.get('simulations')} simulations; {r.wall_time_s:.1f} s")
        ver = verification_text(r.result)
        if ver:
            lines.append(f"    {ver}")
    for c in checks or []:
        lines.append(f"  [{c.verdict}] {c.what}: paper {c.paper}, flexmbs {c.flexmbs}")
    return "\n".join(lines)


def _steps_text(steps):
    """[238, 239, 240, 241, 242, 1338] -> '238-242, 1338'; [] -> '/'."""
    if steps is None:
        return "-"
    if isinstance(steps, str):
        return steps
    steps = sorted(int(s) for s in steps)
    if not steps:
        return "/"
    parts, a, b = [], steps[0], steps[0]
    for s in steps[1:]:
        if s == b + 1:
            b = s
            continue
        parts.append(f"{a}" if a == b else f"{a}-{b}")
        a = b = s
    parts.append(f"{a}" if a == b else f"{a}-{b}")
    return ", ".join(parts)


def _active(rec, key="active_steps"):
    """The active steps of a history record (the union over its constraint names), or None."""
    act = rec.get(key)
    if act is None:
        return None
    if isinstance(act, dict):
        return sorted({s for v in act.values() for s in v})
    return list(act)



def active_steps_rows(weakly, fully, published):
    """A table of kind 'active_steps' beside flexmbs: list of (iteration, paper weakly, flexmbs
    weakly static problem, flexmbs weakly simulation, paper fully, flexmbs fully), step lists
    as text.

    weakly / fully: the results (dicts) of the table's two runs; published: its published
    entry, {'weakly_by_cycle': {cycle: steps}, 'fully_by_iteration': {'a-b' or 'a': steps}}.
    For the weakly coupled method flexmbs lists, per cycle, the steps active at the solution of
    the static problem that produced the cycle's design and the steps where the cycle's full
    simulation is within 0.1 % of the limit; for the fully coupled method the steps of the
    iterate within 0.1 % of the limit (iteration 0 is the start).
    """
    pw = published["weakly_by_cycle"]
    pf = {}
    for k, v in published["fully_by_iteration"].items():
        a, _, b = k.partition("-")
        for i in range(int(a), int(b or a) + 1):
            pf[i] = v
    wh = {r["iteration"]: r for r in (weakly or {}).get("history", [])}
    fh = {r["iteration"]: r for r in (fully or {}).get("history", [])}
    n = max([0, *map(int, pw), *pf, *wh, *fh])
    out = []
    for i in range(0 if 0 in fh else 1, n + 1):
        w = wh.get(i)
        f = fh.get(i)
        out.append((i, _steps_text(pw.get(str(i))) if str(i) in pw else "",
                    "" if w is None else _steps_text(_active(w)),
                    "" if w is None else _steps_text(_active(w, "simulation_active_steps")),
                    _steps_text(pf[i]) if i in pf else "",
                    "" if f is None else _steps_text(_active(f))))
    if weakly is not None and weakly.get("converged"):
        last = max(wh) if wh else 0
        out = [r if r[0] != last else (r[0], r[1], r[2] + " (converged)", r[3], r[4], r[5])
               for r in out]
    return out


def format_active_steps(table, rows, heading=""):
    """The text of a table of kind 'active_steps' (`active_steps_rows`)."""
    head = ("iter.", "paper weakly", "flexmbs weakly (static problem)",
            "flexmbs weakly (simulation)", "paper fully", "flexmbs fully")
    w = [5, 22, 34, 30, 12, 24]
    lines = [f"Table {table}: {heading}",
             "  ".join(h.ljust(k) for h, k in zip(head, w))]
    for r in rows:
        lines.append("  ".join(str(v).ljust(k) for v, k in zip(r, w)))
    return "\n".join(lines)


# ============================================================================ the run
@dataclass
class Report:
    """What `reproduce` computed and wrote.

    Attributes
    ----------
    out : Path
        The output folder (README.md, comparison.json, figures/, jobs/).
    tables : list of int
    rows : dict table -> list of Row
    checks : dict table -> list of Check (the variants' checks last)
    variants : dict table -> list of VariantRow (the table's ``[[tables.N.variants]]``)
    active_steps : dict table -> list of tuples (`active_steps_rows`), for the tables of kind
        'active_steps'
    maps : dict key -> MapResult
    figures : dict key -> (caption, path relative to `out`)
    failures : dict job name -> error text, for runs that produced no result
    elapsed : dict phase -> wall time (s) of this call: 'optimizations', one per map,
        'figures', 'total'
    timings : dict phase -> {elapsed_s, jobs_computed, executor, date}: the last call that
        computed jobs of that phase (kept in ``out/jobs/timings.json``)
    extra : dict of diagnostics, e.g. the tables' scans (`design_scan`, key `scan_key`)
    settings : dict (executor, grid, tables, stored_runs)
    study : Study
    """
    out: Path
    tables: list
    rows: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)
    variants: dict = field(default_factory=dict)
    active_steps: dict = field(default_factory=dict)
    maps: dict = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    failures: dict = field(default_factory=dict)
    elapsed: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    results: dict = field(default_factory=dict, repr=False)
    study: Study | None = field(default=None, repr=False)

    def __post_init__(self):
        self.study = load_study(self.study)

    def table_time(self, table):
        """Serial wall time of a table: the sum of its runs' wall times (s)."""
        runs = {r.name for r in self.study.tables[table].runs()}
        return sum(float(self.results[n]["wall_time_s"]) for n in runs if n in self.results)

    def text(self, table):
        """The terminal comparison of one table."""
        spec = self.study.tables[table]
        if spec.kind == "active_steps":
            return format_active_steps(table, self.active_steps.get(table) or [], spec.heading)
        rows = self.rows.get(table, [])
        missing = [r.name for r in spec.runs() if r.name not in self.results]
        unit = spec.units[0] if len(set(spec.units)) == 1 else ""
        txt = (format_table(table, rows, None, spec.title, spec.variables, unit) if rows
               else f"Table {table}:")
        for name in missing:
            txt += f"\n  [NO RESULT] {name}: {self.failures.get(name, 'not run')}"
        vrows = self.variants.get(table) or []
        if vrows:
            txt += "\n" + "\n".join(format_variants(vrows, unit))
        for v in spec.variants:
            if v.name not in {r.variant.name for r in vrows}:
                txt += f"\n  [NO RESULT] variant {v.label}: {self.failures.get(v.name, 'not run')}"
        for c in self.checks.get(table) or []:
            txt += f"\n  [{c.verdict}] {c.what}: paper {c.paper}, flexmbs {c.flexmbs}"
        return txt

    @property
    def row_tables(self):
        """The report's tables that have rows (kind 'rows')."""
        return [t for t in self.tables if self.study.tables[t].kind == "rows"]

    @property
    def all_checks(self):
        return [c for t in self.tables for c in self.checks.get(t, [])]


def _record_timing(report, phase, computed, elapsed):
    """Keep, per phase, the wall time of the last invocation that computed jobs in it (a
    rerun over stored results takes no time and must not hide the original cost)."""
    if computed > 0:
        report.timings[phase] = dict(elapsed_s=elapsed, jobs_computed=computed,
                                     executor=report.settings.get("executor"),
                                     date=time.strftime("%Y-%m-%d %H:%M"))


def _resolve_dask(dask, workers):
    """(address, cluster): a LocalCluster is started once for 'local'."""
    if dask is None:
        return None, None
    if dask == "local":
        from distributed import LocalCluster
        cluster = LocalCluster(n_workers=workers or os.cpu_count(), threads_per_worker=1,
                               processes=True, dashboard_address=None)
        return cluster.scheduler_address, cluster
    return dask, None


def _run_variants(variants, vstore, report, workers, address, progress, say):
    """The variants' jobs, stored under ``jobs/variants/``: the single runs in one batch, then
    each multi-start in turn (its starts a batch of their own, each start stored in
    ``jobs/variants/NAME/``). Returns {name: result}; failures go to report.failures."""
    fps = {v.name: job_fingerprint(optimization_job if v.multistart is None else multistart_job,
                                   v.job()) for v in variants}
    report.settings["stored_variants"] = [v.name for v in variants
                                          if _stored(vstore / f"{v.name}.json", fps[v.name],
                                                     _schema(v))]
    single = {v.name: v.job() for v in variants if v.multistart is None}
    out = {}
    if single:
        say(f"{len(single)} variant optimization(s); results in {vstore}")
        try:
            out.update(run_batch(optimization_job, single, workers=workers, dask=address,
                                 store=vstore, progress=progress, label="variants",
                                 fingerprints={n: fps[n] for n in single}))
        except Exception as exc:    # noqa: BLE001 - report what finished, name what did not
            for n in single:
                v = _stored(vstore / f"{n}.json", fps[n], OptimizationJobResult)
                if v is not None:
                    out[n] = v
                else:
                    report.failures[n] = f"{type(exc).__name__}: {exc} (first error of the batch)"
            say(f"some variant optimizations failed: {type(exc).__name__}: {exc}")
    for v in variants:
        if v.multistart is None:
            continue
        f = vstore / f"{v.name}.json"
        stored = _stored(f, fps[v.name], MultistartJobResult, warn=True)
        if stored is not None:
            out[v.name] = stored
            continue
        say(f"variant {v.name}: multi-start of {v.multistart['starts']} starts; each start "
            f"stored in {vstore / v.name}")
        try:
            res = multistart_job(**v.job(), workers=workers, dask=address, store=vstore / v.name,
                                 progress=progress)
        except Exception as exc:    # noqa: BLE001 - the report names the failed variant
            report.failures[v.name] = f"{type(exc).__name__}: {exc}"
            say(f"variant {v.name} failed: {type(exc).__name__}: {exc}")
            continue
        res = dict(res, fingerprint=fps[v.name])
        vstore.mkdir(parents=True, exist_ok=True)
        write_atomic(f, json.dumps(jsonable(res)))
        out[v.name] = res
    return out


def _stored(path, fp, schema=None, warn=False):
    """The stored result at `path` when it answers `fp` (flexmbs.model.fingerprint) and has the
    content of `schema` (flexmbs.batch.invalid_result), else None (with warn=True, a warning
    naming the file and what differs or is wrong)."""
    value = read_stored(path)
    if value is None:
        return None
    why = invalid_result(value, schema)
    diff = None if why else stale_result(value, fp)
    if why or diff:
        if warn:
            what = (f"is JSON but not a result ({why})" if why else
                    f"answers another question ({'; '.join(diff)})")
            warnings.warn(f"stored result {path} {what}: computed again", stacklevel=3)
        return None
    return value


def reproduce(tables=None, out="reproduction", *, workers=None, dask=None, grid=41, maps=True,
              force=False, progress=None, log=None, study=None):
    """Run the optimizations behind a study's tables and compare them with its published
    numbers.

    The figures and the report (README.md, comparison.json) are drawn and written from the
    returned Report by `flexmbs.paper.report.publish` (as `flexmbs reproduce` does).

    Parameters
    ----------
    tables : list of int, optional
        Numbers of the study's tables (default: all).
    out : path, default 'reproduction'
        Output folder: ``README.md`` (the report), ``comparison.json``, ``figures/*.png`` and
        ``jobs/`` (one JSON file per finished job; what is there is not run again).
    workers : int, optional
        Local worker processes (default: the number of cores; 1: serial in this process);
        with ``dask='local'``, the number of Dask workers.
    dask : str, optional
        A Dask scheduler address (``tcp://host:8786``), or 'local' for a LocalCluster.
    grid : int, default 41
        Points per axis of the design-domain maps.
    maps : bool, default True
        Compute the maps of the tables asked for.
    force : bool, default False
        Run the tables' optimizations again even when a stored result exists.
    progress : bool, optional
        Progress bars on stderr (default: when stderr is a terminal).
    log : callable, optional
        Called with a line of text at every phase (the command line prints them).
    study : str, path or Study, optional
        The study (default: the shipped study of the paper, `flexmbs.paper.study.load_study`).

    Returns
    -------
    Report
    """

    t_start = time.perf_counter()
    study = load_study(study)
    all_tables = study.tables
    tables = sorted(set(all_tables if tables is None else tables))
    bad = [t for t in tables if t not in all_tables]
    if bad:
        raise ModelError(f"tables must be among {sorted(all_tables)}, got {bad}")
    if not (isinstance(grid, int) and grid >= 2):
        raise ModelError(f"grid must be an integer >= 2, got {grid!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):
        raise ModelError(f"workers must be an integer >= 1, got {workers!r}")
    check_dask(dask)        # once, before any job (not once per failing job)
    say = log or (lambda s: None)
    out = Path(out)
    runs = table_runs(tables, study)
    # before any run: the folder can be written and has room for the results (a rough upper
    # bound: 0.5 MB per optimization, 2 KB per map point, 1 MB per figure)
    check_writable(out, f"output folder {str(out)!r}", create=True)
    n_map = sum(2 * grid * grid for spec in study.maps.values() if maps and spec.table in tables)
    check_disk_space(out, 500e3 * len(runs) + 2e3 * n_map + 20e6,
                     f"output folder {str(out)!r}")
    store = out / "jobs" / "optimizations"
    vstore = out / "jobs" / "variants"
    variants = [v for t in tables for v in all_tables[t].variants]
    if force:
        import shutil
        for r in runs:
            (store / f"{r.name}.json").unlink(missing_ok=True)
        for v in variants:
            (vstore / f"{v.name}.json").unlink(missing_ok=True)
            if (vstore / v.name).is_dir():
                shutil.rmtree(vstore / v.name)
    data = study.published_data()
    report = Report(out=out, tables=tables, study=study)
    tfile = out / "jobs" / "timings.json"
    report.timings = read_stored(tfile)
    if not isinstance(report.timings, dict):       # missing, or not what reproduce writes
        report.timings = {}
    address, cluster = _resolve_dask(dask, workers)
    executor = (f"Dask scheduler {address}" + (" (LocalCluster)" if cluster else "")
                if address else ("serial" if workers == 1 else
                                 f"{workers or os.cpu_count()} local worker processes"))
    report.settings = dict(executor=executor, grid=grid, tables=tables)
    try:
        say(f"{len(runs)} optimizations for table(s) {', '.join(map(str, tables))} "
            f"({executor}); results in {store}")
        t0 = time.perf_counter()
        jobs = {r.name: r.job() for r in runs}
        fps = {n: job_fingerprint(optimization_job, kw) for n, kw in jobs.items()}
        report.settings["stored_runs"] = [n for n in jobs
                                          if _stored(store / f"{n}.json", fps[n],
                                                     OptimizationJobResult) is not None]
        try:
            results = run_batch(optimization_job, jobs, workers=workers, dask=address,
                                store=store, progress=progress, label="optimizations",
                                fingerprints=fps)
        except Exception as exc:    # noqa: BLE001 - report what finished, name what did not
            results = {n: v for n in jobs
                       if (v := _stored(store / f"{n}.json", fps[n],
                                        OptimizationJobResult)) is not None}
            for n in jobs:
                if n not in results:
                    report.failures[n] = f"{type(exc).__name__}: {exc} (first error of the batch)"
            say(f"some optimizations failed: {type(exc).__name__}: {exc}")
        report.results = results
        report.elapsed["optimizations"] = time.perf_counter() - t0
        _record_timing(report, "optimizations",
                       len(results) - len(report.settings["stored_runs"]),
                       report.elapsed["optimizations"])
        if variants:
            t0 = time.perf_counter()
            vresults = _run_variants(variants, vstore, report, workers, address, progress, say)
            report.elapsed["variants"] = time.perf_counter() - t0
            _record_timing(report, "variants",
                           len(vresults) - len(report.settings["stored_variants"]),
                           report.elapsed["variants"])
            for v in variants:
                if v.name in vresults:
                    report.variants.setdefault(v.table, []).append(
                        VariantRow(v, variant_paper(v, data, study), vresults[v.name]))
        for t in tables:
            spec = all_tables[t]
            if spec.kind != "rows":
                continue
            rows = [Row(t, r, paper_row(t, r.method, r.start_mm, data, study), results[r.name])
                    for r in spec.runs() if r.name in results]
            simulate_paper_designs(rows)
            report.rows[t] = rows
            report.checks[t] = table_checks(spec, rows) + variant_checks(
                report.variants.get(t, []))
        for t in tables:
            spec = all_tables[t]
            if spec.scan is not None:
                report.extra[scan_key(spec)] = design_scan(spec)
        for t in tables:
            spec = all_tables[t]
            if spec.kind == "active_steps":
                w, f = (spec.run(m).name for m in ("weakly", "fully"))
                report.active_steps[t] = active_steps_rows(results.get(w), results.get(f),
                                                           _published(spec, data))
        if maps:
            for key, spec in study.maps.items():
                if spec.table not in tables:
                    continue
                t0 = time.perf_counter()
                mj = {}
                for region in REGIONS:
                    mj.update(map_jobs(spec, grid, region))
                mstore = out / "jobs" / key
                mfps = {n: job_fingerprint(max_deviation_job, kw) for n, kw in mj.items()}
                map_stored = sum(_stored(mstore / f"{n}.json", mfps[n], MaxDeviationResult)
                                 is not None for n in mj)
                say(f"Fig. {spec.figure}: {len(mj)} simulations (two {grid} x {grid} grids of "
                    f"{', '.join(spec.axes)}: the bounds' box and a zoom), results in "
                    f"{out / 'jobs' / key}")
                res = run_batch(max_deviation_job, mj, workers=workers, dask=address,
                                store=mstore, progress=progress, label=f"Fig. {spec.figure}",
                                fingerprints=mfps)
                grids = {}
                for region in REGIONS:
                    grids[region], names, idx, h, units = _collect_map(spec, grid, res, region)
                m = MapResult(spec, grids, names, len(mj), time.perf_counter() - t0, idx, h,
                              units)
                report.maps[key] = m
                report.elapsed[key] = m.wall_time_s
                _record_timing(report, key, len(mj) - map_stored, m.wall_time_s)
    finally:
        if cluster is not None:
            cluster.close()
    report.elapsed["total"] = time.perf_counter() - t_start
    (out / "jobs").mkdir(parents=True, exist_ok=True)
    write_atomic(out / "jobs" / "timings.json", json.dumps(report.timings, indent=1))
    return report
