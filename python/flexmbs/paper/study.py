"""Studies: the tables, maps and figures `flexmbs reproduce` runs, compares with published
numbers and reports, as data (a TOML file; every key in ``docs/study-format.md``).

A study declares tables (a case, overrides, starting designs, methods, optimizer options,
where the published numbers are, the checks of the published findings, extra rows run with
other options or as a multi-start, `Variant`), design-domain maps and figures. `load_study()` reads and validates one (pydantic, as `flexmbs.model.description` does for
cases; errors are `CaseError` naming the file and the key) into a `Study`. The shipped study
(``cases/studies/paper.toml``, installed in ``flexmbs/cases_data/studies``) is the paper's;
a user's study file reproduces any other published results the same way
(``flexmbs reproduce --study FILE``).

>>> from flexmbs.paper.study import load_study
>>> s = load_study()                                    # the shipped study ('paper')
>>> sorted(s.tables)[:3], s.tables[1].methods
([1, 2, 3], ('weakly', 'fully'))
"""
from __future__ import annotations

import functools
import json
import re
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from flexmbs.batch import job_name
from flexmbs.errors import CaseError, ModelError
from flexmbs.files import check_regular_file
from flexmbs.methods.fully import OPTIMIZERS
from flexmbs.model.casefile import (_loc, case_path, friendly_error, nesting_guard,
                                    read_description, shipped_path)
from flexmbs.model.description import Finite, Int, NoBool, NonNegative, Positive
from flexmbs.model.options import build, FullyOptions, OPTIMIZER_TABLES, WeaklyOptions

__all__ = ["load_study", "study_path", "Study", "TableSpec", "MapSpec", "Run", "Variant",
           "METHODS", "ROW_CHECKS", "VARIANT_CHECKS", "DEFAULT_STUDY"]

#: The optimization methods a study runs.
METHODS = ("weakly", "fully")
#: The name of the shipped study `load_study()` reads by default.
DEFAULT_STUDY = "paper"

