"""The command line: ``flexmbs simulate``, ``flexmbs demo``, and subcommands added by other modules.

Usage::

    flexmbs simulate CASE [--design P1,P2,...] [--t-end T] [--h H] [--rho-inf R]
                          [--set KEY=VALUE ...] [--out result.npz] [--plot FILE.png] [--json]
    flexmbs demo [--out DIR] [--workers N]
    flexmbs reproduce [--table N ...|--all] [--out DIR] [--workers N | --dask ADDRESS] [--quick]

CASE is a case name (``robot_2dof``, ``robot_2dof_tracking``, ``fourbar``, ``fourbar_no_masses``)
or a path to a TOML case file. Errors in the input or in the simulation print one line on stderr
and exit with status 2.

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
import sys
import tomllib

import numpy as np

from flexmbs.errors import CaseError, FlexmbsError

__all__ = ["main", "build_parser", "COMMANDS", "add_case_arguments", "case_from_args",
           "parse_design", "parse_set", "register_simulate", "register_demo"]

#: Subcommand registration functions, "module:function", in the order of the help text.
COMMANDS = [
    "flexmbs.cli:register_simulate",
    "flexmbs.cli:register_demo",
    "flexmbs.optimize.cli:register",
    "flexmbs.reproduce:register",
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


def parse_design(text, case):
    """A design (mm) from "P1,P2,..." (one value applies to every variable); None: the start."""
    if text is None:
        return case.start_mm.copy()
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise CaseError(f"--design {text!r}: expected comma-separated numbers (mm)") from None
    n = len(case.design_names)
    if len(values) == 1:
        values = values * n
    if len(values) != n:
        raise CaseError(f"--design {text!r}: case {case.name!r} has {n} design variables "
                        f"({', '.join(case.design_names)}), got {len(values)} values")
    return np.array(values)


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
    p.add_argument("--out", metavar="FILE.npz", help="save time, deviation, coordinates, reference")
    p.add_argument("--plot", metavar="FILE.png",
                   help="save an overview figure: motion (deflection magnified) and deviation")
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


def run_simulate(args):
    case = case_from_args(args)
    design = parse_design(args.design, case)
    r = case.simulate(design)
    grad = None
    if args.gradient:
        from flexmbs.sensitivity import case_gradients
        grad = case_gradients(case, design, method="direct" if args.gradient == "direct" else "forward")
    if args.out:
        _save_npz(args.out, case, r)
    if args.plot:
        from flexmbs.plots import plot_case
        plot_case(r, args.plot)
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
    ref = {f"reference_{k}": v for k, v in r.reference.items() if k != "t"}
    np.savez_compressed(
        path, t=r.t, deviation=r.deviation, design_mm=r.design_mm, mass=r.mass,
        q=r.result.q, qd=r.result.qd, dofs=r.result.dofs, sensor_dofs=case.sensor_dofs,
        summary=json.dumps(r.summary()), case_config=json.dumps(case.config), **ref)


# ----------------------------------------------------------------------------- demo
def register_demo(subparsers):
    p = subparsers.add_parser(
        "demo", help="reproduce the paper's Table 1 with both methods (under a minute)",
        description="The paper's 2-dof robot (section 6.2, deviation (28), 0.65 s): optimize "
                    "it with the weakly and the fully coupled methods from the start design, "
                    "print the results beside the paper's Table 1, draw Fig. 5 and write a "
                    "report (DIR/README.md). `flexmbs reproduce` does the same for every table.")
    p.add_argument("--out", default="reproduction/demo", metavar="DIR",
                   help="output folder (default: reproduction/demo)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="local worker processes (default 2: one per method; 1: serial)")
    p.set_defaults(func=run_demo)


def run_demo(args):
    from flexmbs.reproduce import print_report, reproduce

    print("flexmbs demo: the paper's Table 1 (2-dof robot, deviation (28), 0.65 s), weakly and "
          "fully coupled optimizations from p = [50, 50, 50, 50] mm", flush=True)
    report = reproduce([1], args.out, workers=args.workers, force=True,
                       log=lambda s: print(s, flush=True))
    print_report(report)
    print()
    for r in report.rows.get(1, []):
        fmt = lambda p: "[" + ", ".join(f"{v:.2f}" for v in p) + "]"     # noqa: E731
        print(f"Table 1, {r.method} coupled optimum: flexmbs {r.mass_kg:.4f} kg, "
              f"p = {fmt(r.design_mm)} mm; paper {r.paper['mass']:.3f} kg, "
              f"p = {fmt(r.paper['p'])} mm")
    return 1 if report.failures else 0


# ----------------------------------------------------------------------------- main
def build_parser():
    """The argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="flexmbs",
        description="Planar flexible multibody simulation and structural optimization of "
                    "mechanism components (the paper's cases live in cases/*.toml).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for spec in COMMANDS:
        module, _, func = spec.partition(":")
        getattr(importlib.import_module(module), func)(sub)
    return parser


def main(argv=None):
    """Entry point of the ``flexmbs`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except (FlexmbsError, OSError) as exc:
        kind = type(exc).__name__
        print(f"flexmbs {args.command}: {kind}: {exc}".replace("\n", " "), file=sys.stderr)
        return 2
