"""The command line: ``flexmbs simulate``, ``flexmbs demo``, and subcommands added by other modules.

Usage::

    flexmbs simulate CASE [--design P1,P2,...] [--t-end T] [--h H] [--rho-inf R]
                          [--set KEY=VALUE ...] [--out result.npz] [--plot FILE.png] [--json]
    flexmbs animate CASE [--design P1,P2,...] [--set KEY=VALUE ...] --out motion.gif|.mp4|.pvd
                         [--frames N] [--fps F] [--magnify S] [--color-by deviation|stress|none]
    flexmbs demo [--out DIR] [--workers N]
    flexmbs reproduce [--study FILE] [--table N ...|--all] [--out DIR] [--workers N | --dask ADDRESS] [--quick]

CASE is the name of a shipped case (``flexmbs.casefile.available_cases()``: the files of cases/)
or a path to a TOML case file (docs/case-format.md). Errors in the input or in the simulation, and files that cannot be
written, print one line on stderr and exit with status 2 (``--debug`` before or after the
subcommand, or the environment variable ``FLEXMBS_DEBUG=1``, also prints the traceback). Output
paths (--out, --plot, --history) are checked before the run: the folder must be writable, a
figure's extension must be a format matplotlib writes. Files are written to a temporary name and
renamed when complete. Ctrl-C prints one line (what is kept, how to resume) and exits with 130.

Adding a subcommand
-------------------
Each subcommand is registered by a function ``register(subparsers)`` that adds its parser and
sets its handler with ``set_defaults(func=handler)``; a handler takes the parsed arguments and
returns an exit status. List the function in `COMMANDS` as ``"module:function"`` (imported when
the parser is built). `add_case_arguments` and `problem_from_args` give every subcommand the same
CASE, --set, --t-end, --h and --rho-inf options; `design_from_text` reads a --design value.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
import traceback
import warnings
from pathlib import Path

import numpy as np

from flexmbs.batch import save_figure
from flexmbs.errors import CaseError, FlexmbsError, ModelError

__all__ = ["main", "build_parser", "COMMANDS", "add_case_arguments", "problem_from_args",
           "design_from_text", "parse_values", "parse_set", "register_simulate", "positive_int",
           "nonnegative_int", "at_least_two", "path_text",
           "output_file", "figure_file", "print_evaluation", "add_design_arguments",
           "evaluate_case", "evaluation_json", "needs_motion"]

#: Subcommand registration functions, "module:function", in the order of the help text.
COMMANDS = [
    "flexmbs.cli:register_simulate",
    "flexmbs.cli_reproduce:register_demo",
    "flexmbs.cli_evaluate:register",
    "flexmbs.cli_check:register",
    "flexmbs.cli_animate:register",
    "flexmbs.optimize.cli:register",
    "flexmbs.cli_reproduce:register",
]


# ----------------------------------------------------------------------------- shared options
def add_case_arguments(parser):
    """CASE plus the options that override its settings (--t-end, --h, --rho-inf, --set)."""
    parser.add_argument("case", metavar="CASE",
                        help="name of a shipped case (e.g. robot_2dof, fourbar, "
                             "slider_crank_press) or path to a .toml case file")
    parser.add_argument("--t-end", type=float, metavar="T",
                        help="end time (s), i.e. --set time.t_end=T; default: the case's")
    parser.add_argument("--h", type=float, metavar="H",
                        help="time step (s), i.e. --set time.h=H; default: the case's")
    parser.add_argument("--rho-inf", type=float, metavar="R",
                        help="spectral radius at infinite frequency; default: the case's")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override any key of the case file (repeatable) by its dotted "
                             "path, items of a table array by name: --set time.h=2e-4, "
                             "--set bodies.arm1.elements=4")
    parser.add_argument("--gradient-method", choices=("direct", "adjoint", "auto"),
                        default=None,
                        help="how gradients are computed: direct differentiation (every "
                             "response's gradient; the default of simulate and evaluate), the "
                             "discrete adjoint (objective and constraint rows only, cost "
                             "independent of the number of variables), or auto (the default of "
                             "optimize: the adjoint when the variables are >= 32 and outnumber "
                             "the aggregated rows 4 times; docs/adjoint.md)")
    parser.add_argument("--checkpoints", type=_checkpoints, default=None, metavar="auto|K",
                        help="the adjoint's forward run keeps the full state every K time "
                             "points only and recomputes the segments backwards (auto: K = "
                             "sqrt(steps), about the least memory); default: the tape of every "
                             "state when it fits in memory, checkpoints when it does not "
                             "(docs/adjoint.md 3b)")


def _checkpoints(text):
    """--checkpoints: 'auto' or an integer >= 1."""
    if text == "auto":
        return text
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer >= 1, got {text!r}")
    return k


def parse_set(items):
    """Overrides {dotted key: value} from ``KEY=VALUE`` strings (`casefile.parse_override`)."""
    from flexmbs.casefile import parse_override

    out = {}
    for item in items:
        try:
            key, value = parse_override(item)
        except CaseError as exc:
            raise CaseError(f"--set {item!r}: {exc}") from None
        out[key] = value
    return out


def problem_from_args(args, gradient_method="direct"):
    """The Problem named by the arguments of `add_case_arguments`, with their overrides;
    `gradient_method` unless --gradient-method is given."""
    from flexmbs.problem import Problem

    overrides = parse_set(args.set)
    for key, value in (("t_end", args.t_end), ("h", args.h), ("rho_inf", args.rho_inf)):
        if value is not None:
            overrides[f"time.{key}"] = value
    return Problem(args.case, overrides=overrides or None,
                   gradient_method=getattr(args, "gradient_method", None) or gradient_method,
                   checkpoints=getattr(args, "checkpoints", None))


def parse_values(text, names, owner, option="--design"):
    """Design values from "X1,X2,..." for the variables `names` (one value applies to every
    variable); CaseError naming the option and the case `owner` otherwise."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise CaseError(f"{option} {text!r}: expected comma-separated numbers") from None
    n = len(names)
    if len(values) == 1:
        values = values * n
    if len(values) != n:
        raise CaseError(f"{option} {text!r}: case {owner!r} has {n} design variables "
                        f"({', '.join(names)}), got {len(values)} values")
    return np.array(values)


