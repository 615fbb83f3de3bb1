"""``flexmbs optimize CASE --method weakly|...``: the optimization subcommand.

Usage::

    flexmbs optimize CASE --method weakly [--start P1,...] [--t-end T] [--set KEY=VALUE ...]
                          [--eps E] [--max-cycles N] [--confirm-cycles N] [--move-limit F]
                          [--frame tangent|chord] [--json] [--history FILE] [--plot FILE.png]

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

from flexmbs.cli import (add_case_arguments, case_from_args, figure_file, output_file,
                         parse_design, print_json)
from flexmbs.errors import CaseError
from flexmbs.optimize.result import HistoryWriter

__all__ = ["register", "run_optimize", "run_weakly", "add_weakly_options", "start_from_args",
           "METHODS", "METHOD_OPTIONS"]

#: Optimization methods: name -> "module:function(args, case) -> OptimizationResult".
METHODS = {"weakly": "flexmbs.optimize.cli:run_weakly",
           "fully": "flexmbs.optimize.fully:run_cli"}

#: Functions adding method-specific options to the parser, "module:function(parser)".
METHOD_OPTIONS = ["flexmbs.optimize.cli:add_weakly_options",
                  "flexmbs.optimize.fully:add_cli_options"]


def _load(spec):
    module, _, func = spec.partition(":")
    return getattr(importlib.import_module(module), func)


def register(subparsers):
    """Add the ``optimize`` subcommand."""
    p = subparsers.add_parser(
        "optimize", help="minimize the beam mass of a case under its deviation limit",
        description="Minimize the beam mass of a case subject to its deviation limit at every "
                    "time step, with the weakly coupled method (equivalent static loads in "
                    "cycles, paper 5.3) or another registered method.")
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
    if recs and recs[-1].get("design_mm") is not None:
        p = ",".join(f"{v:.6g}" for v in recs[-1]["design_mm"])
        how = f"to resume from the last design analysed, run the same command with --start={p}"
        if writer.path:
            how += " and a new --history name (an existing history file is started afresh)"
    else:
        how = "no design analysed yet: run the same command again"
    print(f"flexmbs optimize: interrupted; {where}; {how}", file=sys.stderr, flush=True)


def run_optimize(args):
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
        result = run(args, case)
    except KeyboardInterrupt:
        writer.close()
        _interrupted(args, writer)
        return 130
    finally:
        writer.close()
        args.history = history_path
    if args.plot:
        result.plot(args.plot, limit_m=case.limit_m)
    if args.json:
        out = result.to_dict()
        out["case_file"] = case.source
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
