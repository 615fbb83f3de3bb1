"""Reproduce the paper: the optimizations behind its Tables 1-8 and Figures 5-15.

`reproduce(tables, out)` runs every optimization a table needs (each starting point x method
is one job of `flexmbs.batch.run_batch`: local worker processes by default, a Dask cluster when
an address is given), compares the results with the published numbers (the paper's tables,
shipped with flexmbs as ``paper_tables.json``) and returns a `Report`;
`flexmbs.report.publish(report)` draws the figures and writes ``out/README.md``, a report a
reader can check without running anything. Every job's result is saved under ``out/jobs/``
as soon as it finishes; running the same command again skips what is done.

The command line is ``flexmbs reproduce`` (flexmbs/cli_reproduce.py).

Tables and what they need
-------------------------
====  ==================================================================  ====================
 1    robot, deviation (28), 0.65 s, start 50 mm: both methods             Fig. 5
 2    robot, deviation (30), 0.65 s: both methods                          Fig. 6
 3    four-bar with 5 kg at A and B: both methods                          Fig. 8
 4    four-bar without the lumped masses: both methods                     Fig. 9
 5    robot, (28), 0.66 s: weakly oscillates, fully converges              Figs. 10, 11
 6    robot, (28), 0.65 s, four starts x two methods                       Fig. 12 (map)
 7    robot, (28), 0.6685 s (1338 steps), four starts x two methods        Figs. 13, 14, 15
 8    active time steps per cycle / iteration, Table 7 from [55]*4         (Table 7's runs)
====  ==================================================================  ====================

Example
-------
>>> from flexmbs.reproduce import reproduce
>>> from flexmbs.report import publish
>>> report = publish(reproduce([1], "reproduction", workers=2))   # doctest: +SKIP
>>> row = report.rows[1][0]                                       # doctest: +SKIP
>>> row.method, row.mass_kg, row.paper["mass"], row.mass_difference   # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["reproduce", "Report", "Row", "TableSpec", "Run", "TABLES", "paper_tables",
           "table_runs", "optimization_job", "map_jobs",
           "MAPS", "MapSpec", "MapResult", "REGIONS", "Check", "table_checks",
           "STARTS", "WEAKLY_OPTIONS", "FULLY_OPTIONS", "CRITERIA", "paper_row", "build_rows",
           "design_spread", "table8_rows", "format_table", "format_table8",
           "simulate_paper_designs", "paper_design_text", "first_variable_scan"]

#: Starting points of Tables 6 and 7 (mm).
STARTS = ((50.0, 50.0, 50.0, 50.0), (55.0, 55.0, 55.0, 55.0), (55.0, 45.0, 35.0, 25.0),
          (45.0, 45.0, 45.0, 45.0))

#: Options of the optimizers for every table, beyond the case files' stopping tests: the
#: methods' defaults (30 cycles at most for the weakly coupled method), and at most 40
#: iterations (about twice the paper's 21) for the four-bar's fully coupled runs. On the
#: four-bar the weakly coupled cycles never meet test (25) (the paper needed 73 cycles): they
#: wander around one design, and 100 cycles instead of 30 change its mass by under 1 %.
WEAKLY_OPTIONS = {"robot_2dof": dict(max_cycles=30), "robot_2dof_tracking": dict(max_cycles=30),
                  "fourbar": dict(max_cycles=30), "fourbar_no_masses": dict(max_cycles=30)}
FULLY_OPTIONS = {"robot_2dof": dict(), "robot_2dof_tracking": dict(),
                 "fourbar": dict(max_iterations=40, design_rel_change=1e-3),
                 "fourbar_no_masses": dict(max_iterations=40, design_rel_change=1e-3)}


# ============================================================================ published numbers
def paper_tables():
    """The published numbers of the paper's Tables 1-8 (dict, as in ``paper_tables.json``).

    Read from the repository's ``tests/data/paper_tables.json`` when flexmbs runs from a source
    tree, else from the copy installed with the package (``flexmbs/paper_data``).
    """
    root = Path(__file__).resolve().parents[2]
    f = root / "tests" / "data" / "paper_tables.json"
    if f.is_file() and (root / "python" / "flexmbs").is_dir():
        return json.loads(f.read_text(encoding="utf-8"))
    try:
        g = resources.files("flexmbs") / "paper_data" / "paper_tables.json"
        return json.loads(g.read_text(encoding="utf-8"))
    except (FileNotFoundError, ModuleNotFoundError, NotADirectoryError) as exc:
        raise ModelError("paper_tables.json not found (neither tests/data/ of a source tree "
                         "nor flexmbs/paper_data/ of the installed package)") from exc


# ============================================================================ runs and tables
@dataclass(frozen=True)
class Run:
    """One optimization: a case (name + overrides), a method and a starting design.

    Runs that are equal share one job (Table 1's runs are Table 6's first row).
    """
    case: str
    method: str
    start_mm: tuple
    overrides: tuple = ()       # sorted (key, value) pairs

    @property
    def name(self):
        """The job name: case, end time, method and start, e.g.
        ``robot_2dof-t0.65-weakly-50-50-50-50``."""
        ov = dict(self.overrides)
        t_end = ov.pop("time.t_end", None)
        parts = [self.case]
        if t_end is not None:
            parts.append(f"t{t_end:g}")
        parts += [f"{k}{v}" for k, v in sorted(ov.items())]
        parts.append(self.method)
        parts.append("-".join(f"{v:g}" for v in self.start_mm))
        return "-".join(parts)

    def job(self):
        """Keyword arguments of `optimization_job`."""
        opts = (WEAKLY_OPTIONS if self.method == "weakly" else FULLY_OPTIONS)[self.case]
        return dict(case=self.case, method=self.method, start=list(self.start_mm),
                    overrides=dict(self.overrides), options=dict(opts))


@dataclass(frozen=True)
class TableSpec:
    """A table of the paper: its case, its rows (runs) and where its numbers are published."""
    number: int
    title: str
    case: str
    overrides: tuple
    section: str                # key of paper_tables.json: "robot_2dof" or "four_bar"
    key: str                    # the table's key in that section
    starts: tuple               # starting designs (one row per start and method)
    methods: tuple = ("weakly", "fully")
    figures: tuple = ()

    def runs(self):
        return [Run(self.case, m, tuple(float(v) for v in s), self.overrides)
                for m in self.methods for s in self.starts]


_R50 = (STARTS[0],)
_F250 = ((250.0, 250.0, 250.0),)
TABLES = {
    1: TableSpec(1, "2-dof robot, deviation (28), 0.65 s (1301 steps)", "robot_2dof",
                 (("time.t_end", 0.65),), "robot_2dof", "table1_formulation28_tend0.65", _R50,
                 figures=("fig05",)),
    2: TableSpec(2, "2-dof robot, tracking deviation (30), 0.65 s (1301 steps)",
                 "robot_2dof_tracking", (("time.t_end", 0.65),), "robot_2dof",
                 "table2_formulation30_tend0.65", _R50, figures=("fig06",)),
    3: TableSpec(3, "four-bar mechanism with 5 kg at A and B, deviation (33) of A, 0.5 s",
                 "fourbar", (), "four_bar", "table3_with_lumped_masses", _F250,
                 figures=("fig08",)),
    4: TableSpec(4, "four-bar mechanism without lumped masses, deviation (33) of A, 0.5 s",
                 "fourbar_no_masses", (), "four_bar", "table4_without_lumped_masses", _F250,
                 figures=("fig09",)),
    5: TableSpec(5, "2-dof robot, deviation (28), 0.66 s (1321 steps)", "robot_2dof",
                 (("time.t_end", 0.66),), "robot_2dof", "table5_formulation28_tend0.66", _R50,
                 figures=("fig10", "fig11")),
    6: TableSpec(6, "2-dof robot, deviation (28), 0.65 s: four starting points", "robot_2dof",
                 (("time.t_end", 0.65),), "robot_2dof", "table6_formulation28_tend0.65_initial_points",
                 STARTS, figures=("fig12",)),
    7: TableSpec(7, "2-dof robot, deviation (28), 0.6685 s (1338 steps): four starting points",
                 "robot_2dof", (("time.t_end", 0.6685),), "robot_2dof",
                 "table7_formulation28_tend0.6687_initial_points", STARTS,
                 figures=("fig13", "fig14", "fig15")),
    8: TableSpec(8, "active time steps per cycle / iteration, Table 7's problem from "
                    "[55, 55, 55, 55]", "robot_2dof", (("time.t_end", 0.6685),), "robot_2dof",
                 "table8_active_constraints_start55", (STARTS[1],)),
}


def table_runs(numbers):
    """The distinct runs the given tables need, longest first (four-bar, then fully coupled)."""
    seen = {}
    for n in numbers:
        for r in TABLES[n].runs():
            seen.setdefault(r.name, r)
    def cost(r):                # the longest runs first: the four-bar's, then fully coupled
        return (0 if "max_iterations" in FULLY_OPTIONS[r.case] else 1,
                0 if r.method == "fully" else 1)
    return sorted(seen.values(), key=cost)


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
        Keyword arguments of `optimize_weakly` / `optimize_fully`.
    """
    from flexmbs.optimize import optimize_fully, optimize_weakly
    from flexmbs.problem import Problem

    prob = Problem(case, overrides=overrides or None)
    if method not in ("weakly", "fully"):
        raise ModelError(f"method must be 'weakly' or 'fully', got {method!r}")
    run = optimize_weakly if method == "weakly" else optimize_fully
    r = run(prob, np.asarray(start, float), **(options or {}))
    d = r.to_dict()
    d["deviation_m"] = None if r.deviation is None else [float(v) for v in r.deviation]
    d["h_s"] = float(prob.description.time.h)
    d["case_overrides"] = dict(overrides or {})
    d["case_name"] = case
    return d