def design_from_text(text, problem, option="--design"):
    """The design of a --design/--start value for a Problem (None: its start), checked
    against the variables' bounds."""
    if text is None:
        return problem.start
    x = parse_values(text, problem.variables, problem.description.case.name, option)
    try:
        return problem.mechanism.design_values(x)
    except ModelError as exc:
        raise CaseError(f"{option} {text!r}: {exc}") from None


def _int_at_least(minimum):
    """argparse type: an integer >= minimum."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got "
                                             f"{text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value
    return parse


#: argparse type: an integer >= 1 (e.g. --workers).
positive_int = _int_at_least(1)
#: argparse type: an integer >= 0 (e.g. --seed).
nonnegative_int = _int_at_least(0)
#: argparse type: an integer >= 2 (e.g. --frames: a first and a last).
at_least_two = _int_at_least(2)


def path_text(text):
    """argparse type of a file or folder name (--out, --plot, --history, --store, --study):
    not empty or blank (an empty --out wrote nothing and said nothing)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a file or folder name, got {text!r}")
    return text


def output_file(path, option, suffix=None, required=0.0):
    """Check, before the run, an output file given as `option`: its folder exists and is
    writable, the path is not a folder, and (rough estimate) `required` bytes fit on the disk.
    With `suffix` (e.g. '.npz'), the suffix is added when the name does not end with it.
    Returns the path that will be written (report exactly this one)."""
    from flexmbs.batch import check_disk_space, check_writable

    path = str(path)
    if suffix and not path.endswith(suffix):
        path += suffix
    if Path(path).is_dir():
        raise ModelError(f"{option} {path!r} is a folder; give a file name")
    folder = Path(path).parent
    check_writable(folder, f"{option} {path!r}")
    if required:
        check_disk_space(folder, required, f"{option} {path!r}")
    return path


def figure_file(path, option):
    """`output_file` for a figure: the extension must be a format matplotlib writes (a name
    without one gets '.png'). Returns the path that will be written."""
    from matplotlib.backend_bases import FigureCanvasBase

    path = str(path)
    formats = FigureCanvasBase.get_supported_filetypes()
    ext = os.path.splitext(path)[1]
    if not ext:
        path += ".png"
    elif ext[1:].lower() not in formats:
        raise ModelError(f"{option} {path!r}: unknown figure format {ext!r}; matplotlib "
                         f"writes {', '.join('.' + k for k in sorted(formats))}")
    return output_file(path, option)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(type(obj).__name__)


