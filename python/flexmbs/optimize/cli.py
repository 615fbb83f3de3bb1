"""``flexmbs optimize CASE --method weakly|...``: the optimization subcommand.

Usage::

    flexmbs optimize CASE --method weakly [--start P1,...] [--t-end T] [--set KEY=VALUE ...]
                          [--eps E] [--max-cycles N] [--confirm-cycles N] [--move-limit F]
                          [--frame tangent|chord] [--json] [--history FILE] [--plot FILE.png]

CASE is a case of the paper's format (optimized by the registered methods) or a general-format
case (docs/case-format.md: a .toml file with [[bodies]], or a name found only in cases/general,
e.g. slider_crank_press), optimized with ``--method fully`` on its own objective and constraints
(flexmbs.optimize.problem_fully; --t-end, --h, --rho-inf and --set time.h=... override its
[time] table and other keys).

Methods are looked up in `METHODS` (name -> "module:function", the function takes the parsed
arguments and the Case and returns an OptimizationResult); method-specific options are added
by the functions listed in `METHOD_OPTIONS` ("module:function", called with the parser). The
fully coupled method registers itself by adding its entries to both.

Exit status: 0 when the method converged, 1 when it stopped without converging (maximum
number of cycles, oscillation), 2 on bad input or a failed simulation, 130 when stopped by
Ctrl-C (one line on stderr names the history file and the --start that resumes from the last
design analysed).
"""
from __future__ import annotations

import importlib
import sys
import tomllib
from pathlib import Path

from flexmbs.cli import (add_case_arguments, case_from_args, figure_file, output_file,
                         parse_design, parse_set, print_json)
from flexmbs.errors import CaseError
from flexmbs.optimize.fully import (AGGREGATIONS, CONSTRAINT_FORMS, OPTIMIZERS,
                                    optimize_fully)
from flexmbs.optimize.problem_fully import OPTIMIZERS as GENERAL_OPTIMIZERS
from flexmbs.optimize.result import HistoryWriter

__all__ = ["register", "run_optimize", "run_weakly", "add_weakly_options", "start_from_args",
           "general_problem", "run_general", "METHODS", "METHOD_OPTIONS", "run_fully",
           "add_fully_options"]

#: Optimization methods: name -> "module:function(args, case) -> OptimizationResult".
METHODS = {"weakly": "flexmbs.optimize.cli:run_weakly",
           "fully": "flexmbs.optimize.cli:run_fully"}

#: Functions adding method-specific options to the parser, "module:function(parser)".
METHOD_OPTIONS = ["flexmbs.optimize.cli:add_weakly_options",
                  "flexmbs.optimize.cli:add_fully_options"]


def _load(spec):
    module, _, func = spec.partition(":")
    return getattr(importlib.import_module(module), func)


def register(subparsers):
    """Add the ``optimize`` subcommand."""
    p = subparsers.add_parser(
        "optimize", help="minimize the beam mass of a case under its deviation limit",
        description="Minimize the beam mass of a case subject to its deviation limit at every "
                    "time step, with the weakly coupled method (equivalent static loads in "
                    "cycles, paper 5.3) or another registered method. A general-format case "
                    "(docs/case-format.md) is optimized on its own objective and constraints "
                    "with --method fully.")
    add_case_arguments(p)
    p.add_argument("--method", choices=sorted(METHODS), default="weakly",
                   help="optimization method (default: weakly)")
    p.add_argument("--start", metavar="P1,P2,...",
                   help="starting design in mm (one value: all variables); default: the case's")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (the result) instead of the progress and summary")
    p.add_argument("--history", metavar="FILE",
                   help="write one JSON line per cycle/iteration to FILE as the run goes")
    p.add_argument("--plot", metavar="FILE.png",
                   help="save the objective history and the final design's deviation history")
    for spec in METHOD_OPTIONS:
        _load(spec)(p)
    p.set_defaults(func=run_optimize)


def add_weakly_options(p):
    g = p.add_argument_group("weakly coupled method")
    g.add_argument("--eps", type=float, default=None, metavar="E",
                   help="tolerance of the relative ESL change, eq. (25); default: the case "
                        "file's optimizer.weakly.esl_rel_change, else 1e-2")
    g.add_argument("--max-cycles", type=int, default=30, metavar="N",
                   help="maximum number of cycles (MBS analyses), default 30")
    g.add_argument("--confirm-cycles", type=int, default=1, metavar="N",
                   help="eq. (25) must also hold in N more cycles (0: the paper's test), default 1")
    g.add_argument("--move-limit", type=float, default=None, metavar="F",
                   help="relative move limit of the design per cycle (e.g. 0.1); default none")
    g.add_argument("--frame", choices=("tangent", "chord"), default="tangent",
                   help="corotational frame of the bodies (default: tangent, as the paper)")


