"""``flexmbs optimize CASE --method weakly|fully``: the optimization subcommand.

Usage::

    flexmbs optimize CASE [--method weakly|fully] [--start X1,...] [--t-end T]
                          [--set KEY=VALUE ...] [--json] [--history FILE [--resume]]
                          [--progress | --no-progress] [--plot FILE.png]
        weakly: [--eps E] [--max-cycles N] [--confirm-cycles N] [--move-limit F]
                [--damping W] [--esl-blend B] [--design-tol TOL] [--shrink S]
                [--frame auto|tangent|chord|BEAM=KIND,...]
        fully:  [--optimizer mma|sqp|slsqp|nlopt-mma|nlopt-ccsaq|nlopt-slsqp] [--kkt-tol TOL]
                [--max-iterations N] [--design-rel-change TOL]
                [--starts N [--candidates M] [--sampler sobol|lhs] [--seed S]
                 [--workers N | --dask ADDRESS] [--store FOLDER]]

CASE is the name of a shipped case or a case file (docs/case-format.md); it is optimized on
its own objective and constraints (flexmbs.optimize.optimize_weakly / optimize_fully). The
method, the optimizer and every option not given on the command line come from the case's
``[optimize]`` table (flexmbs.model.options; e.g. ``--set optimize.max_iterations=50``,
``--set optimize.sqp.trust_radius=0.1``), else from the options' defaults.

Methods are looked up in `METHODS` (name -> "module:function", the function takes the parsed
arguments and the Problem and returns an OptimizationResult); method-specific options are
added by the functions listed in `METHOD_OPTIONS` ("module:function", called with the parser).
This module is the command line's: the optimizers never import it.

Progress: a tqdm bar on stderr (iteration or cycle, simulations, mass, constraint violation;
with --starts: starts done, best feasible objective), on by default when stderr is a terminal
(--progress / --no-progress).

Summary and JSON: the verdicts of docs/json-output.md ("What `optimize` reports"); after a
verified optimum, the step it was verified on and the command that simulates it there
(`check_command`: ``flexmbs simulate CASE --design=... --set time.h=H``).

Exit status: 0 when the method converged (with --starts: the best start's run), 1 when it
stopped without converging (maximum number of cycles, oscillation; with --starts, also when no
start ended feasible), 2 on bad input or a failed simulation, 130 when stopped by
Ctrl-C (one line on stderr names the history file, says that the same command with --resume
continues the run, and gives the --start of its last design analysed).
"""
from __future__ import annotations

import argparse
import functools
import importlib
import os
import shlex
import sys

from flexmbs.batch import check_dask
from flexmbs.cli.common import (add_case_arguments, announce_run, check_set_conflicts,
                                design_from_text, figure_file, nonnegative_int, output_file,
                                path_text, print_json, problem_from_args)
from flexmbs.errors import CaseError, ModelError
from flexmbs.methods.fully import choose_optimizer, optimize_fully, OPTIMIZERS
from flexmbs.methods.multistart import multistart
from flexmbs.methods.result import HistoryWriter
from flexmbs.methods.verified import objective_unit
from flexmbs.methods.weakly import optimize_weakly
from flexmbs.model.options import (build, FullyOptions, MultistartOptions, OptimizeSection,
                                   WeaklyOptions)
from flexmbs.optimizers.library import preload
from flexmbs.progress import Bar, describe_cycle, describe_iteration

__all__ = ["register", "run_optimize", "check_command", "run_weakly", "add_weakly_options", "run_fully",
           "add_fully_options", "METHODS", "METHOD_OPTIONS"]

#: Optimization methods: name -> "module:function(args, problem) -> OptimizationResult".
METHODS = {"weakly": "flexmbs.cli.optimize:run_weakly",
           "fully": "flexmbs.cli.optimize:run_fully"}

#: Functions adding method-specific options to the parser, "module:function(parser)".
METHOD_OPTIONS = ["flexmbs.cli.optimize:add_weakly_options",
                  "flexmbs.cli.optimize:add_fully_options"]


def _load(spec):
    module, _, func = spec.partition(":")
    return getattr(importlib.import_module(module), func)


