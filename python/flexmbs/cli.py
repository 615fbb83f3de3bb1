"""The command line: ``flexmbs simulate``, ``flexmbs demo``, and subcommands added by other modules.

Usage::

    flexmbs simulate CASE [--design P1,P2,...] [--t-end T] [--h H] [--rho-inf R]
                          [--set KEY=VALUE ...] [--out result.npz] [--plot FILE.png] [--json]
    flexmbs demo [--out DIR] [--workers N]
    flexmbs reproduce [--table N ...|--all] [--out DIR] [--workers N | --dask ADDRESS] [--quick]

CASE is a case name (``robot_2dof``, ``robot_2dof_tracking``, ``fourbar``, ``fourbar_no_masses``)
or a path to a TOML case file. Errors in the input or in the simulation, and files that cannot be
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
the parser is built). `add_case_arguments` and `case_from_args` give every subcommand the same
CASE, --set, --t-end, --h and --rho-inf options; `parse_design` reads a --design value.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
import tomllib
import traceback
import warnings
from pathlib import Path

import numpy as np

from flexmbs.batch import save_figure
from flexmbs.errors import CaseError, FlexmbsError, ModelError

__all__ = ["main", "build_parser", "COMMANDS", "add_case_arguments", "case_from_args",
           "parse_design", "parse_values", "parse_set", "register_simulate", "positive_int",
           "output_file", "figure_file"]

#: Subcommand registration functions, "module:function", in the order of the help text.
COMMANDS = [
    "flexmbs.cli:register_simulate",
    "flexmbs.cli_reproduce:register_demo",
    "flexmbs.cli_evaluate:register",
    "flexmbs.optimize.cli:register",
    "flexmbs.cli_reproduce:register",
]


# ----------------------------------------------------------------------------- shared options
def add_case_arguments(parser):
    """CASE plus the options that override its settings (--t-end, --h, --rho-inf, --set)."""
    parser.add_argument("case", metavar="CASE",
                        help="case name (robot_2dof, robot_2dof_tracking, fourbar, "
                             "fourbar_no_masses) or path to a .toml case file")
    parser.add_argument("--t-end", type=float, metavar="T", help="end time (s); default: the case's")
    parser.add_argument("--h", type=float, metavar="H", help="time step (s); default: the case's")
    parser.add_argument("--rho-inf", type=float, metavar="R",
                        help="spectral radius at infinite frequency; default: the case's")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override any key of the case file (repeatable), e.g. "
                             "--set drive=relative, --set theta0_deg=0, --set mechanism.mass_tip_kg=0.5")


def parse_set(items):
    """Overrides from ``KEY=VALUE`` strings; VALUE is read as a TOML value (number, "string",
    [array], true/false), a bare word as a string."""
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or not key:
            raise CaseError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        out[key] = value
    return out


def case_from_args(args):
    """The Case named by the arguments of `add_case_arguments`, with their overrides."""
    from flexmbs.cases import load_case

    overrides = parse_set(args.set)
    for key, value in (("t_end", args.t_end), ("h", args.h), ("rho_inf", args.rho_inf)):
        if value is not None:
            overrides[key] = value
    return load_case(args.case, **overrides)


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


def parse_design(text, case):
    """A design (mm) from "P1,P2,..." (one value applies to every variable); None: the start."""
    if text is None:
        return case.start_mm.copy()
    return parse_values(text, case.design_names, case.name)


def positive_int(text):
    """argparse type: an integer >= 1 (e.g. --workers)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


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
        "simulate", help="simulate a case at a design and report mass and maximum deviation",
        description="Simulate a case at a design: beam mass, deviation history and its maximum.")
    add_case_arguments(p)
    p.add_argument("--design", metavar="P1,P2,...",
                   help="design variables in mm (one value: all of them); default: the case's start")
    p.add_argument("--out", metavar="FILE.npz",
                   help="save time, deviation, coordinates, reference (.npz is added to a "
                        "name without it)")
    p.add_argument("--plot", metavar="FILE.png",
                   help="save an overview figure: motion (deflection magnified) and deviation "
                        "(format from the extension: png, pdf, svg, ...)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    p.add_argument("--gradient", nargs="?", const="direct", choices=("direct", "fd"),
                   help="also compute design derivatives of the mass and of the deviation at its "
                        "maximum: direct differentiation (default) or forward finite differences "
                        "(the paper's method, relative step 1e-6)")
    p.set_defaults(func=run_simulate)