Method = Literal["weakly", "fully"]
Scalar = Union[bool, int, float, str]
Design = Annotated[list[Finite], Field(min_length=1)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ----------------------------------------------------------------------------- checks
class _Check(_Strict):
    what: str | None = None         # replaces the generated description of the finding
    paper: str | None = None        # replaces the generated text of the paper's side


class _RowCheck(_Check):
    methods: list[Method] | None = None     # the rows it applies to (default: every row)


class MassWithin(_RowCheck):
    """Converged, and the mass within rel of the published one (rows with a published mass)."""
    type: Literal["mass_within"]
    rel: NonNegative


class DesignWithin(_RowCheck):
    """Every design variable within rel of the published one (rows with a published design)."""
    type: Literal["design_within"]
    rel: NonNegative


class NotConverged(_RowCheck):
    """The run does not converge (the paper: the method oscillates)."""
    type: Literal["not_converged"]


class LocalOptimumReported(_RowCheck):
    """The optimum reported beside the published one, no criterion (a local optimum)."""
    type: Literal["local_optimum_reported"]
    note: str = "a local optimum"


class Converges(_Check):
    """The first run of `method` converges."""
    type: Literal["converges"]
    method: Method


class StartsAgreeWithin(_Check):
    """The designs of `method` from every start agree within rel (largest relative spread)."""
    type: Literal["starts_agree_within"]
    method: Method
    rel: NonNegative


class StartsDifferMore(_Check):
    """The designs of `method` from the starts spread more than those of `than`."""
    type: Literal["starts_differ_more"]
    method: Method
    than: Method


class MassesRatioAtLeast(_Check):
    """mass(numerator) / mass(denominator) >= ratio (first run of each method)."""
    type: Literal["masses_ratio_at_least"]
    numerator: Method
    denominator: Method
    ratio: Positive


class VariablesAtBound(_Check):
    """The named variables of the first run of `method` at their bound within rel."""
    type: Literal["variables_at_bound"]
    method: Method
    variables: Annotated[list[str], Field(min_length=1)]
    bound: Literal["lower", "upper"] = "lower"
    rel: NonNegative = 0.01


class VariablesOffBound(_Check):
    """The named variables of the first run of `method` farther than rel from their bound."""
    type: Literal["variables_off_bound"]
    method: Method
    variables: Annotated[list[str], Field(min_length=1)]
    bound: Literal["lower", "upper"] = "lower"
    rel: NonNegative = 0.1


CheckSpec = Annotated[Union[MassWithin, DesignWithin, NotConverged, LocalOptimumReported,
                            Converges, StartsAgreeWithin, StartsDifferMore, MassesRatioAtLeast,
                            VariablesAtBound, VariablesOffBound], Field(discriminator="type")]
class MassAtMost(_Check):
    """A variant's mass (a multi-start's best feasible one) at most (1 + rel) x the published
    mass of its method: within rel of the paper or lighter."""
    type: Literal["mass_at_most"]
    rel: NonNegative = 0.0


class Feasible(_Check):
    """A variant's design is feasible, re-checked by a simulation (a multi-start: a start ended
    feasible)."""
    type: Literal["feasible"]


class ReachedByAtLeast(_Check):
    """At least n starts of a multi-start variant reached the best design (within its
    best_tolerance), or, with rel, ended feasible at most (1 + rel) x the published mass."""
    type: Literal["reached_by_at_least"]
    n: Annotated[int, NoBool, Field(ge=1)]
    rel: NonNegative | None = None


class SpreadReported(_Check):
    """A multi-start variant's local optima reported (best, worst, how many starts reached the
    best, how many ended feasible), no criterion."""
    type: Literal["spread_reported"]


VariantCheckSpec = Annotated[Union[MassAtMost, Feasible, ReachedByAtLeast, SpreadReported],
                             Field(discriminator="type")]
#: Check types of a table's variants (`[[tables.N.variants]]`).
VARIANT_CHECKS = ("mass_at_most", "feasible", "reached_by_at_least", "spread_reported")

#: Check types applied to every row (the others apply once per table).
ROW_CHECKS = ("mass_within", "design_within", "not_converged", "local_optimum_reported")
_CHECK_TAGS = ROW_CHECKS + ("converges", "starts_agree_within", "starts_differ_more",
                            "masses_ratio_at_least", "variables_at_bound", "variables_off_bound") \
    + VARIANT_CHECKS


# ----------------------------------------------------------------------------- the file
class Scan(_Strict):
    """Maximum deviation over one design variable, the others held at each of `others`."""
    variable: str
    values: Annotated[list[Finite], Field(min_length=1)]
    others: Annotated[list[list[Finite]], Field(min_length=1)]
    caption: str = ""


Option = Union[Scalar, dict[str, Scalar]]
#: a plain name (a file or folder under the output folder: no path)
_PLAIN = re.compile(r"^[A-Za-z0-9_\-]+$")
Slug = Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]*$")]


class MultistartFile(_Strict):
    """`flexmbs.methods.multistart.multistart` settings of a variant."""
    starts: Annotated[int, NoBool, Field(ge=1)] = 8
    optimizer: str = "nlopt-mma"
    sampler: Literal["sobol", "lhs"] = "sobol"
    seed: Annotated[int, NoBool, Field(ge=0)] = 0
    candidates: Annotated[int, NoBool, Field(ge=1)] | None = None
    best_tolerance: NonNegative = 0.003


class VariantFile(_Strict):
    """An extra row of a table: the table's case run with other options (or a multi-start),
    reported beside the paper's rows, with its own checks."""
    key: Slug
    label: str
    method: Method
    options: dict[str, Option] = {}
    start: Design | None = None
    multistart: MultistartFile | None = None
    checks: list[VariantCheckSpec] = []


class TableFile(_Strict):
    kind: Literal["rows", "active_steps"] = "rows"
    title: str
    heading: str | None = None
    case: str
    overrides: dict[str, Scalar] = {}
    published: Annotated[list[str], Field(min_length=1)]
    starts: Annotated[list[Design], Field(min_length=1)]
    methods: Annotated[list[Method], Field(min_length=1)] = ["weakly", "fully"]
    options: dict[Method, dict[str, Scalar]] = {}
    cost: Positive = 1.0
    checks: list[CheckSpec] = []
    scan: Scan | None = None
    variants: list[VariantFile] = []


