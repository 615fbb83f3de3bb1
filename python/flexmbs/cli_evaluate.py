"""``flexmbs evaluate CASE``: every response of a general-format case at a design, with its
design gradient (exact, direct differentiation), as a summary or one JSON object."""
from __future__ import annotations

import json
import sys

import numpy as np

from flexmbs.cli import parse_values

__all__ = ["register", "design_from_text"]


def register(subparsers):
    p = subparsers.add_parser(
        "evaluate", help="responses of a general-format case at a design, with gradients",
        description="Simulate a general-format case (docs/case-format.md) at a design and report "
                    "every response (maximum over time), the objective and the constraints, with "
                    "their exact design gradients.")
    p.add_argument("case", metavar="CASE", help="path to a general-format .toml case file, or "
                                                 "the name of one in cases/general")
    p.add_argument("--design", metavar="X1,X2,...",
                   help="design variables in their units (one value: all of them); "
                        "default: the case's start")
    p.add_argument("--gradient", action="store_true", help="also compute design gradients")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def design_from_text(text, prob, option="--design"):
    """The design of a --design/--start value for a Problem (None: its start)."""
    if text is None:
        return prob.start
    return parse_values(text, prob.variables, prob.description.case.name, option)


def run(args):
    from flexmbs.problem import Problem
    prob = Problem(args.case)
    ev = prob.evaluate(design_from_text(args.design, prob), gradient=args.gradient)
    if args.json:
        json.dump(ev.to_json(), sys.stdout)
        sys.stdout.write("\n")
        return 0
    units = [v.unit for v in prob.description.design]
    print(f"{prob.description.case.name}: {prob.description.case.description or ''}")
    print("  design          " + ", ".join(f"{n} = {v:.5g} {u}" for n, v, u in
                                           zip(prob.variables, ev.x, units)))
    for name, v in ev.values.items():
        g = ev.gradients.get(name)
        if np.ndim(v) == 0:
            line = f"  {name:15s} {float(v):.6g}"
            if g is not None:
                line += "   gradient " + ", ".join(f"{x:.4g}" for x in g)
        else:
            j = int(np.argmax(v))
            line = f"  {name:15s} max {v[j]:.6g} at t = {ev.t[j]:.4f} s"
            if g is not None:
                line += "   gradient of the max " + ", ".join(f"{x:.4g}" for x in g[j])
        print(line)
    if ev.constraints.size:
        state = "feasible" if ev.feasible else "INFEASIBLE"
        print(f"  constraints     {state}: largest g = {ev.max_violation:.4g} "
              f"({ev.constraints.size} rows, g <= 0)")
    print(f"  wall time       {ev.wall_time:.3f} s")
    return 0