# ============================================================================ design-domain maps
@dataclass(frozen=True)
class MapSpec:
    """A design-domain map of the deviation at one time step over a grid of (p2, p4).

    Paper Fig. 12: step 200 (0.0995 s) of the 0.65 s problem, p1 = 39.35, p3 = 35 mm.
    Paper Fig. 15: step 1338 (0.6685 s) of the 0.6685 s problem, p1 = 52.49, p3 = 33.24 mm.
    Two grids: the whole box of the bounds, and a zoom around the optima of the map's table,
    where the paper describes the landscape (smooth in Fig. 12, oscillating near the limit in
    Fig. 15).
    """
    key: str
    figure: int
    table: int
    case: str
    overrides: tuple
    step: int                   # 1-based, as the paper counts (t = (step - 1) h)
    fixed: tuple                # ((index, value mm), ...) of the variables held fixed
    zoom: tuple                 # ((lo, hi), (lo, hi)) mm of the mapped variables
    axes: tuple = (1, 3)        # 0-based indices of the mapped variables (p2, p4)

    def grid(self, n, lower, upper, region="full"):
        """The n values of each mapped variable (mm): between the bounds ('full') or in the
        zoom box ('zoom')."""
        i, j = self.axes
        if region == "zoom":
            (a0, a1), (b0, b1) = self.zoom
        elif region == "full":
            a0, a1, b0, b1 = lower[i], upper[i], lower[j], upper[j]
        else:
            raise ModelError(f"region must be 'full' or 'zoom', got {region!r}")
        return np.linspace(a0, a1, n), np.linspace(b0, b1, n)


