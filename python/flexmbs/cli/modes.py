"""``flexmbs modes CASE``: the vibration modes of a design at configurations of its motion
(flexmbs.analysis.modes), and the lightly damped modes the case's step cannot resolve."""
from __future__ import annotations

import argparse

from flexmbs.cli.common import (add_case_arguments, design_from_text, figure_file, output_file,
                                path_text, positive_int, print_json, problem_from_args)
from flexmbs.errors import ModelError

__all__ = ["register", "run"]


def _times(text):
    try:
        v = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        v = []
    if not v:
        raise argparse.ArgumentTypeError(f"expected times in s, e.g. 0.3 or 0,0.1,0.2, got "
                                         f"{text!r}")
    return v


def register(subparsers):
    p = subparsers.add_parser(
        "modes", help="vibration modes at configurations of the motion, and the modes the "
                      "step cannot resolve",
        description="Simulate a case at a design, linearize it at configurations of its "
                    "motion (--at; default the start) and print the lowest vibration modes: "
                    "frequency, damping ratio and the bodies that move. Then list the lightly "
                    "damped modes the responses see that the case's step does not resolve "
                    "(their answer depends on the integrator's numerical damping). "
                    "docs/modes.md.")
    add_case_arguments(p)
    p.add_argument("--design", metavar="X1,X2,...",
                   help="design variables in their units (one value: all of them); default: "
                        "the case's start")
    p.add_argument("--count", type=positive_int, default=6, metavar="N",
                   help="modes printed per configuration, lowest first (default 6; a 0 Hz "
                        "motion of the mechanism counts as one)")
    p.add_argument("--at", type=_times, default=None, metavar="T[,T...]",
                   help="times (s) of the configurations; default the start")
    p.add_argument("--plot", type=path_text, default=None, metavar="FILE.png",
                   help="draw the modes at the first time over its configuration")
    p.add_argument("--animate", type=path_text, default=None, metavar="FILE.gif|.mp4",
                   help="a film of one mode (--mode) oscillating at the first time")
    p.add_argument("--mode", type=positive_int, default=None, metavar="K",
                   help="the mode --animate shows, 1 = the lowest (default: the lowest above "
                        "0 Hz)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args):
    from flexmbs.analysis.modes import moving_bodies, modes_of_result, resolved_limit

    plot = figure_file(args.plot, "--plot") if args.plot else None
    film = output_file(args.animate, "--animate") if args.animate else None
    if film is not None:
        from flexmbs.visual.animation import check_format
        check_format(film, "--animate")
    prob = problem_from_args(args)
    x = design_from_text(args.design, prob)
    result = prob.simulate(x, store="all")
    model = result.design_model
    at = args.at if args.at is not None else [float(result.t[0])]
    found = modes_of_result(model, result, at, count=args.count)
    ts = prob.description.time
    unresolved = prob.modal_check(x, result).unresolved(ts.grid_h, ts.rho_inf)
    owners = {b.name: b.nodes for b in model.bodies.values()}
    if plot is not None:
        from flexmbs.visual.modeshapes import plot_modes
        q0 = result.q[int(abs(result.t - found[0].t).argmin())]
        plot_modes(model, q0, found[0], plot, title=f"{prob.description.case.name}: modes at "
                                                     f"t = {found[0].t:.4g} s")
    if film is not None:
        from flexmbs.visual.modeshapes import animate_mode
        md = found[0]
        if args.mode is not None:
            k = args.mode - 1
        else:
            elastic = [i for i in range(len(md)) if md.frequency[i] > 0]
            if not elastic:
                raise ModelError("--animate: no mode above 0 Hz among those computed; raise "
                                 "--count")
            k = elastic[0]
        if k >= len(md):
            raise ModelError(f"--mode {k + 1}: only {len(md)} modes computed (--count)")
        q0 = result.q[int(abs(result.t - md.t).argmin())]
        animate_mode(model, q0, md, k, film)
    if args.json:
        design = prob.mechanism.start if x is None else prob.mechanism.design_values(x)
        print_json({"case": prob.description.case.name, "design": [float(v) for v in design],
                    "h": ts.grid_h, "rho_inf": ts.rho_inf,
                    "resolved_omega_h": resolved_limit(ts.rho_inf),
                    "modes": [m.to_json() for m in found],
                    "unresolved": {k: [u.to_json() for u in v] for k, v in unresolved.items()},
                    "plot": plot, "animate": film})
        return 0
    print(f"{prob.description.case.name}: vibration modes (step h = {ts.grid_h:g} s, rho_inf "
          f"{ts.rho_inf:g}: resolved up to omega h = {resolved_limit(ts.rho_inf):.3g}, "
          f"{resolved_limit(ts.rho_inf) / (6.283185307179586 * ts.grid_h):.4g} Hz)")
    for md in found:
        print(f"  t = {md.t:.4g} s ({md.free} coordinates the joints leave free)")
        for i in range(len(md)):
            z = float(md.damping[i])
            damp = "undamped" if z < 1e-6 else f"damping ratio {z:.3g}"
            moving = ", ".join(moving_bodies(md.shapes[i], owners))
            print(f"    {i + 1:3d}  {md.frequency[i]:12.5g} Hz  {damp:22s} {moving}")
    if unresolved:
        print("  modes the step does not resolve:")
        for v in unresolved.values():
            for u in v:
                print(f"    {u.describe()}")
    else:
        print("  every lightly damped mode the responses see is resolved by the step")
    if plot:
        print(f"  figure {plot}")
    if film:
        print(f"  film {film}")
    return 0
