"""What every subcommand of the command line shares: CASE and its overrides
(`add_case_arguments`, `problem_from_args`), a design (`add_design_arguments`,
`design_from_text`), argument types, output files checked before a run (`output_file`,
`figure_file`), the printed summary of an evaluation and JSON output."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from flexmbs.analysis.adaptive import pilot_steps
from flexmbs.errors import CaseError, ModelError
from flexmbs.files import check_disk_space, check_writable
from flexmbs.model.casefile import parse_override
from flexmbs.output import NO_RESPONSES, motion_summary
from flexmbs.problem import FEASIBILITY_TOL, Problem
from flexmbs.resources import format_bytes, format_seconds

__all__ = ["add_case_arguments", "problem_from_args", "design_from_text", "parse_values",
           "parse_set", "positive_int", "nonnegative_int", "path_text", "output_file",
           "figure_file", "print_json", "print_evaluation", "add_design_arguments", "printable",
           "at_least_two", "needs_motion", "evaluate_case", "evaluation_json",
           "check_set_conflicts", "flag_overrides", "announce_run", "tolerance_text",
           "LONG_RUN_STEPS"]


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


#: the options that stand for a key of the case: (option, attribute of the arguments, key)
FLAG_KEYS = (("--t-end", "t_end", "time.t_end"), ("--h", "h", "time.h"),
             ("--rho-inf", "rho_inf", "time.rho_inf"))


def parse_set(items):
    """Overrides {dotted key: value} from ``KEY=VALUE`` strings (`casefile.parse_override`);
    a key given twice with two values is a CaseError naming both."""

    out, given = {}, {}
    for item in items:
        try:
            key, value = parse_override(item)
        except CaseError as exc:
            raise CaseError(f"--set {item!r}: {exc}") from None
        if key in out and not _same(out[key], value):
            raise CaseError(f"--set {given[key]!r} and --set {item!r} give two values of "
                            f"{key}: give one")
        out[key], given[key] = value, item
    return out


def _same(a, b):
    """Two override values are the same value (1 and 1.0 are; True and 1 are not)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    return type(a) is type(b) and a == b or (
        isinstance(a, (int, float)) and isinstance(b, (int, float)) and a == b)


def _set_value(overrides, key):
    """(the --set key, the value) that `overrides` gives `key` (a dotted path), directly or
    inside a table given to one of its parents (--set time={t_end=1}); None if none does."""
    parts = key.split(".")
    for k in range(len(parts), 0, -1):
        head = ".".join(parts[:k])
        if head in overrides:
            value = overrides[head]
            for part in parts[k:]:
                if not isinstance(value, dict) or part not in value:
                    break
                value = value[part]
            else:
                return head, value
    return None


def check_set_conflicts(args, pairs):
    """CaseError when an option given on the command line and a --set of the case key it
    stands for give two values; pairs: (option, value or None when not given, key)."""
    overrides = parse_set(getattr(args, "set", None) or [])
    for option, value, key in pairs:
        hit = None if value is None else _set_value(overrides, key)
        if hit is not None and not _same(hit[1], value):
            shown = f"{value:g}" if isinstance(value, float) else str(value)
            raise CaseError(f"{option} {shown} and --set {hit[0]}={hit[1]!r} give two "
                            f"values of {key}: give one")


def flag_overrides(args):
    """The overrides of the --set items and of the options standing for a key (FLAG_KEYS);
    an option and a --set of its key with two values is a CaseError naming both (one rule
    for every pair: neither wins silently)."""
    check_set_conflicts(args, [(option, getattr(args, attr, None), key)
                               for option, attr, key in FLAG_KEYS])
    overrides = parse_set(args.set)
    for option, attr, key in FLAG_KEYS:
        value = getattr(args, attr, None)
        if value is not None and _set_value(overrides, key) is None:
            overrides[key] = value
    return overrides


def problem_from_args(args, gradient_method="direct"):
    """The Problem named by the arguments of `add_case_arguments`, with their overrides
    (`flag_overrides`); `gradient_method` unless --gradient-method is given."""

    overrides = flag_overrides(args)
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


#: A run of more time steps than this is announced on stderr before it starts (`announce_run`)
LONG_RUN_STEPS = 100_000


def _note_steps(command, steps, what, prob, grid=None, each=""):
    """The line `announce_run` writes for a run of `steps` time steps (`what` tells them)."""
    from flexmbs.analysis.simulate import memory_estimate

    mech = prob.mechanism
    est = memory_estimate(mech.model, mech.t_end, mech.h, prob.settings, steps=grid)
    seconds = est.seconds * steps / max(est.nt - 1, 1)
    print(f"flexmbs {command}: {steps} time steps{each} ({what}), roughly "
          f"{format_seconds(seconds)}{each}", file=sys.stderr, flush=True)