class MapFile(_Strict):
    figure: Int
    table: Int
    step: Annotated[int, NoBool, Field(ge=1)]
    axes: Annotated[list[str], Field(min_length=2, max_length=2)]
    fixed: dict[str, Finite] = {}
    zoom: Annotated[list[Annotated[list[Finite], Field(min_length=2, max_length=2)]],
                    Field(min_length=2, max_length=2)]


class _Figure(_Strict):
    key: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_\-]+$")]
    number: Int


class TwoMethodsFigure(_Figure):
    """Objective history of a table's runs and the deviation history of their optima."""
    kind: Literal["two_methods"]
    table: Int
    what: str


class OscillationFigure(_Figure):
    """A non-converging run: mass and critical time per cycle, the last cycles' deviations."""
    kind: Literal["oscillation"]
    table: Int
    method: Method = "weakly"
    last: Annotated[int, NoBool, Field(ge=1)] = 4
    deviation_label: str = "deviation (mm)"
    title: str
    caption: str


class StartsFigure(_Figure):
    """Every start of a table, one row of panels per method."""
    kind: Literal["starts"]
    table: Int
    title: str
    caption: str


class StartDetailFigure(_Figure):
    """Both methods from one start of a table: mass, maximum deviation per iterate, optima."""
    kind: Literal["start_detail"]
    table: Int
    start: Design
    title: str
    caption: str


class MapFigure(_Figure):
    """The panels of a design-domain map ([maps.KEY])."""
    kind: Literal["map"]
    map: str


FigureSpec = Annotated[Union[TwoMethodsFigure, OscillationFigure, StartsFigure,
                             StartDetailFigure, MapFigure], Field(discriminator="kind")]
_FIGURE_TAGS = ("two_methods", "oscillation", "starts", "start_detail", "map")


class Demo(_Strict):
    table: Int
    about: str


class StudyInfo(_Strict):
    name: str
    reference: str = ""
    introduction: str = ""
    published: str
    demo: Demo | None = None


class StudyFile(_Strict):
    study: StudyInfo
    options: dict[Method, dict[str, Scalar]] = {}
    tables: Annotated[dict[str, TableFile], Field(min_length=1)]
    maps: dict[str, MapFile] = {}
    figures: list[FigureSpec] = []


# ----------------------------------------------------------------------------- runtime
@dataclass(frozen=True)
class Run:
    """One optimization: a case (name or path + overrides), a method, a starting design and
    the optimizer's options. Runs with the same name share one job."""
    case: str
    method: str
    start_mm: tuple
    overrides: tuple = ()       # sorted (key, value) pairs
    options: tuple = ()         # sorted (keyword, value) pairs of the optimizer

    @property
    def name(self):
        """The job name: case, end time, other overrides, method and start, e.g.
        ``case-t0.65-weakly-50-50-50-50`` (characters a job name may not hold, e.g. the space
        of 'my case.toml', replaced: flexmbs.batch.job_name)."""
        ov = dict(self.overrides)
        t_end = ov.pop("time.t_end", None)
        case = Path(self.case).stem if self.case.endswith(".toml") else self.case
        parts = [case]
        if t_end is not None:
            parts.append(f"t{t_end:g}")
        parts += [f"{k}{v}" for k, v in sorted(ov.items())]
        parts.append(self.method)
        parts.append("-".join(f"{v:g}" for v in self.start_mm))
        return job_name("-".join(parts))

    def job(self):
        """Keyword arguments of `flexmbs.paper.reproduce.optimization_job`."""
        return dict(case=self.case, method=self.method, start=list(self.start_mm),
                    overrides=dict(self.overrides), options=dict(self.options))


def _option_text(v):
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_option_text(x)}" for k, x in v.items()) + "}"
    return f'"{v}"' if isinstance(v, str) else f"{v}"