def register(subparsers):
    """Add the ``optimize`` subcommand."""
    p = subparsers.add_parser(
        "optimize", help="minimize a case's objective under its constraints",
        description="Minimize the objective of a case subject to its constraints, with the "
                    "weakly coupled method (equivalent static loads in cycles, paper 5.3) or "
                    "the fully coupled one (optimization on the time responses with exact "
                    "sensitivities, paper 5.4).")
    add_case_arguments(p)
    p.add_argument("--method", choices=sorted(METHODS), default=None,
                   help="optimization method (default: the case's [optimize] method, else "
                        "weakly)")
    p.add_argument("--start", metavar="X1,X2,...",
                   help="starting design in the variables' units (one value: all variables); "
                        "default: the case's")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (the result) instead of the progress and summary")
    p.add_argument("--history", type=path_text, metavar="FILE",
                   help="write one JSON line per cycle/iteration to FILE as the run goes (a "
                        "FILE holding an earlier run's history is refused without --resume; "
                        "FILE is locked while the run writes it)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its --history FILE (with --starts: "
                        "from its --store FOLDER): it follows the recorded path without "
                        "simulating and ends at the same optimum; a missing FILE starts afresh")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="show a progress bar on stderr (default: when stderr is a terminal)")
    p.add_argument("--plot", type=path_text, metavar="FILE.png",
                   help="save the objective history and the final design's deviation history")
    p.add_argument("--verify-rtol", type=float, default=None, metavar="R",
                   help="verify the final design at the step (h/2, h/4, ...) that resolves "
                        "its objective and constraints to R (relative to the limits; default "
                        "1e-3, or the case's [optimize] verify); when infeasible there, the "
                        "optimization continues at that step from the design")
    p.add_argument("--no-verify", dest="verify", action="store_false",
                   help="leave the final design unverified (its values at the case's h only)")
    for spec in METHOD_OPTIONS:
        _load(spec)(p)
    p.set_defaults(func=run_optimize)


def add_weakly_options(p):
    g = p.add_argument_group("weakly coupled method")
    g.add_argument("--eps", type=float, default=None, metavar="E",
                   help="tolerance of the relative ESL change, eq. (25), default 1e-2")
    g.add_argument("--max-cycles", type=int, default=None, metavar="N",
                   help="maximum number of cycles (MBS analyses), default 30")
    g.add_argument("--confirm-cycles", type=int, default=None, metavar="N",
                   help="eq. (25) must also hold in N more cycles (0: the paper's test), default 1")
    g.add_argument("--move-limit", type=float, default=None, metavar="F",
                   help="relative move limit of the design per cycle (e.g. 0.1); default none")
    g.add_argument("--damping", type=float, default=None, metavar="W",
                   help="damped design update x + W (x* - x), 0 < W <= 1; default 1 (the paper)")
    g.add_argument("--esl-blend", type=float, default=None, metavar="B",
                   help="static problem on (1-B) ESL of this cycle + B ESL of the previous one; "
                        "default 0 (the paper)")
    g.add_argument("--design-tol", type=float, default=None, metavar="TOL",
                   help="also converged when the design changes by less than TOL (relative) "
                        "between cycles with the design feasible; default none")
    g.add_argument("--shrink", type=float, default=None, metavar="S",
                   help="on an oscillation, go on with per-variable move limits that shrink by "
                        "S where a variable reverses direction; 0: stop on the oscillation "
                        "(the paper's cycles); default 0.5")
    g.add_argument("--frame", default=None, metavar="KIND|BEAM=KIND,...",
                   help="corotational frame of the beams: auto (default: from each beam's "
                        "joints, tangent where its rotation is held, chord between free "
                        "hinges), tangent (the paper's) or chord; or per beam, e.g. "
                        "follower=chord (others auto)")


def _frame_option(text):
    """--frame: 'auto', 'tangent', 'chord' or 'BEAM=KIND,...' -> optimize_weakly's frame_kind."""
    if text is None or "=" not in text:
        return text
    kinds = {}
    for item in text.split(","):
        name, sep, kind = item.partition("=")
        if not sep or not name.strip():
            raise ModelError(f"--frame: {item!r} is not BEAM=KIND (e.g. follower=chord)")
        kinds[name.strip()] = kind.strip()
    return kinds


def run_weakly(args, problem):

    opts = _options(WeaklyOptions, _section(problem).weakly, args, dict(
        eps=args.eps, max_cycles=args.max_cycles, confirm_cycles=args.confirm_cycles,
        move_limit=args.move_limit, damping=args.damping, esl_blend=args.esl_blend,
        design_tol=args.design_tol, shrink=args.shrink, frame_kind=_frame_option(args.frame)))
    line = functools.partial(_cycle_line, units=_units(problem))
    with _Reporter(args, opts.max_cycles, "cycles", describe_cycle, line) as report:
        return optimize_weakly(problem, design_from_text(args.start, problem, "--start"),
                               options=opts, history=args.history, progress=report,
                               resume=args.resume)