def start_from_args(args, case):
    """The --start design (mm), or the case's start."""
    try:
        return parse_design(args.start, case)
    except CaseError as exc:
        raise CaseError(str(exc).replace("--design", "--start")) from None


def run_weakly(args, case):
    from flexmbs.optimize.weakly import optimize_weakly

    eps = args.eps
    if eps is None:
        eps = case.optimizer.get("weakly", {}).get("esl_rel_change", 1e-2)
    progress = None if args.json else _print_cycle
    return optimize_weakly(case, start_from_args(args, case), eps=eps,
                           max_cycles=args.max_cycles, confirm_cycles=args.confirm_cycles,
                           move_limit=args.move_limit, frame=args.frame, history=args.history,
                           progress=progress)


def _print_cycle(rec):
    p = ", ".join(f"{v:.3f}" for v in rec["design_mm"])
    ch = rec.get("esl_change")
    chg = "-" if ch is None else f"{ch:.3g}"
    inner = rec.get("inner_iterations")
    print(f"cycle {rec['iteration']:3d}  p = [{p}] mm  mass {rec['mass_kg']:.4f} kg  "
          f"max deviation {rec['max_deviation_m'] * 1e3:.4f} mm  ESL change {chg}"
          + ("" if inner is None else f"  inner {inner}"), flush=True)


def _interrupted(args, writer):
    """The one line printed on Ctrl-C: what is kept and how to resume."""
    recs = writer.records
    where = (f"history of {len(recs)} record(s) in {writer.path}" if writer.path
             else "no history file (--history FILE keeps one)")
    last = recs[-1].get("design_mm", recs[-1].get("design")) if recs else None
    if last is not None:
        p = ",".join(f"{v:.6g}" for v in last)
        how = f"to resume from the last design analysed, run the same command with --start={p}"
        if writer.path:
            how += " and a new --history name (an existing history file is started afresh)"
    else:
        how = "no design analysed yet: run the same command again"
    print(f"flexmbs optimize: interrupted; {where}; {how}", file=sys.stderr, flush=True)


