"""``flexmbs simulate``: a case at a design, every response, the constraints; its results
(.npz) and an overview figure."""
from __future__ import annotations

import json

import numpy as np

from flexmbs.cli.common import (add_case_arguments, add_design_arguments, design_from_text,
                                figure_file, output_file, path_text, print_evaluation,
                                print_json, problem_from_args)
from flexmbs.cli.common import evaluate_case, evaluation_json
from flexmbs.files import atomic_open, save_figure


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
        from flexmbs.visual.plots import plot_overview
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

    hist = {f"response_{k}": np.asarray(v) for k, v in ev.values.items()}
    with atomic_open(path, "wb") as fh:       # a file object: numpy adds no suffix
        np.savez_compressed(
            fh, t=result.t, q=result.q, qd=result.qd, dofs=result.dofs, design=ev.x,
            variables=np.array(prob.variables), reference_q=prob.mechanism.reference.q,
            constraints=ev.constraints, summary=json.dumps(ev.to_json()),
            **prob.mechanism.layout(result.dofs), **hist)