@dataclass(frozen=True)
class Variant:
    """An extra row of a table (``[[tables.N.variants]]``): the table's case (and overrides)
    optimized by `method` with the variant's own `options` (over the optimizer's defaults,
    not the study's or the table's), from `start`, or from the multi-start's drawn starts
    (`multistart`: {starts, optimizer, sampler, seed, candidates, best_tolerance}).

    Its job is stored under ``jobs/variants/NAME.json`` (`name`), apart from the table runs
    (``jobs/optimizations/``), so no variant can take a table run's name."""
    table: int
    key: str
    label: str
    method: str
    case: str
    overrides: tuple            # sorted (key, value) pairs of the table
    start_mm: tuple | None      # None for a multi-start
    options: dict = field(default_factory=dict, hash=False, compare=True)
    multistart: dict | None = field(default=None, hash=False, compare=True)
    checks: tuple = ()

    @property
    def name(self):
        """The job name: ``tableN-KEY`` (under jobs/variants/)."""
        return f"table{self.table}-{self.key}"

    @property
    def options_text(self):
        """The options as the study file gives them, e.g. 'move_limit = 0.1'."""
        opts = dict(self.multistart or {}, **self.options)
        return ", ".join(f"{k} = {_option_text(v)}" for k, v in opts.items()) or "defaults"

    def job(self):
        """Keyword arguments of `flexmbs.paper.reproduce.optimization_job` (a single run) or of
        `flexmbs.paper.reproduce.multistart_job` (a multi-start, without its workers and store)."""
        if self.multistart is not None:
            return dict(case=self.case, overrides=dict(self.overrides),
                        options=dict(self.options), multistart=dict(self.multistart))
        return dict(case=self.case, method=self.method, start=list(self.start_mm),
                    overrides=dict(self.overrides), options=dict(self.options))


@dataclass(frozen=True)
class TableSpec:
    """A table of a study: its case, its rows (one run per method and start), the optimizer
    options, where its published numbers are, its checks, scan and figures.

    variables, lower, upper, units: the case's design variables (with the overrides)."""
    number: int
    title: str
    case: str
    overrides: tuple
    published: tuple            # keys of the published data leading to this table
    starts: tuple
    methods: tuple = METHODS
    options: tuple = ()         # ((method, ((keyword, value), ...)), ...)
    kind: str = "rows"
    heading: str = ""
    cost: Finite = 1.0
    checks: tuple = ()
    scan: Scan | None = None
    figures: tuple = ()
    variables: tuple = ()
    lower: tuple = ()
    upper: tuple = ()
    units: tuple = ()
    variants: tuple = ()        # Variant, in the study file's order

    def run(self, method, start=None):
        """The run of `method` from `start` (default: the first start)."""
        start = self.starts[0] if start is None else start
        return Run(self.case, method, tuple(float(v) for v in start), self.overrides,
                   dict(self.options).get(method, ()))

    def runs(self):
        return [self.run(m, s) for m in self.methods for s in self.starts]

    def index(self, name):
        return self.variables.index(name)


@dataclass(frozen=True)
class MapSpec:
    """A design-domain map of the deviation at one time step over a grid of two design
    variables (`axes`, names), the others at the case's start or at `fixed` {name: value}.

    Two grids: the whole box of the bounds ('full'), and `zoom` ((lo, hi), (lo, hi))."""
    key: str
    figure: int
    table: int
    case: str
    overrides: tuple
    step: int                   # 1-based (t = (step - 1) h)
    fixed: tuple                # ((name, value), ...) of the variables held fixed
    zoom: tuple
    axes: tuple                 # names of the mapped variables

    def grid(self, n, lower, upper, region="full", variables=None):
        """The n values of each mapped variable: between the bounds ('full') or in the zoom
        box ('zoom'). lower, upper: of every design variable, named by `variables`."""
        import numpy as np
        i, j = self.indices(variables)
        if region == "zoom":
            (a0, a1), (b0, b1) = self.zoom
        elif region == "full":
            a0, a1, b0, b1 = lower[i], upper[i], lower[j], upper[j]
        else:
            raise ModelError(f"region must be 'full' or 'zoom', got {region!r}")
        return np.linspace(a0, a1, n), np.linspace(b0, b1, n)

    def indices(self, variables):
        """Indices of the mapped variables in `variables` (the case's names)."""
        return tuple(list(variables).index(a) for a in self.axes)


@dataclass(frozen=True)
class Study:
    """A validated study file (`load_study`)."""
    path: Path
    name: str
    reference: str
    introduction: str
    published: Path
    tables: dict
    maps: dict = field(default_factory=dict)
    figures: tuple = ()
    demo: Demo | None = None

    def published_data(self):
        """The published numbers (the JSON file `published`)."""
        return read_published(self.published)

    def figure_table(self, fig):
        """The table a figure belongs to."""
        return self.maps[fig.map].table if fig.kind == "map" else fig.table