def _section(problem):
    """The case's [optimize] table (its defaults when the case has none)."""
    return getattr(problem.description, "optimize", None) or OptimizeSection()


def _options(kind, base, args, given):
    """The options of a run: the case's (`base`) with the command line's options that were
    given (not None) and its verification (--verify-rtol, --no-verify) over them."""
    table = {WeaklyOptions: "optimize.weakly.", MultistartOptions: "optimize.multistart."}
    # an option and a --set of the key it stands for with two values: an error (the frame,
    # parsed from its own syntax, is left out)
    check_set_conflicts(args, [("--" + k.replace("_", "-"), v, table.get(kind, "optimize.") + k)
                               for k, v in given.items() if k != "frame_kind"])
    data = base.as_dict() if not isinstance(base, FullyOptions) else {
        k: getattr(base, k) for k in FullyOptions.model_fields}
    data.update({k: v for k, v in given.items() if v is not None})
    if not args.verify:
        data["verify"] = False
    elif args.verify_rtol is not None:
        data["verify"] = args.verify_rtol
    return build(kind, data, "the command line's options")


class _Reporter:
    """The command line's progress: one line per record on stdout (not with --json) and, with
    --progress, a tqdm bar on stderr (lines are printed through it so that the two do not
    mix)."""

    def __init__(self, args, total, label, describe, line):
        self.line = None if args.json else line
        self.bar = (Bar(total, label, sys.stderr, describe, lambda r: r["iteration"])
                    if args.progress else None)

    def __call__(self, rec):
        if self.line is not None:
            if self.bar is not None:
                self.bar.write(self.line(rec), file=sys.stdout)
            else:
                print(self.line(rec), flush=True)
        if self.bar is not None:
            self.bar(rec)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.close()


#: a progress line lists the design when it has at most this many variables, else its range
LINE_VARIABLES = 8


def _design_text(design, units=None):
    """The design for a progress line: every value up to LINE_VARIABLES, else the count and
    the range (a line per iteration with 128 numbers is read by nobody); followed by the
    variables' unit when they share one."""
    d = [float(v) for v in design]
    shared = sorted(set(units or []))
    unit = f" {shared[0]}" if len(shared) == 1 and shared[0] else ""
    if len(d) <= LINE_VARIABLES:
        return "[" + ", ".join(f"{v:.4g}" for v in d) + "]" + unit
    return f"({len(d)} values in [{min(d):.4g}, {max(d):.4g}]{unit})"


def _units(problem):
    """(the design variables' units, the objective's unit or '') of `problem`."""
    return list(getattr(problem.mechanism, "units", [])), objective_unit(problem) or ""


def _cycle_line(rec, units=((), "")):
    p = _design_text(rec["design"], units[0])
    ou = f" {units[1]}" if units[1] else ""
    ch = rec.get("esl_change")
    chg = "-" if ch is None else f"{ch:.3g}"
    inner = rec.get("inner_iterations")
    viol = rec.get("max_violation")
    return (f"cycle {rec['iteration']:3d}  x = {p}  objective {rec['objective']:.6g}{ou}  "
            + ("" if viol is None else f"max g {viol:+.2e}  ")
            + f"ESL change {chg}" + ("" if inner is None else f"  inner {inner}"))


def _interrupted(args, writer):
    """The one line printed on Ctrl-C: what is kept and how to resume."""
    recs = writer.records
    where = (f"history of {len(recs)} record(s) in {writer.path}" if writer.path
             else "no history file (--history FILE keeps one and makes a run resumable)")
    last = recs[-1].get("design") if recs else None
    if writer.path and recs:
        p = ",".join(f"{v:.6g}" for v in last)
        how = ("to continue the run where it stopped, run the same command with --resume "
               f"(or start a new run from the last design analysed with --start={p} and a "
               "new --history name)")
    elif last is not None:
        p = ",".join(f"{v:.6g}" for v in last)
        how = f"to resume from the last design analysed, run the same command with --start={p}"
    else:
        how = "no design analysed yet: run the same command again"
    print(f"flexmbs optimize: interrupted; {where}; {how}", file=sys.stderr, flush=True)


