"""The options of the optimization methods and optimizers, as frozen, validated objects.

One object per method and per optimizer, each with its defaults and its meaning in one table
(its docstring; docs/optimizers.md shows the same tables, checked against these objects by
tests/test_options.py), in the manner of the per-optimizer option tables of pyOptSparse:

    FullyOptions        the fully coupled method (flexmbs.methods.fully.optimize_fully): its
                        stopping rules, design scale, verification, and one table per
                        optimizer under its name:
    SQPOptions          sqp            the trust-region SQP (flexmbs.optimizers.loops)
    MMAOptions          mma            Svanberg's globally convergent MMA (flexmbs.optimizers.mma)
    SLSQPOptions        slsqp          scipy's SLSQP
    NLoptOptions        nlopt          NLopt's MMA, CCSAQ and SLSQP (flexmbs.optimizers.library)
    WeaklyOptions       the weakly coupled method (flexmbs.methods.weakly.optimize_weakly)
    MultistartOptions   the multi-start (flexmbs.methods.multistart.multistart)

Every object is built from a dict (a case file's ``[optimize]`` table, a study's options, a
call's ``options=``) by `build`, which turns pydantic's errors into a ModelError naming the
option, its value and what is allowed. A FullyOptions dict may give an optimizer's option
flat (``{"trust_radius": 0.1}``) or in its table (``{"sqp": {"trust_radius": 0.1}}``);
the same option both flat and in its table with two values is an error naming both.
`FullyOptions.check_optimizer` sets aside the table of another optimizer than the one run
(a SettingWarning naming the option and the optimizer run), or refuses it (ModelError) when
the caller named both the optimizer and that table. `OptimizeSection` is the case file's ``[optimize]`` table
(docs/case-format.md).
"""
from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, ValidationError,
                      field_validator)

from flexmbs.errors import ModelError, SettingWarning

__all__ = ["FullyOptions", "SQPOptions", "MMAOptions", "SLSQPOptions", "NLoptOptions",
           "WeaklyOptions", "MultistartOptions", "OptimizeSection", "OPTIMIZER_TABLES",
           "OPTIMIZER_OPTIONS", "build", "check_verify_value", "from_keywords",
           "doc_rows", "markdown_table"]