# ----------------------------------------------------------------------------- loading
def study_path(study=None):
    """The file of a study: an existing path, or the name of a shipped study (default
    'paper'); CaseError naming the shipped studies if neither."""
    return shipped_path(DEFAULT_STUDY if study is None else study, "study", "studies")


def _published_file(name, folder, source):
    """The published-numbers file: beside the study file, else shipped with flexmbs."""
    cands = [folder / name]
    if len(Path(name).parts) == 1:
        root = Path(__file__).resolve().parents[3]
        if (root / "python" / "flexmbs").is_dir():
            cands.append(root / "tests" / "data" / name)
        try:
            cands.append(Path(str(resources.files("flexmbs") / "paper_data" / name)))
        except (ModuleNotFoundError, NotADirectoryError):     # pragma: no cover
            pass
    for c in cands:
        if c.is_file():
            return c
    raise CaseError(f"{source}: key 'study.published': file {name!r} not found (looked in "
                    f"{', '.join(str(c.parent) for c in cands)})")


def _optimizer_keywords(method):
    """The options a study may give a method: WeaklyOptions' fields; the fully coupled
    method's optimizer and FullyOptions' fields, its optimizers' options flat or as tables
    (flexmbs.model.options)."""
    if method == "weakly":
        return list(WeaklyOptions.model_fields)
    flat = [n for t in OPTIMIZER_TABLES.values() for n in t.model_fields]
    return ["optimizer"] + list(FullyOptions.model_fields) + list(dict.fromkeys(flat))


def _check_values(method, opts, where, source):
    """The values of a method's options, validated by its options object."""
    kind = WeaklyOptions if method == "weakly" else FullyOptions
    try:
        build(kind, {k: v for k, v in opts.items() if k != "optimizer"})
    except ModelError as exc:
        raise CaseError(f"{source}: key '{where}': {exc}") from None


#: optimizer options a study file may not set: where a run writes (a path: no file names a
#: file to write), how it is shown and whether it resumes are `flexmbs reproduce`'s
NOT_STUDY_OPTIONS = ("history", "progress", "resume")


def _refuse_run_options(options, where, source):
    for opt in NOT_STUDY_OPTIONS:
        if opt in options:
            raise CaseError(f"{source}: key '{where}.{opt}': a study's runs are stored "
                            f"by `flexmbs reproduce` (in its --out folder), got {opt} = "
                            f"{options[opt]!r}; allowed: the optimizer's other options")


#: keys a variant's fully coupled options held before the optimizers' tables: key -> table
OLD_TABLE_KEYS = {"mma_options": "mma", "nlopt_options": "nlopt"}


def _rename_old_tables(method, opts, where, source):
    """`opts` (a variant's options, changed in place) with the old keys mma_options and
    nlopt_options renamed to the tables mma and nlopt, with a DeprecationWarning naming the
    new key; CaseError when the old key and its table are both given."""
    import warnings

    if method != "fully":
        return
    for old, new in OLD_TABLE_KEYS.items():
        if old not in opts:
            continue
        if new in opts:
            raise CaseError(f"{source}: keys '{where}.{old}' and '{where}.{new}' are the same "
                            f"table (the first deprecated): give '{new}' only")
        warnings.warn(f"{source}: key '{where}.{old}' is deprecated: give it as '{where}.{new}'",
                      DeprecationWarning, stacklevel=4)
        opts[new] = opts.pop(old)


def _check_options(options, where, source):
    for method, opts in options.items():
        allowed = _optimizer_keywords(method)
        _refuse_run_options(opts, f"{where}.{method}", source)
        for k in opts:
            if k not in allowed:
                raise CaseError(f"{source}: key '{where}.{method}.{k}' is not an option of the "
                                f"{method} coupled optimizer, got {k!r}; allowed: "
                                f"{', '.join(allowed)}")
        _check_values(method, opts, f"{where}.{method}", source)


def _resolve_case(case, folder):
    """A case name, or a path relative to the study file's folder."""
    p = Path(case)
    if case.endswith(".toml") and not p.is_absolute() and (folder / p).is_file():
        return str((folder / p).resolve())
    return case


