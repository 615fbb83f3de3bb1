"""``flexmbs evaluate CASE``: every response of a case at a design, with its design gradient
(exact, direct differentiation), as a summary or one JSON object."""
from __future__ import annotations

import json
import sys

from flexmbs.cli import (add_case_arguments, add_design_arguments, design_from_text,
                         print_evaluation, problem_from_args)

__all__ = ["register", "run"]


def register(subparsers):
    p = subparsers.add_parser(
        "evaluate", help="responses of a case at a design, with gradients",
        description="Simulate a case (docs/case-format.md) at a design and report every "
                    "response (maximum over time), the objective and the constraints, with "
                    "their exact design gradients.")
    add_case_arguments(p)
    add_design_arguments(p)
    p.set_defaults(func=run)


def run(args):
    prob = problem_from_args(args)
    ev = prob.evaluate(design_from_text(args.design, prob), gradient=args.gradient,
                       error=args.error)
    if args.json:
        json.dump(ev.to_json(), sys.stdout)
        sys.stdout.write("\n")
        return 0
    print_evaluation(prob, ev)
    return 0
