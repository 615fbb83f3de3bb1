"""``flexmbs check CASE``: is the case's resolution converged? Each response at the case's
step, its estimated time-discretisation error (h against h/2 and h/4) and its change with twice
the elements of every beam, with a verdict (flexmbs.analysis.accuracy.convergence_check)."""
from __future__ import annotations

from flexmbs.analysis.accuracy import convergence_check
from flexmbs.cli.common import add_case_arguments, design_from_text, print_json, problem_from_args
from flexmbs.errors import CaseError

__all__ = ["register", "run"]


def register(subparsers):
    p = subparsers.add_parser(
        "check", help="convergence check: each response against half the step and twice the "
                      "elements",
        description="Simulate a case at a design at its own step h, at h/2 and h/4 (the time "
                    "step's error estimate, and whether each response is in its asymptotic "
                    "range) and with twice the elements of every beam, and print each "
                    "response's change beside its estimated error, with a verdict. Exit "
                    "status 0 when every response converged to --rtol, 1 otherwise.")
    add_case_arguments(p)
    p.add_argument("--design", metavar="X1,X2,...",
                   help="design variables in their units (one value: all of them); default: "
                        "the case's start")
    p.add_argument("--rtol", type=float, default=1e-2, metavar="R",
                   help="relative accuracy asked of every response (default 1e-2)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args):

    prob = problem_from_args(args)
    if not prob.description.responses:
        raise CaseError(f"case {prob.description.case.name!r} has no responses: nothing to "
                        f"check; add a [[responses]] table (docs/case-format.md), or "
                        f"`flexmbs simulate` for the motion alone")
    report = convergence_check(prob, design_from_text(args.design, prob), rtol=args.rtol)
    if args.json:
        print_json(report.to_json())
    else:
        print(report.summary())
    return 0 if report.converged else 1