def announce_run(prob, command, error=False, choose=True):
    """Before a long simulation (more than LONG_RUN_STEPS time steps in all): its time steps
    and a rough time (flexmbs.resources.estimate_memory's) on stderr, one line. With
    error-controlled steps (time.h = "auto") the pilots' steps are announced before they
    run, and with `choose` the grid is chosen here (Problem.steps) and its steps announced
    after. With `error` (the --error estimate) the runs with every step halved and quartered
    count too (7 times the steps). choose=False (an optimization, whose every simulation
    runs on the grid or step announced): "per simulation"."""
    mech, ts = prob.mechanism, prob.description.time
    n = mech.t.size - 1
    each = "" if choose else " per simulation"
    if ts.adaptive:
        pilots = pilot_steps(n)
        if pilots > LONG_RUN_STEPS:
            _note_steps(command, pilots, "the two pilot runs that choose the "
                        "error-controlled steps", prob, each=" per choice" if each else "")
        if not choose:
            return
    grid = prob.steps() if ts.adaptive else None
    steps = n if grid is None else grid.size - 1
    factor = 7 if error else 1
    if factor * steps > LONG_RUN_STEPS:
        what = (f"{steps} error-controlled steps to t = {mech.t_end:g} s" if ts.adaptive
                else f"h = {ts.h:g} s to t = {mech.t_end:g} s")
        if error:
            what += ", and twice and four times as many for --error"
        _note_steps(command, factor * steps, what, prob, grid, each)


def evaluate_case(prob, x, args, store=None):
    """(Evaluation, motion summary or None) of `simulate` and `evaluate`: the responses at
    design x as the options ask; a case whose responses need no simulation (none, or masses
    only) has its motion simulated all the same and summarized (flexmbs.output.motion_summary).
    A long run is announced first (`announce_run`)."""

    announce_run(prob, args.command, error=args.error)
    motion = not needs_motion(prob)
    ev = prob.evaluate(x, gradient=args.gradient, store="all" if motion else store,
                       error=args.error)
    return ev, (motion_summary(prob, ev.result) if motion else None)


def evaluation_json(prob, ev, motion=None):
    """The JSON object of `simulate --json` and `evaluate --json` (docs/json-output.md)."""

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
        worst = int(np.argmax(ev.constraints))
        names = list(ev.constraint_names or [])
        of = f", {names[worst]}'s" if worst < len(names) else ""
        print(f"  constraints     {state}: largest g = {ev.max_violation:.4g}{of} "
              f"({ev.constraints.size} rows g = (value - limit) / |limit| <= 0; feasible when "
              f"g <= {FEASIBILITY_TOL:g})")
        if not ev.feasible:
            print(f"  note            {step_hint(prob, ev)}")
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
        grid = r.get("grid") or {}
        print(f"  simulation      {steps} to t = "
              f"{r.get('t_end', ev.t[-1]):.10g} s: {s.get('newton_iterations', '?')} Newton "
              f"iterations, {s.get('factorizations', '?')} factorizations, "
              f"{s.get('step_cuts', '?')} step cuts")
        if "estimated_error" in grid:
            print("  tolerance       " + tolerance_text(grid))
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


def step_hint(prob, ev):
    """What an infeasible verdict at the case's step does not know: a constraint whose
    estimated error (--error) exceeds its violation may hold at a finer step; without --error,
    the verdict is the case's step's alone (an optimized design is verified at a finer one)."""
    h = f"h = {prob.description.time.grid_h:g} s"
    errs = ev.constraint_errors or {}
    if errs:
        over = {n: e for n, e in errs.items() if e.value > FEASIBILITY_TOL}
        loose = [n for n, e in over.items() if not e.reliable]
        close = [n for n, e in over.items() if e.reliable and e.error >= e.value]
        if loose:
            return (f"the verdict may change at a finer step: {', '.join(loose)} not in the "
                    f"asymptotic range at {h}, so the error estimate is no bound (refine "
                    f"time.h)")
        if close:
            return (f"the verdict depends on the step: {', '.join(close)} exceed their limits "
                    f"by less than their estimated error at {h} (refine time.h)")
        return (f"the violations exceed their estimated errors at {h} (asymptotic range): "
                f"infeasible at finer steps too")
    return (f"the verdict is at the case's {h}; a finer step can change it: --error estimates "
            f"each value's error, and a design verified by `flexmbs optimize` is re-checked at "
            f"its verified step (the command it prints)")


def tolerance_text(grid):
    """Whether an error-controlled grid (Problem.grid_summary) reaches its tolerance, as the
    pilots estimate it, in a line."""
    given = ", ".join(f"{k} = {grid[k]:g}" for k in ("tol", "rtol") if grid.get(k))
    e = grid["estimated_error"]
    text = (f"{given} {'reached' if grid['tolerance_reached'] else 'NOT reached'} by the "
            f"pilots' estimate: error {e:.2g} of it")
    if grid.get("saturated"):
        text += (f"; over {100 * grid['saturated']:.3g} % of the run it asks for steps "
                 f"shorter than the shortest allowed ({grid['shortest_step']:.3g} s): steps "
                 "of that length there, the others shortened to make up for it")
    return text


def printable(text, keep_newlines=False):
    """Text from a file (a case's description, a study's titles), safe for a terminal: every
    character that is not printable (escape sequences, controls, bidirectional overrides) is
    shown escaped, e.g. '\\x1b[2J' for ESC [2J, instead of acting on the terminal."""
    def one(c):
        if c.isprintable() or (keep_newlines and c == "\n"):
            return c
        return c.encode("unicode_escape").decode("ascii")
    return "".join(one(c) for c in str(text))