def _table_spec(n, t, defaults, folder, source, published):
    where = f"tables.{n}"
    case = _resolve_case(t.case, folder)
    try:
        desc = read_description(case_path(case), dict(t.overrides) or None)
    except CaseError as exc:
        raise CaseError(f"{source}: key '{where}.case' ({t.case!r}): {exc}") from None
    dv = desc.design
    names = tuple(v.name for v in dv)
    for k, s in enumerate(t.starts):
        if len(s) != len(names):
            raise CaseError(f"{source}: key '{where}.starts[{k}]' must have {len(names)} values "
                            f"({', '.join(names)}), got {s}")
    node = published
    for k, key in enumerate(t.published):
        if not isinstance(node, dict) or key not in node:
            raise CaseError(f"{source}: key '{where}.published': no entry {key!r} at "
                            f"{t.published[:k]} of the published numbers")
        node = node[key]
    _check_options(t.options, f"{where}.options", source)
    for k, c in enumerate(t.checks):
        for v in getattr(c, "variables", None) or ():
            if v not in names:
                raise CaseError(f"{source}: key '{where}.checks[{k}].variables': {v!r} is not a "
                                f"design variable of {t.case!r} ({', '.join(names)})")
        for m in [getattr(c, a, None) for a in ("method", "than", "numerator", "denominator")] \
                + list(getattr(c, "methods", None) or []):
            if m is not None and m not in t.methods:
                raise CaseError(f"{source}: key '{where}.checks[{k}]': method {m!r} is not "
                                f"among the table's methods {t.methods}")
    if t.kind == "active_steps" and (len(t.starts) != 1 or set(t.methods) != set(METHODS)):
        raise CaseError(f"{source}: key '{where}': a table of kind 'active_steps' has one start "
                        f"and both methods, got {len(t.starts)} start(s), methods {t.methods}")
    if t.scan is not None:
        if t.scan.variable not in names:
            raise CaseError(f"{source}: key '{where}.scan.variable': {t.scan.variable!r} is not "
                            f"a design variable of {t.case!r} ({', '.join(names)})")
        for k, o in enumerate(t.scan.others):
            if len(o) != len(names) - 1:
                raise CaseError(f"{source}: key '{where}.scan.others[{k}]' must have "
                                f"{len(names) - 1} values (the variables but "
                                f"{t.scan.variable}), got {o}")
    opts = {m: {**defaults.get(m, {}), **t.options.get(m, {})} for m in t.methods}
    variants = tuple(_variant(n, k, v, t, case, names, source) for k, v in enumerate(t.variants))
    keys = [v.key for v in variants]
    for k, key in enumerate(keys):
        if key in keys[:k]:
            raise CaseError(f"{source}: key '{where}.variants[{k}].key': {key!r} is used twice "
                            f"in table {n}")
    return TableSpec(
        number=n, title=t.title, case=case, overrides=tuple(sorted(t.overrides.items())),
        published=tuple(t.published), starts=tuple(tuple(map(float, s)) for s in t.starts),
        methods=tuple(t.methods), options=tuple((m, tuple(sorted(o.items())))
                                                for m, o in opts.items()),
        kind=t.kind, heading=t.heading or t.title, cost=float(t.cost), checks=tuple(t.checks),
        scan=t.scan, variables=names, lower=tuple(v.lower for v in dv),
        upper=tuple(v.upper for v in dv), units=tuple(v.unit or "" for v in dv),
        variants=variants)


#: multistart()'s own keywords: not optimizer options of a multi-start variant
_MULTISTART_OWN = ("optimizer", "sampler", "seed", "candidates", "best_tolerance", "starts",
                   "workers", "dask", "store", "progress", "resume", "history", "start_range")