def _plain(v):
    """numpy scalars and arrays as Python numbers and lists."""
    return v.tolist() if hasattr(v, "tolist") else v


Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Count = Annotated[int, Field(ge=1)]
Whole = Annotated[int, Field(ge=0)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
FrameKind = Literal["auto", "tangent", "chord"]
#: `verify`: True, False, 'check' or a relative accuracy in (0, 0.1]
Verify = Union[bool, Literal["check"], Annotated[float, Field(gt=0, le=0.1)]]


def check_verify_value(verify):
    """A `verify` option: True, False, 'check' or a relative accuracy in (0, 0.1] (a float);
    ModelError otherwise."""
    if isinstance(verify, bool) or (isinstance(verify, str) and verify == "check"):
        return verify
    if isinstance(verify, (int, float)) or hasattr(verify, "dtype"):
        try:
            v = float(verify)
        except (TypeError, ValueError):
            v = math.nan
        if 0 < v <= 0.1:
            return v
    raise ModelError(f"verify must be True, False, 'check' or a relative accuracy in (0, 0.1] "
                     f"(e.g. 1e-3), got {verify!r}")


class _Options(BaseModel):
    """Frozen, strict (no '5' for 5, no true for 1 or 1.0: pydantic's strict mode), no
    unknown keys."""
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    def as_dict(self):
        """The options as plain JSON data (what a result and a history record)."""
        return self.model_dump(mode="json")


def _verify_field(v):
    try:
        return check_verify_value(_plain(v))
    except ModelError as exc:
        raise ValueError(str(exc).removeprefix("verify ")) from None


class SQPOptions(_Options):
    """The trust-region SQP (optimizer 'sqp'; flexmbs.optimizers.loops._run_sqp).

    ================  ========  ===============================================================
    option            default   meaning
    ================  ========  ===============================================================
    trust_radius      0.2       initial relative trust-region radius (of the scaled design)
    max_trust_radius  0.5       largest relative trust-region radius
    model_fidelity    0.1       a step is rejected when a constraint near its limit differs
                                from its linearization by more than this (None: no such test)
    ================  ========  ===============================================================
    """
    trust_radius: Pos = 0.2
    max_trust_radius: Pos = 0.5
    model_fidelity: Pos | None = 0.1


class MMAOptions(_Options):
    """Svanberg's globally convergent MMA (optimizer 'mma'; flexmbs.optimizers.mma.MMA).

    ============  ========  ===================================================================
    option        default   meaning
    ============  ========  ===================================================================
    conservative  True      GCMMA: inner iterations until the approximations are conservative
    move          0.5       move limit, a fraction of the variable's range per iteration,
                            in (0, 1]
    asyinit       0.5       initial asymptote distance, a fraction of the range
    asyincr       1.2       asymptote widening when a variable moves the same way twice, > 1
    asydecr       0.7       asymptote narrowing when a variable oscillates, in (0, 1)
    albefa        0.1       the subproblem's bounds alpha, beta this far inside the
                            asymptotes, a fraction of x - asymptote in (0, 1)
    c             1000.0    penalty of the elastic variables (infeasible subproblems)
    check_below   -0.05     constraints below this value are not checked for conservatism
    max_inner     20        GCMMA inner iterations per outer iteration at most
    ============  ========  ===================================================================
    """
    conservative: bool = True
    # bounds that flexmbs.optimizers.mma.MMA needs: a step of at most move x range (more
    # than the range is no limit); asyincr widens and asydecr narrows the asymptotes;
    # albefa < 1 keeps alpha between the lower asymptote and x (beta likewise)
    move: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.5
    asyinit: Pos = 0.5
    asyincr: Annotated[float, Field(gt=1, allow_inf_nan=False)] = 1.2
    asydecr: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.7
    albefa: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.1
    c: Pos = 1000.0
    check_below: Annotated[float, Field(le=0, allow_inf_nan=False)] = -0.05
    max_inner: Count = 20

    def mma_keywords(self):
        """The keyword arguments of flexmbs.optimizers.mma.MMA (all but max_inner)."""
        d = self.model_dump()
        d.pop("max_inner")
        return d


class SLSQPOptions(_Options):
    """scipy's SLSQP (optimizer 'slsqp'; flexmbs.optimizers.loops._run_slsqp).

    ======  ========  =============================================================
    option  default   meaning
    ======  ========  =============================================================
    ftol    1e-10     SLSQP's own objective tolerance (scipy's ``ftol``)
    ======  ========  =============================================================
    """
    ftol: Pos = 1e-10


class NLoptOptions(_Options):
    """NLopt's MMA, CCSAQ and SLSQP (optimizers 'nlopt-mma', 'nlopt-ccsaq', 'nlopt-slsqp';
    flexmbs.optimizers.library.run_nlopt).

    =================  ========  ==================================================================
    option             default   meaning
    =================  ========  ==================================================================
    screen             -0.3      rows given to the optimizer: those with g > screen and the local
                                 maxima of each constraint's history, enlarged (with a restart)
                                 when a left-out row is the most violated (None: every row)
    log_scale          True      variables whose bounds span a decade or more are mapped to
                                 [0, 1] logarithmically
    initial_step       None      NLopt's initial step in [0, 1] units, in (0, 1] (None: NLopt's)
    max_restarts       20        screening restarts at most
    params             {}        NLopt algorithm parameters, e.g. {dual_maxeval = 1000}
    feasibility_phase  True      from an infeasible start, first minimize the largest constraint
                                 value until a design is feasible
    =================  ========  ==================================================================
    """
    screen: Annotated[float, Field(le=0, allow_inf_nan=False)] | None = -0.3
    log_scale: bool = True
    initial_step: Annotated[float, Field(gt=0, le=1)] | None = None
    max_restarts: Whole = 20
    params: dict[str, Finite] = {}
    feasibility_phase: bool = True


#: option table name -> its class (FullyOptions' fields holding an optimizer's options)
OPTIMIZER_TABLES = {"sqp": SQPOptions, "mma": MMAOptions, "slsqp": SLSQPOptions,
                    "nlopt": NLoptOptions}
#: optimizer -> the name of its option table
OPTIMIZER_OPTIONS = {"mma": "mma", "sqp": "sqp", "slsqp": "slsqp", "nlopt-mma": "nlopt",
                     "nlopt-ccsaq": "nlopt", "nlopt-slsqp": "nlopt"}


class FullyOptions(_Options):
    """The fully coupled method (flexmbs.methods.fully.optimize_fully).

    ====================  ================  ========================================================
    option                default           meaning
    ====================  ================  ========================================================
    max_iterations        100               optimizer iterations at most (NLopt: every new design
                                            simulated counts as one)
    max_simulations       1000              simulations at most
    objective_rel_change  1e-3              the paper's test: relative objective change between
                                            two iterations below this ...
    constraint_violation  1e-6              ... and constraint violation max(0, max g) at most
                                            this (flexmbs.problem.FEASIBILITY_TOL)
    design_rel_change     None              if given, the relative change of the scaled design
                                            must be below it too (the paper's four-bar: 1e-3)
    kkt_tol               1e-3              first-order test that must hold as well (relative KKT
                                            residual, flexmbs.optimizers.loops.kkt_residual)
    active_tol            1e-3              constraints with g >= -active_tol are active (KKT test,
                                            history's active_steps)
    scale                 None              design scale, x = p / scale (the variables' units);
                                            None: the start
    verify                True              verify the final design at converged resolution
                                            (True, a relative accuracy in (0, 0.1], 'check':
                                            report only, False)
    sqp                   SQPOptions()      the trust-region SQP's options
    mma                   MMAOptions()      the hand-written MMA's options
    slsqp                 SLSQPOptions()    scipy SLSQP's options
    nlopt                 NLoptOptions()    NLopt's optimizers' options
    ====================  ================  ========================================================

    Only the table of the optimizer run is used (`check_optimizer`).
    """
    max_iterations: Count = 100
    max_simulations: Count = 1000
    objective_rel_change: Pos = 1e-3
    constraint_violation: Pos = 1e-6
    design_rel_change: Pos | None = None
    kkt_tol: Pos = 1e-3
    active_tol: Pos = 1e-3
    scale: Annotated[list[Pos], BeforeValidator(_plain)] | None = None
    verify: Annotated[Verify, BeforeValidator(_verify_field)] = True
    sqp: SQPOptions = SQPOptions()
    mma: MMAOptions = MMAOptions()
    slsqp: SLSQPOptions = SLSQPOptions()
    nlopt: NLoptOptions = NLoptOptions()

    @field_validator("scale", mode="before")
    @classmethod
    def _scale(cls, v):
        if v is not None and not isinstance(v, list):
            v = _plain(v)
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = [v]
            if isinstance(v, tuple):
                v = list(v)
        return v

    @classmethod
    def routed(cls, data, where="options"):
        """`data` (a dict) with every optimizer's option given flat moved into its table;
        ModelError when an option is given both flat and in its table with two values, the
        table's not its default."""
        data = dict(data)
        for table, kind in OPTIMIZER_TABLES.items():
            flat = {k: data.pop(k) for k in list(data) if k in kind.model_fields
                    and k not in cls.model_fields}
            if flat:
                inner = data.get(table, {})
                inner = inner.as_dict() if isinstance(inner, _Options) else inner
                if not isinstance(inner, dict):     # pydantic names the bad table
                    data[table] = inner
                    continue
                default = kind()
                for k, v in flat.items():
                    # a table holding the option's default (a whole table of defaults, from
                    # as_dict or an options object) gives way to the flat value
                    if k in inner and _plain(inner[k]) != _plain(v) \
                            and _plain(inner[k]) != _plain(getattr(default, k)):
                        raise ModelError(f"{where}: option {k} = {v!r} and option {table}.{k} "
                                         f"= {inner[k]!r} differ; give it once")
                data[table] = {**inner, **flat}
        return data

    def unused(self, optimizer):
        """[(table.option, value, owners)] of the options in another optimizer's table than
        `optimizer`'s that differ from their defaults."""
        mine = OPTIMIZER_OPTIONS.get(optimizer)
        out = []
        for table, kind in OPTIMIZER_TABLES.items():
            if table == mine:
                continue
            given, default = getattr(self, table), kind()
            owners = " / ".join(repr(o) for o, t in OPTIMIZER_OPTIONS.items() if t == table)
            out += [(f"{table}.{name}", getattr(given, name), owners)
                    for name in kind.model_fields if getattr(given, name) != getattr(default,
                                                                                      name)]
        return out

    def check_optimizer(self, optimizer, why=None, explicit=False, stacklevel=3):
        """These options for a run of `optimizer`, with every other optimizer's table at its
        defaults. An option of such a table that differs from its default is not used: a
        SettingWarning names it, the optimizer it belongs to and the one run (`why`: the
        optimizer and why it runs, e.g. "sqp (auto: 3 design variables ...)"), or a
        ModelError saying the same when `explicit` (the caller named the optimizer and gave
        these options)."""
        unused = self.unused(optimizer)
        if not unused:
            return self
        items = "; ".join(f"option {name} = {value!r} belongs to optimizer {owners}"
                          for name, value, owners in unused)
        runs = why or repr(optimizer)
        if explicit:
            raise ModelError(f"{items}, but the run uses {runs}; leave it out or choose that "
                             f"optimizer")
        import warnings
        warnings.warn(f"{items}, but the run uses {runs}: not used", SettingWarning,
                      stacklevel=stacklevel)
        mine = OPTIMIZER_OPTIONS.get(optimizer)
        return self.model_copy(update={t: kind() for t, kind in OPTIMIZER_TABLES.items()
                                       if t != mine})

    def record(self, optimizer):
        """The options a run of `optimizer` used, as plain data: the method's and the
        optimizer's table (under its name)."""
        out = {k: v for k, v in self.as_dict().items() if k not in OPTIMIZER_TABLES}
        table = OPTIMIZER_OPTIONS.get(optimizer)
        if table is not None:
            out[table] = getattr(self, table).as_dict()
        return out


class WeaklyOptions(_Options):
    """The weakly coupled method (flexmbs.methods.weakly.optimize_weakly; paper 5.3).

    ===================  ========  ==============================================================
    option               default   meaning
    ===================  ========  ==============================================================
    eps                  1e-2      tolerance of the relative ESL change, eq. (25)
    max_cycles           30        cycles (MBS analyses) at most
    confirm_cycles       1         eq. (25) must hold in 1 + confirm_cycles consecutive cycles
                                   (0: the paper's test)
    move_limit           None      relative move limit per cycle (None: none)
    frames               None      {beam: point}: a beam's frame point (default: where the
                                   chains enter it)
    frame_kind           'auto'    corotational frame of the ESL beams: 'auto', 'tangent',
                                   'chord', or {beam: kind}
    screen               0.3       the static problem starts with the rows of at least screen
                                   times their constraint's maximum (0: all rows), in [0, 1]
    ftol                 1e-8      SLSQP's tolerance in the static problem
    max_inner            200       SLSQP iterations per static problem at most
    active_tol           1e-3      a row is active when g >= -active_tol
    stop_on_oscillation  True      stop when the designs repeat (2 to 6 cycles; with shrink > 0
                                   go on with shrinking move limits) or the ESL change grows
                                   cycle after cycle
    damping              1.0       damped update x + damping (x* - x), in (0, 1]
    esl_blend            0.0       the static problem on (1 - b) ESL_k + b ESL_(k-1), in [0, 1)
    design_tol           None      also converged when the design changes by less than this
                                   (relative) with the design feasible
    shrink               0.5       on an oscillation, go on with move limits that shrink by
                                   this factor where a variable reverses (0: stop), in [0, 1)
    verify               True      verify the final design at converged resolution (as
                                   FullyOptions.verify)
    ===================  ========  ==============================================================
    """
    eps: Pos = 1e-2
    max_cycles: Count = 30
    confirm_cycles: Whole = 1
    move_limit: Pos | None = None
    frames: dict[str, str] | None = None
    frame_kind: FrameKind | dict[str, FrameKind] = "auto"
    screen: Fraction = 0.3
    ftol: Pos = 1e-8
    max_inner: Count = 200
    active_tol: Pos = 1e-3
    stop_on_oscillation: bool = True
    damping: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1.0
    esl_blend: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.0
    design_tol: Pos | None = None
    shrink: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = 0.5
    verify: Annotated[Verify, BeforeValidator(_verify_field)] = True


class MultistartOptions(_Options):
    """The multi-start (flexmbs.methods.multistart.multistart).

    ===============  ===========  ===============================================================
    option           default      meaning
    ===============  ===========  ===============================================================
    starts           8            starting designs
    optimizer        'nlopt-mma'  the optimizer of every start (flexmbs.methods.fully.OPTIMIZERS)
    sampler          'sobol'      quasi-random sampler of the starts: 'sobol' or 'lhs'
    seed             0            the sampler's seed (the same seed gives the same starts)
    start_range      None         [lower, upper] designs the starts are drawn from (default:
                                  the bounds)
    candidates       None         draw this many designs (>= starts), simulate each once and
                                  start from the best `starts` of them
    best_tolerance   0.003        a start reached the best when feasible within this relative
                                  objective of it
    feasibility_tol  1e-6         largest re-checked violation of a feasible design
    verify           True         verify the best design at converged resolution (as
                                  FullyOptions.verify)
    ===============  ===========  ===============================================================
    """
    starts: Count = 8
    optimizer: Literal["auto", "mma", "sqp", "slsqp", "nlopt-mma", "nlopt-ccsaq",
                       "nlopt-slsqp"] = "nlopt-mma"
    sampler: Literal["sobol", "lhs"] = "sobol"
    seed: Whole = 0
    start_range: Annotated[list[Annotated[list[Finite], Field(min_length=1)]],
                           BeforeValidator(_plain), Field(min_length=2, max_length=2)] | None = None
    candidates: Count | None = None
    best_tolerance: Pos = 0.003
    feasibility_tol: Pos = 1e-6
    verify: Annotated[Verify, BeforeValidator(_verify_field)] = True

    @field_validator("start_range", mode="before")
    @classmethod
    def _range(cls, v):
        v = _plain(v)
        if isinstance(v, tuple):
            v = [list(_plain(x)) if isinstance(_plain(x), (list, tuple)) else _plain(x)
                 for x in v]
        return v

    @field_validator("start_range")
    @classmethod
    def _range_sizes(cls, v):
        if v is not None and len(v[0]) != len(v[1]):
            raise ValueError(f"the lower and the upper design must have as many values (one "
                             f"per design variable), got {len(v[0])} and {len(v[1])}")
        return v


class OptimizeSection(FullyOptions):
    """A case file's ``[optimize]`` table (docs/case-format.md): the method and optimizer that
    `flexmbs optimize` and the Problem-level entry points run when not told otherwise, the
    fully coupled method's options (FullyOptions' fields, its optimizers' tables ``sqp``,
    ``mma``, ``slsqp``, ``nlopt``), and the tables ``weakly`` (WeaklyOptions) and
    ``multistart`` (MultistartOptions).

    ==========  ====================  =============================================================
    option      default               meaning
    ==========  ====================  =============================================================
    method      'weakly'              the method of `flexmbs optimize`: 'weakly' or 'fully'
    optimizer   'auto'                the fully coupled method's optimizer ('auto' or one of
                                      flexmbs.methods.fully.OPTIMIZERS)
    weakly      WeaklyOptions()       the weakly coupled method's options
    multistart  MultistartOptions()   the multi-start's options
    ==========  ====================  =============================================================
    """
    method: Literal["weakly", "fully"] = "weakly"
    optimizer: Literal["auto", "mma", "sqp", "slsqp", "nlopt-mma", "nlopt-ccsaq",
                       "nlopt-slsqp"] = "auto"
    weakly: WeaklyOptions = WeaklyOptions()
    multistart: MultistartOptions = MultistartOptions()

    def fully(self):
        """The FullyOptions of the table."""
        return FullyOptions(**{k: getattr(self, k) for k in FullyOptions.model_fields})


def _message(exc, kind, where):
    """One line per error of a pydantic ValidationError: 'WHERE: option a.b = value: what'."""
    lines, seen = [], set()
    for e in exc.errors():
        # the members of a union (e.g. "literal[...]") are not options: left out of the name
        loc = ".".join(str(p) for p in e["loc"] if isinstance(p, int) or p.isidentifier())
        if loc in seen:
            continue
        seen.add(loc)
        if e["type"] == "extra_forbidden":
            owner = _owner(kind, e["loc"])
            allowed = ", ".join(owner.model_fields) if owner is not None else "?"
            lines.append(f"{where}: unknown option {loc!r}; allowed: {allowed}")
        else:
            msg = e["msg"].removeprefix("Value error, ")
            lines.append(f"{where}: option {loc} = {e.get('input')!r}: {msg}")
    return "; ".join(dict.fromkeys(lines))


def _owner(kind, loc):
    """The options class that holds the last key of `loc`."""
    for p in loc[:-1]:
        f = kind.model_fields.get(p) if isinstance(p, str) else None
        if f is None or not isinstance(f.annotation, type) or not issubclass(f.annotation,
                                                                               _Options):
            return kind
        kind = f.annotation
    return kind


def build(kind, data, where="options"):
    """An options object of class `kind` from None (the defaults), an object of that class,
    or a dict of its fields (FullyOptions: an optimizer's options flat or in its table);
    ModelError naming the option, its value and what is allowed."""
    if data is None:
        return kind()
    if isinstance(data, kind):
        return data
    if isinstance(data, _Options):
        data = data.as_dict() if not isinstance(data, FullyOptions) else {
            k: getattr(data, k) for k in data.model_fields}
    if not isinstance(data, dict):
        raise ModelError(f"{where} must be a {kind.__name__} or a dict of its options, got "
                         f"{data!r}")
    data = {k: _plain(v) for k, v in data.items()}
    if issubclass(kind, FullyOptions):
        data = kind.routed(data, where)
    try:
        return kind(**data)
    except ValidationError as exc:
        raise ModelError(_message(exc, kind, where)) from None
    except TypeError as exc:
        raise ModelError(f"{where}: {exc}") from None


def from_keywords(function, kind, options, keywords, tables=None, stacklevel=3):
    """The options of a call that gave its options as keywords (the spelling before the
    options objects): a DeprecationWarning naming the new spelling, and the dict of options.

    tables: {old keyword: table name}, for the old keywords that held one table as a dict
    (optimize_fully's mma_options, nlopt_options). A keyword that is no option of `kind` (nor
    of one of its tables) is a TypeError, as for any unknown keyword. stacklevel: the
    warning's, pointing at the caller of the public function."""
    import warnings

    tables = tables or {}
    known = set(kind.model_fields) | set(tables)
    if issubclass(kind, FullyOptions):
        for t in OPTIMIZER_TABLES.values():
            known |= set(t.model_fields)
    bad = [k for k in keywords if k not in known]
    if bad:
        raise TypeError(f"{function}() got an unexpected keyword argument {bad[0]!r}")
    if options is not None:
        raise ModelError(f"{function}: give the options either in options= or, deprecated, as "
                         f"keywords ({', '.join(keywords)}), not both")
    data = {}
    for k, v in keywords.items():
        if k in tables:
            if v is not None and not isinstance(v, dict):
                raise ModelError(f"{k} must be a dict or None, got {v!r}")
            data[tables[k]] = dict(v or {})
        else:
            data[k] = v
    new = ", ".join(f"{tables.get(k, k)}=..." for k in keywords)
    warnings.warn(f"{function}({', '.join(f'{k}=...' for k in keywords)}) is deprecated: give "
                  f"options={kind.__name__}({new}) (or the same as a dict)",
                  DeprecationWarning, stacklevel=stacklevel)
    return data


def doc_rows(kind):
    """[(option, default, meaning)] of the table in an options class's docstring (its
    continuation lines joined)."""
    import inspect
    lines = inspect.cleandoc(kind.__doc__).splitlines()
    rules = [k for k, line in enumerate(lines) if line.startswith("=") and set(line) <= {"=", " "}]
    rule = lines[rules[0]]
    starts = [k for k, ch in enumerate(rule) if ch == "=" and (k == 0 or rule[k - 1] == " ")]
    rows = []
    for line in lines[rules[1] + 1:rules[2]]:
        cells = [line[a:b].strip() for a, b in zip(starts, starts[1:] + [None])]
        if cells[0]:
            rows.append(cells)
        else:
            rows[-1][-1] += " " + " ".join(c for c in cells[1:] if c)
    return [tuple(r) for r in rows]


def markdown_table(kind):
    """The table of an options class's docstring as a markdown table (docs/optimizers.md)."""
    out = ["| option | default | meaning |", "|---|---|---|"]
    for name, default, meaning in doc_rows(kind):
        out.append(f"| `{name}` | `{default}` | {meaning} |")
    return "\n".join(out)