MAPS = {
    "fig12": MapSpec("fig12", 12, 6, "robot_2dof", (("time.t_end", 0.65),), 200,
                     ((0, 39.35), (2, 35.0)), ((24.0, 32.0), (21.0, 29.0))),
    "fig15": MapSpec("fig15", 15, 7, "robot_2dof", (("time.t_end", 0.6685),), 1338,
                     ((0, 52.49), (2, 33.24)), ((33.0, 41.0), (21.5, 29.5))),
}

#: Regions of a map.
REGIONS = ("full", "zoom")


def map_jobs(spec, n, region="full"):
    """Jobs of `flexmbs.batch.max_deviation_job` for a map: one simulation per grid point.

    Names carry the design (``p2-30.000-p4-25.000``), so grids of different resolutions or
    regions share the points they have in common in a store.
    """
    from flexmbs.problem import Problem
    c = Problem(spec.case, overrides=dict(spec.overrides))
    a, b = spec.grid(n, c.lower, c.upper, region)
    i, j = spec.axes
    names = c.variables
    jobs = {}
    for va in a:
        for vb in b:
            p = np.array(c.start, float)
            for k, v in spec.fixed:
                p[k] = v
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
        a, b: values (mm) of the first (rows) and second (columns) mapped variable; at_step:
        (na, nb) deviation (m) at spec.step; maximum: (na, nb) maximum deviation over all steps.
    names : tuple of the mapped variables' names
    simulations : int
    wall_time_s : float
    """
    spec: MapSpec
    grids: dict
    names: tuple
    simulations: int = 0
    wall_time_s: float = 0.0


def _collect_map(spec, n, results, region):
    from flexmbs.problem import Problem
    c = Problem(spec.case, overrides=dict(spec.overrides))
    a, b = spec.grid(n, c.lower, c.upper, region)
    names = list(map_jobs(spec, n, region))
    at = np.array([results[k]["deviation_at_steps_m"][0] for k in names]).reshape(n, n)
    mx = np.array([results[k]["max_deviation_m"] for k in names]).reshape(n, n)
    i, j = spec.axes
    return (a, b, at, mx), (c.variables[i], c.variables[j])


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


def simulate_paper_designs(rows):
    """Simulate every published design of the rows with flexmbs (one simulation each) and set
    `Row.paper_design`: does the paper's optimum sit on its 1 mm constraint in flexmbs's model?
    """
    from flexmbs.batch import max_deviation_job
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


#: Crank diameters (mm) of the Table 3 diagnostic scan (`first_variable_scan`).
SCAN_P1_MM = (50.0, 54.0, 56.15, 58.0, 60.0, 62.0, 65.0, 68.0, 72.0, 76.0)


def first_variable_scan(case="fourbar", p1=SCAN_P1_MM, tails=((15.0, 15.0), (15.10, 16.24))):
    """Maximum constrained deviation over the first design variable, the others held at each
    of `tails` (Table 3: the four-bar's crank diameter with a slender coupler and follower, on
    the 15 mm bound and at the paper's fully coupled values).

    Shows how strongly (and not monotonically) the peak deviation depends on the design near
    the paper's fully coupled optimum. Returns a list of dicts
    {p1_mm, p2_mm, p3_mm, mass_kg, max_deviation_m, t_at_max_s}.
    """
    from flexmbs.batch import max_deviation_job
    out = []
    for rest in tails:
        for v in p1:
            r = max_deviation_job(case, [v, *rest])
            out.append(dict(p1_mm=v, p2_mm=rest[0], p3_mm=rest[1], mass_kg=r["mass_kg"],
                            max_deviation_m=r["max_deviation_m"], t_at_max_s=r["t_at_max_s"]))
    return out


def paper_row(table, method, start_mm, data=None):
    """The published numbers of one row of a table (dict)."""
    spec = TABLES[table]
    data = paper_tables() if data is None else data
    tab = data[spec.section][spec.key]
    if table == 8:
        tab = data[spec.section][TABLES[7].key]
        table = 7
    entry = tab[method]
    if isinstance(entry, list):
        starts = [list(map(float, s)) for s in tab["starts"]]
        entry = entry[starts.index(list(map(float, start_mm)))]
    return dict(entry)


def build_rows(table, results, data=None):
    """The rows of a table from the job results {job name: result}."""
    data = paper_tables() if data is None else data
    return [Row(table, r, paper_row(table, r.method, r.start_mm, data), results[r.name])
            for r in TABLES[table].runs()]


def design_spread(designs):
    """Largest relative spread of the design variables over several designs:
    max_i (max - min) / mean of p_i."""
    d = np.asarray(designs, float)
    return float(np.max((d.max(axis=0) - d.min(axis=0)) / d.mean(axis=0)))


#: What each table must show (the issue's criteria; tests/test_paper_tables.py asserts them).
CRITERIA = {
    1: dict(mass=0.01, design=0.03),
    2: dict(mass=0.01, design=0.03),
    5: dict(mass=0.01, design=0.05),
    6: dict(mass=0.01, design=0.03),
    7: dict(mass=0.01, design=0.03, fully_mass=0.03, weakly_spread=0.01),
}


@dataclass
class Check:
    """One finding of the paper checked on flexmbs's results.

    ok: True (reproduced), False (not reproduced) or None (a number reported beside the
    paper's without a criterion, e.g. the four-bar's local optima).
    """
    table: int
    what: str
    paper: str
    flexmbs: str
    ok: bool | None

    @property
    def verdict(self):
        return {True: "ok", False: "DIFFERS", None: "reported"}[self.ok]


def table_checks(table, rows):
    """The checks of one table (list of Check): the issue's criteria on its rows."""
    out = []
    crit = CRITERIA.get(table, {})

    def pct(v):
        return "-" if v is None else f"{100 * v:+.2f} %"

    by = {}
    for r in rows:
        by.setdefault(r.method, []).append(r)
    for r in rows:
        start = "[" + ", ".join(f"{v:g}" for v in r.start_mm) + "]"
        tag = f"{r.method}, start {start}"
        if table == 5 and r.method == "weakly":
            out.append(Check(table, f"{tag}: does not converge", "oscillates, stops at the "
                             "maximum number of iterations",
                             ("converged" if r.converged else "not converged") + f" ({r.reason})",
                             not r.converged))
            continue
        # a mass counts only when the run converged (the tests assert both)
        conv = "" if r.converged else ", NOT converged"
        if table == 7 and r.method == "fully":
            tol = crit["fully_mass"]
            out.append(Check(table, f"{tag}: converged, mass within {100 * tol:g} %",
                             f"{r.paper['mass']:.3f} kg", f"{r.mass_kg:.4f} kg "
                             f"({pct(r.mass_difference)}{conv})",
                             r.converged and abs(r.mass_difference) <= tol))
            continue
        if "mass" in crit and r.paper.get("mass") is not None:
            out.append(Check(table, f"{tag}: converged, mass within {100 * crit['mass']:g} %",
                             f"{r.paper['mass']:.3f} kg",
                             f"{r.mass_kg:.4f} kg ({pct(r.mass_difference)}{conv})",
                             r.converged and abs(r.mass_difference) <= crit["mass"]))
            md = r.max_design_difference
            out.append(Check(table, f"{tag}: every p_i within {100 * crit['design']:g} %",
                             "[" + ", ".join(f"{v:.2f}" for v in r.paper["p"]) + "] mm",
                             "[" + ", ".join(f"{v:.2f}" for v in r.design_mm) + "] mm "
                             f"(largest {100 * md:.2f} %)", md <= crit["design"]))
    if table == 5 and "fully" in by:
        r = by["fully"][0]
        out.append(Check(table, "fully coupled converges", "converged in 11 iterations",
                         ("converged" if r.converged else "NOT converged")
                         + f" in {r.iterations} iterations", r.converged))
    if table == 7 and len(by.get("weakly", [])) > 1 and len(by.get("fully", [])) > 1:
        sw = design_spread([r.design_mm for r in by["weakly"]])
        sf = design_spread([r.design_mm for r in by["fully"]])
        pw = design_spread([r.paper["p"] for r in by["weakly"]])
        pf = design_spread([r.paper["p"] for r in by["fully"]])
        out.append(Check(table, "weakly coupled designs of the four starts agree within 1 %",
                         f"spread {100 * pw:.2f} %", f"spread {100 * sw:.2f} %",
                         sw <= crit["weakly_spread"]))
        out.append(Check(table, "fully coupled designs of the four starts differ by more",
                         f"spread {100 * pf:.2f} %", f"spread {100 * sf:.2f} %", sf > sw))
    if table in (3, 4):
        for r in rows:
            if r.paper.get("mass") is None:
                continue
            out.append(Check(
                table, f"{r.method} coupled optimum (a local optimum, paper 7.2)",
                f"{r.paper['mass']:.3f} kg, [" + ", ".join(f"{v:.2f}" for v in r.paper["p"])
                + "] mm", f"{r.mass_kg:.3f} kg ({pct(r.mass_difference)}), ["
                + ", ".join(f"{v:.2f}" for v in r.design_mm) + "] mm", None))
    if table == 3 and "fully" in by and "weakly" in by:
        ratio = by["weakly"][0].mass_kg / by["fully"][0].mass_kg
        out.append(Check(table, "fully coupled at least 4 x lighter than weakly coupled",
                         f"{by['weakly'][0].paper['mass'] / by['fully'][0].paper['mass']:.1f} x",
                         f"{ratio:.1f} x", ratio >= 4.0))
    if table == 4 and "fully" in by and "weakly" in by:
        f, w = by["fully"][0], by["weakly"][0]
        lo = 15.0
        out.append(Check(table, "fully coupled: p2 and p3 at the 15 mm bound",
                         "p2 = p3 = 15 mm",
                         f"p2 = {f.design_mm[1]:.2f}, p3 = {f.design_mm[2]:.2f} mm",
                         bool(np.all(f.design_mm[1:] <= lo * 1.01))))
        out.append(Check(table, "weakly coupled: links 2 and 3 stay above the bound",
                         "links 2 and 3 not removed",
                         f"p2 = {w.design_mm[1]:.2f}, p3 = {w.design_mm[2]:.2f} mm",
                         bool(np.all(w.design_mm[1:] > lo * 1.1))))
    return out


# ============================================================================ text output
def _pct_text(v):
    """A relative difference in per cent with its sign ('+0.00' for a zero), '-' for None."""
    return "-" if v is None else f"{100 * v:+.2f}".replace("-0.00", "+0.00")


def _fmt(v, spec):
    return "-" if v is None else format(v, spec)


def format_table(table, rows, checks=None):
    """The comparison of one table as text: for every row the paper, flexmbs and the
    difference in %, then the run's status, then the checks."""
    spec = TABLES[table]
    nv = len(rows[0].design_mm)
    names = [f"p{k + 1}" for k in range(nv)]
    lines = [f"Table {table}: {spec.title}",
             f"{'':30s}{'mass kg':>9s}{'iter':>6s}{'inner':>7s}"
             + "".join(f"{n:>9s}" for n in names) + "   (mm)"]
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


def table8_rows(weakly, fully, data=None):
    """Table 8 beside flexmbs: list of (iteration, paper weakly, flexmbs weakly static problem,
    flexmbs weakly simulation, paper fully, flexmbs fully), step lists as text.

    weakly / fully: the results (dicts) of Table 7's runs from [55, 55, 55, 55]. For the weakly
    coupled method flexmbs lists, per cycle, the steps active at the solution of the static
    problem that produced the cycle's design and the steps where the cycle's full simulation
    is within 0.1 % of the limit; for the fully coupled method the steps of the iterate within
    0.1 % of the limit (iteration 0 is the start).
    """
    data = paper_tables() if data is None else data
    t8 = data["robot_2dof"][TABLES[8].key]
    pw = t8["weakly_by_cycle"]
    pf = {}
    for k, v in t8["fully_by_iteration"].items():
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


def format_table8(rows8):
    head = ("iter.", "paper weakly", "flexmbs weakly (static problem)",
            "flexmbs weakly (simulation)", "paper fully", "flexmbs fully")
    w = [5, 22, 34, 30, 12, 24]
    lines = ["Table 8: active time steps per cycle (weakly) / iteration (fully), Table 7's "
             "problem from [55, 55, 55, 55]",
             "  ".join(h.ljust(k) for h, k in zip(head, w))]
    for r in rows8:
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
    checks : dict table -> list of Check
    table8 : list of tuples or None (see `table8_rows`)
    maps : dict key -> MapResult ('fig12', 'fig15')
    figures : dict key -> (caption, path relative to `out`)
    failures : dict job name -> error text, for runs that produced no result
    elapsed : dict phase -> wall time (s) of this call: 'optimizations', 'fig12', 'fig15',
        'figures', 'total'
    timings : dict phase -> {elapsed_s, jobs_computed, executor, date}: the last call that
        computed jobs of that phase (kept in ``out/jobs/timings.json``)
    extra : dict of diagnostics, e.g. 'table3_p1_scan' (`first_variable_scan`)
    settings : dict (executor, grid, tables, stored_runs)
    """
    out: Path
    tables: list
    rows: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)
    table8: list | None = None
    maps: dict = field(default_factory=dict)
    figures: dict = field(default_factory=dict)
    failures: dict = field(default_factory=dict)
    elapsed: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    results: dict = field(default_factory=dict, repr=False)

    def table_time(self, table):
        """Serial wall time of a table: the sum of its runs' wall times (s)."""
        runs = {r.name for r in TABLES[table].runs()}
        return sum(float(self.results[n]["wall_time_s"]) for n in runs if n in self.results)

    def text(self, table):
        """The terminal comparison of one table."""
        if table == 8:
            return format_table8(self.table8 or [])
        rows = self.rows.get(table, [])
        missing = [r.name for r in TABLES[table].runs() if r.name not in self.results]
        txt = format_table(table, rows, self.checks.get(table)) if rows else f"Table {table}:"
        for name in missing:
            txt += f"\n  [NO RESULT] {name}: {self.failures.get(name, 'not run')}"
        return txt

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


def reproduce(tables=None, out="reproduction", *, workers=None, dask=None, grid=41, maps=True,
              force=False, progress=None, log=None):
    """Run the optimizations behind the paper's tables and compare them with the paper.

    The figures and the report (README.md, comparison.json) are drawn and written from the
    returned Report by `flexmbs.report.publish` (as `flexmbs reproduce` does).

    Parameters
    ----------
    tables : list of int, optional
        Tables 1-8 (default: all).
    out : path, default 'reproduction'
        Output folder: ``README.md`` (the report), ``comparison.json``, ``figures/*.png`` and
        ``jobs/`` (one JSON file per finished job; what is there is not run again).
    workers : int, optional
        Local worker processes (default: the number of cores; 1: serial in this process);
        with ``dask='local'``, the number of Dask workers.
    dask : str, optional
        A Dask scheduler address (``tcp://host:8786``), or 'local' for a LocalCluster.
    grid : int, default 41
        Points per axis of the design-domain maps of Figs. 12 and 15 (41: 1 mm steps).
    maps : bool, default True
        Compute the maps when Table 6 (Fig. 12) or Table 7 (Fig. 15) is asked for.
    force : bool, default False
        Run the tables' optimizations again even when a stored result exists.
    progress : bool, optional
        Progress bars on stderr (default: when stderr is a terminal).
    log : callable, optional
        Called with a line of text at every phase (the command line prints them).

    Returns
    -------
    Report
    """
    from flexmbs.batch import max_deviation_job, run_batch

    t_start = time.perf_counter()
    tables = sorted(set(TABLES if tables is None else tables))
    bad = [t for t in tables if t not in TABLES]
    if bad:
        raise ModelError(f"tables must be among {sorted(TABLES)}, got {bad}")
    if not (isinstance(grid, int) and grid >= 2):
        raise ModelError(f"grid must be an integer >= 2, got {grid!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):
        raise ModelError(f"workers must be an integer >= 1, got {workers!r}")
    from flexmbs.batch import check_disk_space, check_writable, read_stored, write_atomic
    say = log or (lambda s: None)
    out = Path(out)
    runs = table_runs(tables)
    # before any run: the folder can be written and has room for the results (a rough upper
    # bound: 0.5 MB per optimization, 2 KB per map point, 1 MB per figure)
    check_writable(out, f"output folder {str(out)!r}", create=True)
    n_map = sum(2 * grid * grid for spec in MAPS.values() if maps and spec.table in tables)
    check_disk_space(out, 500e3 * len(runs) + 2e3 * n_map + 20e6,
                     f"output folder {str(out)!r}")
    store = out / "jobs" / "optimizations"
    if force:
        for r in runs:
            (store / f"{r.name}.json").unlink(missing_ok=True)
    data = paper_tables()
    report = Report(out=out, tables=tables)
    tfile = out / "jobs" / "timings.json"
    report.timings = read_stored(tfile) or {}
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
        report.settings["stored_runs"] = [n for n in jobs
                                          if read_stored(store / f"{n}.json") is not None]
        try:
            results = run_batch(optimization_job, jobs, workers=workers, dask=address,
                                store=store, progress=progress, label="optimizations")
        except Exception as exc:    # noqa: BLE001 - report what finished, name what did not
            results = {n: v for n in jobs
                       if (v := read_stored(store / f"{n}.json")) is not None}
            for n in jobs:
                if n not in results:
                    report.failures[n] = f"{type(exc).__name__}: {exc} (first error of the batch)"
            say(f"some optimizations failed: {type(exc).__name__}: {exc}")
        report.results = results
        report.elapsed["optimizations"] = time.perf_counter() - t0
        _record_timing(report, "optimizations",
                       len(results) - len(report.settings["stored_runs"]),
                       report.elapsed["optimizations"])
        for t in tables:
            if t == 8:
                continue
            rows = [Row(t, r, paper_row(t, r.method, r.start_mm, data), results[r.name])
                    for r in TABLES[t].runs() if r.name in results]
            simulate_paper_designs(rows)
            report.rows[t] = rows
            report.checks[t] = table_checks(t, rows)
        if 3 in tables:
            report.extra["table3_p1_scan"] = first_variable_scan()
        if 8 in tables:
            w, f = (Run("robot_2dof", m, STARTS[1], TABLES[8].overrides).name
                    for m in ("weakly", "fully"))
            report.table8 = table8_rows(results.get(w), results.get(f), data)
        if maps:
            for key, spec in MAPS.items():
                if spec.table not in tables:
                    continue
                t0 = time.perf_counter()
                mj = {}
                for region in REGIONS:
                    mj.update(map_jobs(spec, grid, region))
                mstore = out / "jobs" / key
                map_stored = sum(read_stored(mstore / f"{n}.json") is not None for n in mj)
                say(f"Fig. {spec.figure}: {len(mj)} simulations (two {grid} x {grid} grids of "
                    f"p2, p4: the bounds' box and a zoom), results in {out / 'jobs' / key}")
                res = run_batch(max_deviation_job, mj, workers=workers, dask=address,
                                store=mstore, progress=progress, label=f"Fig. {spec.figure}")
                grids = {}
                for region in REGIONS:
                    grids[region], names = _collect_map(spec, grid, res, region)
                m = MapResult(spec, grids, names, len(mj), time.perf_counter() - t0)
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