def _general_case_file(name):
    """The file of a general-format CASE (a .toml file with [[bodies]], or a name found only in
    cases/general, since the paper's names keep their meaning) and its parsed table; None for a
    case in the paper's format (or one load_case will report as missing or malformed)."""
    from flexmbs.casefile import is_general_format
    from flexmbs.cases import case_folders, case_path

    p = Path(name)
    f = p if p.is_file() else None
    if f is None:
        try:
            case_path(name)
            return None                                   # a paper case name
        except CaseError:
            pass
        stem = p.name[:-5] if p.name.endswith(".toml") else p.name
        if len(p.parts) == 1:
            f = next((folder / "general" / f"{stem}.toml" for folder in case_folders()
                      if (folder / "general" / f"{stem}.toml").is_file()), None)
        if f is None:
            return None
    try:
        data = tomllib.loads(f.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None                                       # load_case names the problem
    return (f, data) if is_general_format(data) else None


def general_problem(args, found):
    """The Problem of a general-format case, with --t-end, --h, --rho-inf (keys of [time]) and
    --set KEY=VALUE (a dotted path through the case's tables, e.g. time.h=2e-4) applied."""
    from flexmbs.casefile import description_from_dict
    from flexmbs.problem import Problem

    f, data = found
    overrides = parse_set(args.set)
    for key, value in (("t_end", args.t_end), ("h", args.h), ("rho_inf", args.rho_inf)):
        if value is not None:
            overrides[f"time.{key}"] = value
    for key, value in overrides.items():
        *path, leaf = key.split(".")
        table = data
        for k, part in enumerate(path):
            table = table.get(part) if isinstance(table, dict) else None
            if not isinstance(table, dict):
                raise CaseError(f"--set {key}={value!r}: {'.'.join(path[:k + 1])!r} is not a "
                                f"table of the general-format case {str(f)!r} (give a dotted "
                                f"path through its tables, e.g. time.h=2e-4)")
        table[leaf] = value
    return Problem(description_from_dict(data, str(f)))


def run_general(args, problem):
    """``flexmbs optimize CASE`` for a general-format case: the weakly coupled method
    (flexmbs.optimize.problem_weakly) or the fully coupled one (flexmbs.optimize.problem_fully)
    on its objective and constraints."""
    from flexmbs.optimize.problem_fully import optimize_problem
    from flexmbs.optimize.problem_weakly import optimize_problem_weakly

    from flexmbs.cli_evaluate import design_from_text
    start = None if args.start is None else design_from_text(args.start, problem, "--start")
    if getattr(args, "starts", None) is not None:
        return _run_multistart(args, problem, start)
    if args.method == "weakly":
        progress = None if args.json else _print_cycle
        return optimize_problem_weakly(
            problem, start, eps=1e-2 if args.eps is None else args.eps,
            max_cycles=args.max_cycles, confirm_cycles=args.confirm_cycles,
            move_limit=args.move_limit, frame_kind=args.frame, history=args.history,
            progress=progress)
    defaults = dict(sensitivity="direct", aggregation="none", aggregation_parameter=None,
                    windows=1, constraint_form="linear")
    for opt, default in defaults.items():
        if getattr(args, opt, default) != default:
            raise CaseError(f"--{opt.replace('_', '-')} {getattr(args, opt)}: a general-format "
                            f"case sets its constraints (aggregation, form) in its "
                            f"[[constraints]] tables and is always differentiated directly; "
                            f"leave this option out")
    progress = None if args.json else _print_general_iteration
    max_it = 100 if args.max_iterations is None else args.max_iterations
    return optimize_problem(problem, start, optimizer=args.optimizer or "mma",
                            kkt_tol=args.kkt_tol,
                            max_iterations=max_it, history=args.history, progress=progress)


def _run_multistart(args, problem, start):
    """``flexmbs optimize CASE --starts N``: the fully coupled method from N starts."""
    from flexmbs.optimize.multistart import multistart

    if args.method != "fully":
        raise CaseError(f"--starts {args.starts}: multi-start runs the fully coupled method; "
                        f"add --method fully (got --method {args.method})")
    if start is not None:
        raise CaseError("--starts draws the starting designs; leave --start out")
    if args.starts < 1:
        raise CaseError(f"--starts must be a positive integer, got {args.starts}")
    if args.history.path is not None:
        raise CaseError("--history is written by one run; with --starts give --store FOLDER "
                        "(one result file per start)")
    max_it = 100 if args.max_iterations is None else args.max_iterations
    return multistart(problem, args.starts, optimizer=args.optimizer or "nlopt-mma",
                      sampler=args.sampler, seed=args.seed, candidates=args.candidates,
                      workers=args.workers,
                      dask=args.dask, store=args.store, progress=False if args.json else None,
                      kkt_tol=args.kkt_tol, max_iterations=max_it)


def _print_general_iteration(rec):
    p = ", ".join(f"{v:.5g}" for v in rec["design"])
    print(f"iteration {rec['iteration']:3d}  x = [{p}]  objective {rec['objective']:.6g}  "
          f"violation {rec['max_violation']:.1e}  KKT {rec['kkt_residual']:.1e}  "
          f"simulations {rec['simulations']}", flush=True)


def run_optimize(args):
    found = _general_case_file(args.case)
    if found is not None:
        problem = general_problem(args, found)
        case = None
        run = run_general
    else:
        if getattr(args, "starts", None) is not None:
            raise CaseError(f"--starts: multi-start is for general-format cases "
                            f"(docs/case-format.md); {args.case!r} is a paper-format case")
        problem = None
        case = case_from_args(args)
        run = _load(METHODS[args.method])
    # output paths are checked before the run, not after it
    history_path = args.history
    if history_path:
        history_path = output_file(history_path, "--history")
    if args.plot:
        args.plot = figure_file(args.plot, "--plot")
    writer = HistoryWriter(history_path)
    args.history = writer           # the methods accept a HistoryWriter for `history`
    try:
        result = run(args, case if problem is None else problem)
    except KeyboardInterrupt:
        writer.close()
        _interrupted(args, writer)
        return 130
    finally:
        writer.close()
        args.history = history_path
    if args.plot:
        result.plot(args.plot, limit_m=None if case is None else case.limit_m)
    if args.json:
        out = result.to_dict()
        out["case_file"] = case.source if case is not None else str(found[0])
        if args.history:
            out["history_file"] = args.history
        if args.plot:
            out["plot"] = args.plot
        print_json(out)
    else:
        print(result.summary())
        pred = result.details.get("predicted_max_deviation_m")
        if pred is not None:
            print(f"  max deviation predicted by the last static problem {pred * 1e3:.4f} mm")
        for what, f in (("history", args.history), ("figure", args.plot)):
            if f:
                print(f"  {what:<8s} {f}")
    sys.stdout.flush()
    return 0 if result.converged else 1


# ----------------------------------------------------------------------------- fully coupled
def add_fully_options(parser):
    """Options of ``flexmbs optimize CASE --method fully``."""
    g = parser.add_argument_group("fully coupled method")
    g.add_argument("--sensitivity", choices=("direct", "fd"), default="direct",
                   help="design sensitivities: direct differentiation (default) or forward "
                        "finite differences (the paper's, relative step --fd-step)")
    g.add_argument("--fd-step", type=float, default=1e-6, metavar="S",
                   help="relative finite-difference step, default 1e-6")
    g.add_argument("--optimizer", choices=tuple(dict.fromkeys(OPTIMIZERS + GENERAL_OPTIMIZERS)),
                   default=None,
                   help="mma: Svanberg's globally convergent MMA (default; with --starts: "
                        "nlopt-mma, docs/optimizers.md); sqp: trust-region "
                        "SQP (paper-format cases); slsqp: plain scipy SLSQP (no move limits, "
                        "fails from some starts); nlopt-mma, nlopt-ccsaq, nlopt-slsqp: NLopt's "
                        "(general-format cases, docs/optimizers.md)")
    g.add_argument("--aggregation", choices=AGGREGATIONS, default="none",
                   help="none: one constraint per time step (the paper's, default); ks / pnorm: "
                        "aggregated constraints, eq. (22)")
    g.add_argument("--aggregation-parameter", type=float, default=None, metavar="R",
                   help="KS rho (default 100) or p-norm exponent (default 50)")
    g.add_argument("--windows", type=int, default=1, metavar="N",
                   help="aggregate over N consecutive time windows, default 1")
    g.add_argument("--constraint-form", choices=CONSTRAINT_FORMS, default="linear",
                   help="dl/limit - 1 <= 0 (default) or (dl/limit)^2 - 1 <= 0")
    g.add_argument("--kkt-tol", type=float, default=1e-3, metavar="TOL",
                   help="first-order test added to the paper's stopping test, default 1e-3")
    g.add_argument("--max-iterations", type=int, default=None, metavar="N",
                   help="maximum optimizer iterations; default: the case file's, else 100")
    m = parser.add_argument_group("multi-start (general-format cases, --method fully)")
    m.add_argument("--starts", type=int, default=None, metavar="N",
                   help="run the fully coupled method from N quasi-random starting designs "
                        "(log-scaled where the bounds span a decade) and report the best "
                        "feasible design, re-simulated, and the spread of the local optima")
    m.add_argument("--sampler", choices=("sobol", "lhs"), default="sobol",
                   help="sampler of the starts: scrambled Sobol (default) or Latin hypercube")
    m.add_argument("--candidates", type=int, default=None, metavar="M",
                   help="draw M >= N designs, simulate each once, and start from the N "
                        "feasible ones of lowest objective")
    m.add_argument("--seed", type=int, default=0, metavar="S",
                   help="seed of the sampler (default 0: the same starts every run)")
    m.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local worker processes for the starts (default: the number of cores)")
    m.add_argument("--dask", metavar="ADDRESS",
                   help="run the starts on a Dask scheduler (tcp://host:8786, or 'local')")
    m.add_argument("--store", metavar="FOLDER",
                   help="save each start's result as it finishes; a rerun skips those stored")


def run_fully(args, case):
    """Handler of ``flexmbs optimize CASE --method fully``: returns an OptimizationResult."""
    progress = None if args.json else _print_iteration
    return optimize_fully(case, start_from_args(args, case), sensitivity=args.sensitivity,
                          fd_step=args.fd_step, optimizer=args.optimizer or "mma",
                          aggregation=args.aggregation,
                          aggregation_parameter=args.aggregation_parameter,
                          windows=args.windows, constraint_form=args.constraint_form,
                          kkt_tol=args.kkt_tol, max_iterations=args.max_iterations,
                          history=args.history, progress=progress)


def _print_iteration(rec):
    p = ", ".join(f"{v:.3f}" for v in rec["design_mm"])
    active = next(iter(rec["active_steps"].values()), [])
    shown = ",".join(str(n) for n in active[:6]) + (",..." if len(active) > 6 else "")
    print(f"iteration {rec['iteration']:3d}  p = [{p}] mm  mass {rec['mass_kg']:.4f} kg  "
          f"max deviation {rec['max_deviation_m'] * 1e3:.4f} mm  KKT {rec['kkt_residual']:.1e}  "
          f"simulations {rec['simulations']}  active [{shown}]", flush=True)