def print_json(obj):
    """Print one JSON object on stdout."""
    print(json.dumps(obj, default=_json_default))


# ----------------------------------------------------------------------------- simulate
def register_simulate(subparsers):
    p = subparsers.add_parser(
        "simulate", help="simulate a case at a design: every response, the constraints",
        description="Simulate a case at a design and report every response (maximum over "
                    "time), the objective and the constraints; optionally their exact design "
                    "gradients, the results (.npz) and an overview figure.")
    add_case_arguments(p)
    add_design_arguments(p)
    p.add_argument("--out", type=path_text, metavar="FILE.npz",
                   help="save time, coordinates, rigid reference and response histories, "
                        "and what each coordinate is (its node, body, point, station s: "
                        "Mechanism.layout) (.npz is added to a name without it)")
    p.add_argument("--plot", type=path_text, metavar="FILE.png",
                   help="save an overview figure: motion (deflection magnified) and the "
                        "constrained responses (format from the extension: png, pdf, svg, ...)")
    p.set_defaults(func=run_simulate)


def add_design_arguments(p):
    """--design, --gradient and --json: the options of a command that evaluates one design."""
    p.add_argument("--design", metavar="X1,X2,...",
                   help="design variables in their units (one value: all of them); default: "
                        "the case's start")
    p.add_argument("--gradient", action="store_true",
                   help="also compute the design gradients (exact: direct differentiation, or the "
                        "adjoint with --gradient-method adjoint|auto)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    p.add_argument("--error", action="store_true",
                   help="estimate each value's time-discretisation error (the design simulated "
                        "again at h/2 and h/4; about 6 more simulations' time) and say whether "
                        "it is in its asymptotic range")


def _gradient_text(g, gunits):
    """A gradient with its units: '1.2e-06, 3.4e-07 (m/mm)' when every component has the
    same unit, else each component with its own."""
    gunits = list(gunits or [])
    if len(gunits) != len(g) or None in gunits:
        return ", ".join(f"{x:.6g}" for x in g)
    if len(set(gunits)) == 1:
        return ", ".join(f"{x:.6g}" for x in g) + f" ({gunits[0]})"
    return ", ".join(f"{x:.6g} {u}" for x, u in zip(g, gunits))


def needs_motion(prob):
    """Whether a response of the problem needs a simulation (any but a mass)."""
    return any(r.type != "mass" for r in prob.description.responses)


def evaluate_case(prob, x, args, store=None):
    """(Evaluation, motion summary or None) of `simulate` and `evaluate`: the responses at
    design x as the options ask; a case whose responses need no simulation (none, or masses
    only) has its motion simulated all the same and summarized (flexmbs.output.motion_summary)."""
    from flexmbs.output import motion_summary

    motion = not needs_motion(prob)
    ev = prob.evaluate(x, gradient=args.gradient, store="all" if motion else store,
                       error=args.error)
    return ev, (motion_summary(prob, ev.result) if motion else None)


def evaluation_json(prob, ev, motion=None):
    """The JSON object of `simulate --json` and `evaluate --json` (docs/json-output.md)."""
    from flexmbs.output import NO_RESPONSES

    out = ev.to_json()
    out["case"] = prob.description.case.name
    if motion is not None:
        out["motion"] = motion
        out["units"]["motion"] = {"deflection": "m", "t": "s"}
        if not prob.description.responses:
            out["notes"] = [NO_RESPONSES]
    return out