def _variant(n, k, v, t, case, names, source):
    """A table's variant (`Variant`), checked: its method's options, its start, its multi-start
    settings."""
    where = f"tables.{n}.variants[{k}]"
    _rename_old_tables(v.method, v.options, f"{where}.options", source)
    allowed = _optimizer_keywords(v.method)
    _refuse_run_options(v.options, f"{where}.options", source)
    for k in v.options:
        if k not in allowed:
            raise CaseError(f"{source}: key '{where}.options.{k}' is not an option of the "
                            f"{v.method} coupled optimizer, got {k!r}; allowed: "
                            f"{', '.join(allowed)}")
    _check_values(v.method, v.options, f"{where}.options", source)
    ms = None
    if v.multistart is not None:
        m = v.multistart
        if v.method != "fully":
            raise CaseError(f"{source}: key '{where}.multistart': a multi-start runs the fully "
                            f"coupled method, got method {v.method!r}")
        if v.start is not None:
            raise CaseError(f"{source}: key '{where}.start': a multi-start draws its starting "
                            f"designs; leave 'start' out (got {v.start})")
        if m.optimizer not in OPTIMIZERS:
            raise CaseError(f"{source}: key '{where}.multistart.optimizer' must be one of "
                            f"{', '.join(OPTIMIZERS)}, got {m.optimizer!r}")
        if m.candidates is not None and m.candidates < m.starts:
            raise CaseError(f"{source}: key '{where}.multistart.candidates' must be >= starts "
                            f"({m.starts}), got {m.candidates}")
        for opt in v.options:
            if opt in _MULTISTART_OWN:
                raise CaseError(f"{source}: key '{where}.options.{opt}' is a setting of the "
                                f"multi-start: give it in '{where}.multistart' (keys: starts, "
                                f"optimizer, sampler, seed, candidates, best_tolerance)")
        ms = m.model_dump()
    else:
        for c, chk in enumerate(v.checks):
            if chk.type in ("reached_by_at_least", "spread_reported"):
                raise CaseError(f"{source}: key '{where}.checks[{c}]': {chk.type!r} needs a "
                                f"multi-start variant (key '{where}.multistart')")
    start = None
    if ms is None:
        start = tuple(float(x) for x in (v.start if v.start is not None else t.starts[0]))
        if len(start) != len(names):
            raise CaseError(f"{source}: key '{where}.start' must have {len(names)} values "
                            f"({', '.join(names)}), got {list(start)}")
    return Variant(table=n, key=v.key, label=v.label, method=v.method, case=case,
                   overrides=tuple(sorted(t.overrides.items())), start_mm=start,
                   options=dict(v.options), multistart=ms, checks=tuple(v.checks))


#: pydantic's tags of the members of a value's union (an option: a scalar, or a table of
#: scalars such as frame_kind's or mma_options'), added to an error's location
_MEMBER_TAGS = ("bool", "int", "float", "str")


def _member_tag(part):
    return isinstance(part, str) and (part in _MEMBER_TAGS or part.startswith("dict["))


def _union_lines(errors, source_loc):
    """One sentence per option value that fits no member of its union (pydantic gives one
    error per member, 4 to 8 of them): the deepest key at fault, what it may be, the value."""
    groups = {}
    for e in errors:
        loc = tuple(p for p in e["loc"] if not _member_tag(p))
        g = groups.setdefault(loc, dict(input=e.get("input"), table=False))
        last = e["loc"][-1] if e["loc"] else None        # a table is allowed at this key
        g["table"] |= isinstance(last, str) and last.startswith("dict[")
    out = []
    for loc, g in groups.items():
        if any(other != loc and other[:len(loc)] == loc for other in groups):
            continue                 # a key inside this value is named instead
        what = "a number, a string or true/false" + (", or a table of those (e.g. "
                                                     "frame_kind = { follower = \"chord\" })"
                                                     if g["table"] else "")
        out.append(f"key '{source_loc(loc)}' must be {what}, got {g['input']!r}")
    return out


def _format_errors(exc, source):
    errors = exc.errors()
    union = [e for e in errors if any(_member_tag(p) for p in e["loc"])]
    lines = [friendly_error(e, StudyFile, "docs/study-format.md",
                            tags=_CHECK_TAGS + _FIGURE_TAGS) for e in errors if e not in union]
    lines += _union_lines(union, _loc)
    more = f" (and {len(lines) - 5} more)" if len(lines) > 5 else ""
    return f"{source}: " + "; ".join(lines[:5]) + more