def run_optimize(args):
    preload()      # a Ctrl-C mid-run must not land in a first import (library.preload)
    problem = problem_from_args(args, gradient_method="auto")
    if args.method is None:
        args.method = _section(problem).method
    if getattr(args, "starts", None) is not None and args.method != "fully":
        raise CaseError(f"--starts {args.starts}: multi-start runs the fully coupled method; "
                        f"add --method fully (got --method {args.method})")
    run = _load(METHODS[args.method])
    if args.progress is None:
        args.progress = sys.stderr.isatty()
    if args.resume and not args.history and getattr(args, "starts", None) is None:
        raise CaseError("--resume continues the run recorded in --history FILE: give the "
                        "--history of the interrupted run")
    # output paths are checked before the run, not after it
    history_path = args.history
    if history_path:
        history_path = output_file(history_path, "--history")
        if not args.resume and os.path.isfile(history_path) and \
                os.path.getsize(history_path) > 0:
            raise CaseError(f"--history {history_path!r} holds the history of an earlier run "
                            "and would be overwritten: add --resume to continue that run, or "
                            "give another --history name (or delete the file)")
    if args.plot:
        args.plot = figure_file(args.plot, "--plot")
    announce_run(problem, "optimize", choose=False)
    writer = HistoryWriter(history_path, resume=args.resume and bool(history_path))
    args.history = writer           # the methods accept a HistoryWriter for `history`
    try:
        result = run(args, problem)
    except KeyboardInterrupt:
        writer.close()
        _interrupted(args, writer)
        return 130
    finally:
        writer.close()
        args.history = history_path
    if args.plot:
        result.plot(args.plot, limit_m=problem.deviation_limit())
    check = check_command(args, problem, result)
    if args.json:
        out = result.to_dict()
        out["check_command"] = check
        if args.history:
            out["history_file"] = args.history
        if args.plot:
            out["plot"] = args.plot
        print_json(out)
    else:
        print(result.summary())
        pred = result.details.get("predicted_max_violation")
        if pred is not None:
            print(f"  largest g predicted by the last static problem {pred:+.3e}")
        if check:
            h = _verified_step(result)
            print(f"  re-check at the verified step h = {h:.4g} s:")
            print(f"    {check}")
        for what, f in (("history", args.history), ("figure", args.plot)):
            if f:
                print(f"  {what:<8s} {f}")
    sys.stdout.flush()
    return 0 if result.converged else 1


def _verified_step(result):
    """The step (s) the result's design was verified on, None when it was not."""
    rec = result.best if hasattr(result, "best") else result.details
    v = (rec or {}).get("verification")
    return None if not v else float(v["h"])


def check_command(args, problem, result):
    """The command that simulates the result's design at its verified step
    (``flexmbs simulate CASE --design=... --set time.h=H`` with the run's other overrides), or
    None: not verified, or an adaptive case (its verification subdivides the frozen grid,
    which a fixed step does not reproduce)."""
    h = _verified_step(result)
    design = getattr(result, "design", None)
    if h is None or design is None or problem.description.time.adaptive:
        return None
    words = ["flexmbs", "simulate", args.case,
             "--design=" + ",".join(repr(float(v)) for v in design)]
    for item in args.set:
        if item.partition("=")[0].strip() != "time.h":
            words += ["--set", item]
    for option, value in (("--t-end", args.t_end), ("--rho-inf", args.rho_inf)):
        if value is not None:
            words += [option, repr(value)]
    words += ["--set", f"time.h={h!r}"]
    return " ".join(shlex.quote(w) for w in words)