def print_evaluation(prob, ev, source=None, motion=None):
    """The summary of an Evaluation for people: design, every response with its unit (and
    its gradient's), the constraints, warnings, the resolution and the run's statistics;
    with `motion` (flexmbs.output.motion_summary), the motion's largest deflections and drive
    forces."""
    from flexmbs.output import NO_RESPONSES
    from flexmbs.problem import FEASIBILITY_TOL
    from flexmbs.resources import format_bytes

    d = prob.description
    units = prob.mechanism.units
    resp_units = (ev.units or {}).get("responses", {})
    grad_units = (ev.units or {}).get("gradients", {})
    print(f"{d.case.name}: {printable(d.case.description or '')}")
    if source:
        print(f"  case file       {printable(source)}")
    if prob.variables:
        print("  design          " + ", ".join(f"{n} = {v:.10g} {u}" for n, v, u in
                                               zip(prob.variables, ev.x, units)))
    for name, v in ev.values.items():
        g = ev.gradients.get(name)
        u = resp_units.get(name)
        us = f" {u}" if u else ""
        if np.ndim(v) == 0:
            line = f"  {name:15s} {float(v):.10g}{us}"
            if g is not None:
                line += "   gradient " + _gradient_text(g, grad_units.get(name))
        else:
            j = int(np.argmax(v))
            line = (f"  {name:15s} max {v[j]:.10g}{us} at t = {ev.t[j]:.6g} s "
                    f"(step {j} of {v.size - 1})")
            if g is not None:
                line += "   gradient of the max " + _gradient_text(g[j], grad_units.get(name))
        e = (ev.errors or {}).get(name)
        if e is not None and (e.error > 0 or np.ndim(v)):
            line += f"   {e.describe()}"
        print(line)
    if ev.constraints.size:
        state = "feasible" if ev.feasible else "INFEASIBLE"
        print(f"  constraints     {state}: largest g = {ev.max_violation:.4g} "
              f"({ev.constraints.size} rows g <= 0, relative to the limits; feasible when "
              f"g <= {FEASIBILITY_TOL:g})")
    for w in ev.gradient_warnings():
        print(f"  warning         {printable(w)}")
    if motion is not None:
        if not d.responses:
            print(f"  no responses    {NO_RESPONSES}")
        for name, m in motion["deflection"].items():
            print(f"  {name:15s} largest deflection from the rigid motion {m['max']:.6g} m "
                  f"at t = {m['t']:.6g} s")
        for name, m in motion["drives"].items():
            what = "torque" if m["unit"] == "N m" else "force"
            print(f"  {name:15s} largest |{what}| {m['max_abs']:.6g} {m['unit']} "
                  f"at t = {m['t']:.6g} s")
    s = ev.stats or {}
    r = ev.resolution or {}
    if s:
        ts = d.time
        steps = s.get("steps", r.get("steps", ev.t.size - 1))
        steps = (f"{steps} error-controlled steps (outputs every {ts.grid_h:g} s)"
                 if ts.adaptive else f"{steps} steps of h = {ts.grid_h:g} s")
        print(f"  simulation      {steps} to t = "
              f"{r.get('t_end', ev.t[-1]):.10g} s: {s.get('newton_iterations', '?')} Newton "
              f"iterations, {s.get('factorizations', '?')} factorizations, "
              f"{s.get('step_cuts', '?')} step cuts")
        if r.get("elements"):
            print("  resolution      elements " + ", ".join(
                f"{b} {n}" for b, n in r["elements"].items())
                + f"; rho_inf {d.time.rho_inf:g}, start {d.time.start}")
        mem = s.get("memory_estimate")
        print(f"  time            wall {ev.wall_time:.3f} s, CPU {ev.cpu_time:.3f} s"
              + (f"; memory estimate {format_bytes(mem)}" if mem is not None else ""))
    else:
        print(f"  time            wall {ev.wall_time:.3f} s, CPU {ev.cpu_time:.3f} s (nothing "
              f"simulated: no response needs the motion)")


def _npz_estimate(prob):
    """Rough upper bound (bytes) of the --out file: q, qd and the rigid reference per step."""
    return 8.0 * prob.mechanism.t.size * (3 * prob.mechanism.model.ndof + 16)


def run_simulate(args):
    prob = problem_from_args(args)
    x = design_from_text(args.design, prob)
    # output paths are checked before the run, not after it
    if args.out:
        args.out = output_file(args.out, "--out", suffix=".npz", required=_npz_estimate(prob))
    if args.plot:
        args.plot = figure_file(args.plot, "--plot")
    ev, motion = evaluate_case(prob, x, args, store="all" if (args.out or args.plot) else None)
    result = ev.result
    if args.out:
        _save_npz(args.out, prob, ev, result)
    if args.plot:
        from flexmbs.plots import plot_overview
        save_figure(plot_overview(prob, result, ev), args.plot, dpi=150, bbox_inches="tight")
    if args.json:
        out = evaluation_json(prob, ev, motion)
        for key in ("out", "plot"):
            if getattr(args, key):
                out[key] = getattr(args, key)
        print_json(out)
    else:
        print_evaluation(prob, ev, motion=motion)
        for what, f in (("results", args.out), ("figure", args.plot)):
            if f:
                print(f"  {what:<15s} {f}")
    return 0