@functools.lru_cache(maxsize=8)
def _load(path_text, text):
    path = Path(path_text)
    source = str(path)
    try:
        with nesting_guard(source):
            raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(f"{source}: not valid TOML: {exc}") from None
    try:
        with nesting_guard(source):
            f = StudyFile.model_validate(raw)
    except ValidationError as exc:
        raise CaseError(_format_errors(exc, source)) from None
    folder = path.parent
    _check_options(f.options, "options", source)
    pub = _published_file(f.study.published, folder, source)
    try:
        published = read_published(pub, f"{source}: key 'study.published': {pub}")
    except CaseError:
        raise
    except (OSError, ValueError) as exc:
        raise CaseError(f"{source}: key 'study.published': {pub} is not readable JSON: "
                        f"{exc}") from None
    tables = {}
    for key, t in f.tables.items():
        if not key.isdigit():
            raise CaseError(f"{source}: key 'tables.{key}': tables are numbered "
                            f"([tables.1], [tables.2], ...), got {key!r}")
        tables[int(key)] = _table_spec(int(key), t, f.options, folder, source, published)
    tables = dict(sorted(tables.items()))
    maps = {}
    for key, m in f.maps.items():
        where = f"maps.{key}"
        if not _PLAIN.match(key):
            # its results go to OUT/jobs/KEY: a plain name, never a path out of the folder
            raise CaseError(f"{source}: key '{where}': a map's key names its folder of "
                            f"results: letters, digits, '_' and '-' only, got {key!r}")
        if m.table not in tables:
            raise CaseError(f"{source}: key '{where}.table': no table {m.table} "
                            f"(tables: {', '.join(map(str, tables))})")
        spec = tables[m.table]
        for name in [*m.axes, *m.fixed]:
            if name not in spec.variables:
                raise CaseError(f"{source}: key '{where}': {name!r} is not a design variable of "
                                f"table {m.table}'s case ({', '.join(spec.variables)})")
        maps[key] = MapSpec(key, m.figure, m.table, spec.case, spec.overrides, m.step,
                            tuple(m.fixed.items()), tuple(tuple(z) for z in m.zoom),
                            tuple(m.axes))
    keys = set()
    for k, fig in enumerate(f.figures):
        where = f"figures[{k}]"
        if fig.key in keys:
            raise CaseError(f"{source}: key '{where}.key': {fig.key!r} is used twice")
        keys.add(fig.key)
        if fig.kind == "map":
            if fig.map not in maps:
                raise CaseError(f"{source}: key '{where}.map': no map {fig.map!r} (maps: "
                                f"{', '.join(maps) or 'none'})")
        elif fig.table not in tables:
            raise CaseError(f"{source}: key '{where}.table': no table {fig.table} "
                            f"(tables: {', '.join(map(str, tables))})")
    if f.study.demo is not None and f.study.demo.table not in tables:
        raise CaseError(f"{source}: key 'study.demo.table': no table {f.study.demo.table}")
    # a run shared by tables is one job: it must have the same options everywhere
    seen = {}
    for t in tables.values():
        for r in t.runs():
            if seen.setdefault(r.name, r) != r:
                raise CaseError(f"{source}: run {r.name} of table {t.number} has other optimizer "
                                f"options than in another table: {dict(r.options)} vs "
                                f"{dict(seen[r.name].options)}")
    owner = [maps[fig.map].table if fig.kind == "map" else fig.table for fig in f.figures]
    tables = {n: replace(t, figures=tuple(fig.key for fig, o in zip(f.figures, owner) if o == n))
              for n, t in tables.items()}
    return Study(path=path, name=f.study.name, reference=f.study.reference,
                 introduction=f.study.introduction, published=pub, tables=tables, maps=maps,
                 figures=tuple(f.figures), demo=f.study.demo)


def read_published(path, source=None):
    """The JSON content of a study's published numbers; CaseError naming the file when it is
    nested too deeply to read (json recurses per level)."""
    check_regular_file(path, source or "published numbers", CaseError)
    with nesting_guard(source or path):
        return json.loads(Path(path).read_text(encoding="utf-8-sig"))


def load_study(study=None):
    """Read and validate a study: a path to a study file or the name of a shipped study
    (default: the paper's). Returns a `Study`; CaseError naming the file and the key."""
    if isinstance(study, Study):
        return study
    p = study_path(study).resolve()
    check_regular_file(p, "study file", CaseError)
    try:
        text = p.read_text(encoding="utf-8-sig")     # a leading BOM is dropped
    except (OSError, UnicodeDecodeError) as exc:
        raise CaseError(f"{p}: cannot be read: {exc}") from None
    return _load(str(p), text)          # read again when the file changed