def _summary_lines(case, r):
    s = r.summary()
    design = ", ".join(f"{n} = {v:.4g}" for n, v in zip(case.design_names, r.design_mm))
    status = "within the limit" if r.feasible else "ABOVE the limit"
    return [
        f"{case.name}: {case.description}",
        f"  case file       {case.source}",
        f"  design          {design} mm",
        f"  beam mass       {r.mass:.4f} kg",
        f"  max deviation   {r.max_deviation * 1e3:.4f} mm ({r.formulation}) at t = {r.t_at_max:.4f} s "
        f"(step {r.step_at_max} of {r.t.size}), limit {r.limit_m * 1e3:g} mm: {status}",
        f"  simulation      {s['steps']} steps of {s['h_s']:g} s, rho_inf {s['rho_inf']:g}, "
        f"{s['newton_iterations']} Newton iterations, {s['wall_time_s']:.3f} s",
    ]


def _npz_estimate(case):
    """Rough upper bound (bytes) of the --out file: q and qd at every step."""
    try:
        ndof = int(case.model.ndof)
        nt = int(round(float(case.t_end) / float(case.h))) + 1
    except (AttributeError, TypeError, ValueError, ZeroDivisionError):
        return 0.0
    return 8.0 * nt * (2 * ndof + 16)


def run_simulate(args):
    case = case_from_args(args)
    design = parse_design(args.design, case)
    # output paths are checked before the run, not after it
    if args.out:
        args.out = output_file(args.out, "--out", suffix=".npz", required=_npz_estimate(case))
    if args.plot:
        args.plot = figure_file(args.plot, "--plot")
    r = case.simulate(design)
    grad = None
    if args.gradient:
        from flexmbs.sensitivity import case_gradients
        grad = case_gradients(case, design, method="direct" if args.gradient == "direct" else "forward")
    if args.out:
        _save_npz(args.out, case, r)
    if args.plot:
        from flexmbs.plots import plot_case
        save_figure(plot_case(r), args.plot, dpi=150, bbox_inches="tight")
    if args.json:
        out = r.summary()
        out["case_file"] = case.source
        if args.out:
            out["out"] = args.out
        if args.plot:
            out["plot"] = args.plot
        if grad is not None:
            out["gradient_method"] = grad.method
            out["gradient_simulations"] = grad.simulations
            out["gradient_wall_time_s"] = grad.wall_time
            out["d_mass_d_design_kg_per_mm"] = grad.d_mass.tolist()
            out["d_max_deviation_d_design_m_per_mm"] = grad.d_max_deviation.tolist()
        print_json(out)
    else:
        print("\n".join(_summary_lines(case, r)))
        if grad is not None:
            fmt = ", ".join
            print(f"  d mass / dp     [{fmt(f'{v:.4g}' for v in grad.d_mass)}] kg/mm")
            print(f"  d max dev / dp  [{fmt(f'{v:.4g}' for v in grad.d_max_deviation)}] m/mm "
                  f"({grad.method}, {grad.simulations} simulation(s), {grad.wall_time:.3f} s)")
        for what, f in (("results", args.out), ("figure", args.plot)):
            if f:
                print(f"  {what:<15s} {f}")
    return 0


def _save_npz(path, case, r):
    from flexmbs.batch import atomic_open

    ref = {f"reference_{k}": v for k, v in r.reference.items() if k != "t"}
    with atomic_open(path, "wb") as fh:       # a file object: numpy adds no suffix
        np.savez_compressed(
            fh, t=r.t, deviation=r.deviation, design_mm=r.design_mm, mass=r.mass,
            q=r.result.q, qd=r.result.qd, dofs=r.result.dofs, sensor_dofs=case.sensor_dofs,
            summary=json.dumps(r.summary()), case_config=json.dumps(case.config), **ref)


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
                    "mechanism components (the paper's cases live in cases/*.toml).")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (also: FLEXMBS_DEBUG=1); "
                             "accepted after the subcommand too")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for spec in COMMANDS:
        module, _, func = spec.partition(":")
        getattr(importlib.import_module(module), func)(sub)
    return parser


def _one_line(exc):
    text = str(exc)
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.strerror}: {exc.filename!r}"
    return " ".join(text.split())


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings on the command line: one line each, without the source line."""
    print(f"flexmbs: {category.__name__}: {' '.join(str(message).split())}",
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
        exc.parser.print_usage(sys.stderr)
        print(f"{exc.parser.prog}: error: {exc.message}{_usage_hint(exc.message, argv)}",
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
