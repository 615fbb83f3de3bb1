"""``flexmbs animate CASE --out FILE``: the motion of a design as a film (.gif, .mp4) or as a
ParaView time series (.pvd), docs/visualization.md."""
from __future__ import annotations

import argparse
import os

from flexmbs.cli.common import (add_case_arguments, announce_run, at_least_two, design_from_text,
                                output_file, path_text, print_json, problem_from_args)
from flexmbs.errors import ModelError

__all__ = ["register", "run", "OUTPUTS"]

#: --out suffixes and what each writes
OUTPUTS = {".gif": "a GIF film (Pillow)", ".mp4": "an MP4 film (H.264, imageio-ffmpeg's ffmpeg)",
           ".pvd": "a ParaView time series (.pvd and a folder of .vtu frames, meshio)"}


def _positive(text):
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def register(subparsers):
    from flexmbs.visual.animation import COLOR_BY, DEFAULT_FPS, DEFAULT_FRAMES

    p = subparsers.add_parser(
        "animate", help="the motion of a design as a film (.gif, .mp4) or a ParaView time "
                        "series (.pvd)",
        description="Simulate a case at a design and write its motion: a film (.gif or .mp4: "
                    "every body, the deflection magnified over the rigid reference drawn as a "
                    "ghost, the beams coloured by a response, a time label, the constrained "
                    "histories underneath with a moving marker) or a ParaView time series "
                    "(.pvd: every body's nodes and elements with displacement, rotation, "
                    "strains, stress and deviation as fields). docs/visualization.md.")
    add_case_arguments(p)
    p.add_argument("--design", metavar="X1,X2,...",
                   help="design variables in their units (one value: all of them); default: "
                        "the case's start")
    p.add_argument("--out", type=path_text, required=True, metavar="FILE",
                   help="the file to write; its suffix chooses what: "
                        + "; ".join(f"{k} {v}" for k, v in OUTPUTS.items()))
    p.add_argument("--frames", type=at_least_two, default=None, metavar="N",
                   help=f"time steps shown, spread evenly over the run (first and last "
                        f"included); default {DEFAULT_FRAMES} for a film, every step for .pvd")
    p.add_argument("--fps", type=_positive, default=DEFAULT_FPS, metavar="F",
                   help=f"frames per second of a film (default {DEFAULT_FPS})")
    p.add_argument("--magnify", type=_positive, default=None, metavar="S",
                   help="deflection magnification of a film; default: a round factor that "
                        "makes the largest deflection about 8%% of the mechanism's size "
                        "(printed on every frame)")
    p.add_argument("--color-by", choices=tuple(COLOR_BY), default="deviation",
                   help="what colours the beams of a film: each node's deviation from the rigid "
                        "reference (default), each element's normal stress, or nothing")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a summary")
    p.set_defaults(func=run)


def out_kind(path, option="--out"):
    """The suffix of an --out file, lower case; ModelError naming the value and the allowed
    suffixes otherwise."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in OUTPUTS:
        raise ModelError(f"{option} {path!r}: unknown suffix {ext or '(none)'!r}; allowed: "
                         f"{', '.join(OUTPUTS)}")
    return ext


def run(args):
    from flexmbs.visual.animation import DEFAULT_FRAMES, animate
    from flexmbs.visual.export import frame_folder, to_vtk

    ext = out_kind(args.out)
    out = output_file(args.out, "--out")       # checked before the run
    if ext == ".pvd":
        frame_folder(out)
    prob = problem_from_args(args)
    x = design_from_text(args.design, prob)
    announce_run(prob, "animate")
    ev = prob.evaluate(x, gradient=False, store="all")
    summary = {"case": prob.description.case.name, "out": out, "design": list(ev.x)}
    if ext == ".pvd":
        _, files, steps = to_vtk(prob, ev.result, out, frames=args.frames)
        every = int(round((steps[-1] - steps[0]) / max(steps.size - 1, 1)))
        summary.update(frames=len(files), folder=os.path.dirname(files[0]), every=every)
        line = f"{len(files)} frames (one every {every} time steps) in {summary['folder']}"
    else:
        a = animate(prob, ev.result, out, evaluation=ev,
                    frames=args.frames if args.frames is not None else DEFAULT_FRAMES,
                    fps=args.fps, magnification=args.magnify, color_by=args.color_by)
        summary.update(frames=a.frames, fps=a.fps, magnification=a.magnification,
                       color_by=a.color_by, color_max=a.color_max, unit=a.unit,
                       seconds=a.wall_time)
        line = a.describe()
    if args.json:
        print_json(summary)
    else:
        print(f"{prob.description.case.name}: {out}")
        print(f"  {line}")
    return 0