# ----------------------------------------------------------------------------- fully coupled
def add_fully_options(parser):
    """Options of ``flexmbs optimize CASE --method fully``."""
    g = parser.add_argument_group("fully coupled method")
    g.add_argument("--optimizer", choices=("auto",) + OPTIMIZERS, default=None,
                   help="default: the case's [optimize] optimizer (with --starts: its "
                        "[optimize.multistart] optimizer), else auto (with --starts: "
                        "nlopt-mma); auto: sqp below 32 design "
                        "variables, mma from 32; sqp: trust-region SQP; "
                        "nlopt-ccsaq, nlopt-mma, nlopt-slsqp: NLopt's; mma: Svanberg's "
                        "globally convergent MMA, hand-written (the paper's; `flexmbs "
                        "reproduce` uses it); slsqp: plain scipy SLSQP (no move limits, fails "
                        "from some starts). docs/optimizers.md compares them")
    g.add_argument("--kkt-tol", type=float, default=None, metavar="TOL",
                   help="first-order test added to the paper's stopping test, default 1e-3")
    g.add_argument("--max-iterations", type=int, default=None, metavar="N",
                   help="maximum optimizer iterations, default 100")
    g.add_argument("--design-rel-change", type=float, default=None, metavar="TOL",
                   help="also require the relative design change below TOL to stop (the "
                        "paper's four-bar: 1e-3); default: not required")
    m = parser.add_argument_group("multi-start (--method fully)")
    m.add_argument("--starts", type=int, default=None, metavar="N",
                   help="run the fully coupled method from N quasi-random starting designs "
                        "(log-scaled where the bounds span a decade) and report the best "
                        "feasible design, re-simulated, and the spread of the local optima")
    m.add_argument("--sampler", choices=("sobol", "lhs"), default=None,
                   help="sampler of the starts: scrambled Sobol (default) or Latin hypercube")
    m.add_argument("--candidates", type=int, default=None, metavar="M",
                   help="draw M >= N designs, simulate each once, and start from the N "
                        "feasible ones of lowest objective")
    m.add_argument("--seed", type=nonnegative_int, default=None, metavar="S",
                   help="seed of the sampler (default 0: the same starts every run)")
    m.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local worker processes for the starts (default: the number of cores)")
    m.add_argument("--dask", metavar="ADDRESS",
                   help="run the starts on a Dask scheduler (tcp://host:8786, or 'local')")
    m.add_argument("--store", type=path_text, metavar="FOLDER",
                   help="save each start's result as it finishes; a rerun skips those stored")


def run_fully(args, problem):
    """Handler of ``flexmbs optimize CASE --method fully``: returns an OptimizationResult."""

    section = _section(problem)
    if args.starts is not None:
        return _run_multistart(args, problem)

    optimizer = args.optimizer or section.optimizer
    opts = _used_tables(_fully_options(args, section), optimizer, problem)
    line = functools.partial(_iteration_line, units=_units(problem))
    with _Reporter(args, opts.max_iterations, "iterations", describe_iteration,
                   line) as report:
        return optimize_fully(problem, design_from_text(args.start, problem, "--start"),
                              optimizer=optimizer, options=opts,
                              history=args.history, progress=report, resume=args.resume)


def _fully_options(args, section):
    """The fully coupled method's options: the case's [optimize] table and the command line's."""
    return _options(FullyOptions, section.fully(), args, dict(
        kkt_tol=args.kkt_tol, max_iterations=args.max_iterations,
        design_rel_change=args.design_rel_change))


def _used_tables(opts, optimizer, problem):
    """The fully coupled method's options with the case's tables of another optimizer than
    the one run set aside (a SettingWarning naming them: the command line may choose another
    optimizer than the case's)."""
    chosen, why = choose_optimizer(optimizer, len(problem.variables))
    return opts.check_optimizer(chosen, why)


def _iteration_line(rec, units=((), "")):
    p = _design_text(rec["design"], units[0])
    ou = f" {units[1]}" if units[1] else ""
    return (f"iteration {rec['iteration']:3d}  x = {p}  objective {rec['objective']:.6g}{ou}  "
            f"violation {rec['max_violation']:.1e}  KKT {rec['kkt_residual']:.1e}  "
            f"simulations {rec['simulations']}")


def _run_multistart(args, problem):
    """``flexmbs optimize CASE --method fully --starts N``."""

    if args.start is not None:
        raise CaseError("--starts draws the starting designs; leave --start out")
    if args.starts < 1:
        raise CaseError(f"--starts must be a positive integer, got {args.starts}")
    if args.history.path is not None:
        raise CaseError("--history is written by one run; with --starts give --store FOLDER "
                        "(one result file per start)")
    check_dask(args.dask, "--dask")
    if args.resume and args.store is None:
        raise CaseError("--resume with --starts continues from the --store FOLDER of the "
                        "interrupted run: give --store")
    section = _section(problem)
    ms = _options(MultistartOptions, section.multistart, args, dict(
        starts=args.starts, optimizer=args.optimizer, sampler=args.sampler, seed=args.seed,
        candidates=args.candidates))
    fully = _used_tables(_fully_options(args, section), ms.optimizer, problem)
    return multistart(problem, options=ms, fully=fully, workers=args.workers, dask=args.dask,
                      store=args.store, progress=bool(args.progress), resume=args.resume)
