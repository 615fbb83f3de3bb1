"""``flexmbs evaluate CASE``: every response of a case at a design, with its design gradient
(exact, direct differentiation), as a summary or one JSON object."""
from __future__ import annotations

from flexmbs.cli.common import (add_case_arguments, add_design_arguments, design_from_text,
                                evaluate_case, evaluation_json, print_evaluation, print_json,
                                problem_from_args)

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
    ev, motion = evaluate_case(prob, design_from_text(args.design, prob), args)
    if args.json:
        print_json(evaluation_json(prob, ev, motion))
        return 0
    print_evaluation(prob, ev, motion=motion)
    return 0