def _save_npz(path, prob, ev, result):
    from flexmbs.batch import atomic_open

    hist = {f"response_{k}": np.asarray(v) for k, v in ev.values.items()}
    with atomic_open(path, "wb") as fh:       # a file object: numpy adds no suffix
        np.savez_compressed(
            fh, t=result.t, q=result.q, qd=result.qd, dofs=result.dofs, design=ev.x,
            variables=np.array(prob.variables), reference_q=prob.mechanism.reference.q,
            constraints=ev.constraints, summary=json.dumps(ev.to_json()),
            **prob.mechanism.layout(result.dofs), **hist)


# ----------------------------------------------------------------------------- main
class _UsageError(Exception):
    """A command-line usage error, raised by _Parser.error instead of exiting at once (so
    that `main` can add a hint that needs the command line)."""

    def __init__(self, parser, message):
        super().__init__(message)
        self.parser = parser
        self.message = message


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(self, message)


#: A value that argparse takes for an option: "-40,30" or "-4e1" (a plain "-40" is a number).
_DASH_VALUE = re.compile(r"^-[\d.]")


def _usage_hint(message, argv):
    """For "argument --design: expected one argument" when the next word is a negative value,
    the form that works: --design=-40,30,..."""
    m = re.match(r"argument ([-\w/]+)(?:/[-\w]+)*: expected one argument", message)
    if not m:
        return ""
    names = m.group(1).split("/")
    for k, word in enumerate(argv[:-1]):
        if word in names and _DASH_VALUE.match(argv[k + 1]):
            return (f"; a value that starts with '-' must be attached with '=': write "
                    f"{word}={argv[k + 1]}")
    return ""


def build_parser():
    """The argument parser with every registered subcommand."""
    parser = _Parser(
        prog="flexmbs",
        description="Planar flexible multibody simulation and structural optimization of "
                    "mechanism components (shipped cases: cases/*.toml, format: "
                    "docs/case-format.md).")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (also: FLEXMBS_DEBUG=1); "
                             "accepted after the subcommand too")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for spec in COMMANDS:
        module, _, func = spec.partition(":")
        getattr(importlib.import_module(module), func)(sub)
    return parser


def printable(text, keep_newlines=False):
    """Text from a file (a case's description, a study's titles), safe for a terminal: every
    character that is not printable (escape sequences, controls, bidirectional overrides) is
    shown escaped, e.g. '\\x1b[2J' for ESC [2J, instead of acting on the terminal."""
    def one(c):
        if c.isprintable() or (keep_newlines and c == "\n"):
            return c
        return c.encode("unicode_escape").decode("ascii")
    return "".join(one(c) for c in str(text))


def _one_line(exc):
    text = str(exc)
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.strerror}: {exc.filename!r}"
    return printable(" ".join(text.split()))


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings on the command line: one line each, without the source line."""
    print(f"flexmbs: {category.__name__}: {printable(' '.join(str(message).split()))}",
          file=file or sys.stderr)


def main(argv=None):
    """Entry point of the ``flexmbs`` command; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = os.environ.get("FLEXMBS_DEBUG", "").strip() not in ("", "0")
    if "--debug" in argv:           # anywhere: before or after the subcommand
        debug = True
        argv = [a for a in argv if a != "--debug"]
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as exc:
        # one line, as every other error (the usage is in `--help`)
        message = printable(" ".join(f"{exc.message}{_usage_hint(exc.message, argv)}".split()))
        print(f"{exc.parser.prog}: error: {message} (see '{exc.parser.prog} --help')",
              file=sys.stderr)
        return 2
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    with warnings.catch_warnings():
        if not debug:
            warnings.showwarning = _show_warning
        try:
            return int(args.func(args) or 0)
        except (FlexmbsError, OSError, MemoryError) as exc:
            if debug:
                traceback.print_exc()
            kind = type(exc).__name__
            print(f"flexmbs {args.command}: {kind}: {_one_line(exc)}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            if debug:
                traceback.print_exc()
            print(f"flexmbs {args.command}: interrupted", file=sys.stderr)
            return 130
