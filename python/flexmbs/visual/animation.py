"""The motion of a simulated mechanism as a film: GIF (Pillow) or MP4 (ffmpeg).

`animate(problem, result, path)` draws, frame by frame (matplotlib, Agg canvas, no pyplot):

- every body at the frame's time: the beams as their deformed centre lines (through every
  node), coloured by a chosen response (`color_by`: the deviation of each node from its place
  in the rigid reference, or the normal stress of each element), the rigid bodies as their
  outlines, the point masses as squares, the joints (ground pins and clamps as triangles,
  joints between bodies as circles);
- the deflection magnified by a stated factor (rigid + factor (flexible - rigid): the joints
  stay joined), printed on the frame, beside the rigid reference drawn as a grey ghost;
- the rigid paths of the points that deviation responses follow (dotted), a time label;
- underneath, the constrained histories of an Evaluation (each response over its upper limit,
  so that several of them share the axis and the limit is the line at 1; a lower limit is the
  line at lower / upper), with a moving marker at the frame's time. No panel when the case has no constrained history.

The frames are `frames` time steps spread evenly over the run (first and last included; a
1301-step run at the default 100 frames shows every 13th step), played at `fps` frames per
second. GIFs are written by Pillow, MP4s (H.264) by the ffmpeg binary that the imageio-ffmpeg
package ships (`ffmpeg_exe`). The file is written under a temporary name beside `path` and
renamed when complete; an MP4 is renamed only after ffmpeg has read it back with every frame.
A film that cannot be written whole (a full disk, a file size limit) raises ResourceError and
leaves no file; an interrupted one (Ctrl-C, SIGTERM on the command line) leaves no file either.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from flexmbs.errors import ModelError
from flexmbs.files import atomic_path, write_failure
from flexmbs.visual.plots import (_followed_points, _LIMIT_COLOR, _RIGID_COLOR, constrained_histories,
                           nice_magnification)
from flexmbs.visual.scene import frame_steps, scene

__all__ = ["animate", "Animation", "FORMATS", "COLOR_BY", "DEFAULT_FRAMES", "DEFAULT_FPS",
           "ffmpeg_exe", "default_magnification"]

#: File suffixes `animate` writes, and by what.
FORMATS = {".gif": "Pillow (matplotlib's PillowWriter)",
           ".mp4": "ffmpeg from imageio-ffmpeg (matplotlib's FFMpegWriter, H.264)"}
#: What the beams may be coloured by: name -> (scene field, scale, unit, label).
COLOR_BY = {"deviation": ("deviation", 1e3, "mm", "deviation from the rigid reference"),
            "stress": ("stress", 1e-6, "MPa", "normal stress"),
            "none": (None, 1.0, "", "")}
DEFAULT_FRAMES = 100
DEFAULT_FPS = 20
#: the default magnification makes the largest deflection about this fraction of the
#: mechanism's size (rounded down to 1, 2 or 5 x 10^k)
MAGNIFIED_FRACTION = 0.08


@dataclass
class Animation:
    """What `animate` wrote: path, frames, fps, the steps shown (0-based), the magnification,
    the response the beams are coloured by and its largest value over the frames (in `unit`),
    the seconds spent."""
    path: str
    frames: int
    fps: float
    steps: np.ndarray
    magnification: float
    color_by: str
    color_max: float
    unit: str
    wall_time: float

    def describe(self):
        """One line for people."""
        every = int(round(np.median(np.diff(self.steps)))) if self.steps.size > 1 else 1
        return (f"{self.frames} frames (one every {every} time steps) at {self.fps:g} fps "
                f"({self.frames / self.fps:.1f} s), deflection x {self.magnification:g}"
                + (f", coloured by {self.color_by} (max {self.color_max:.4g} {self.unit})"
                   if self.color_by != "none" else "") + f", {self.wall_time:.1f} s")


def ffmpeg_exe():
    """The ffmpeg binary of the imageio-ffmpeg package (installed with flexmbs)."""
    try:
        import imageio_ffmpeg
    except ImportError:       # pragma: no cover - a dependency of the package
        raise ModelError("MP4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg), "
                         "or write a .gif") from None
    return imageio_ffmpeg.get_ffmpeg_exe()


def check_format(path, what="path"):
    """The suffix of an animation file, lower case; ModelError naming the value and the
    allowed suffixes otherwise."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in FORMATS:
        raise ModelError(f"{what} {os.fspath(path)!r}: unknown animation format {ext or '(none)'!r}; "
                         f"allowed: {', '.join(FORMATS)}")
    return ext


def default_magnification(sc):
    """A round factor that makes the largest deflection of a Scene about MAGNIFIED_FRACTION of
    the mechanism's size (1 when nothing deflects)."""
    dmax = float(np.max(sc.deviation)) if sc.deviation.size else 0.0
    return nice_magnification(MAGNIFIED_FRACTION * sc.size() / dmax) if dmax > 0 else 1.0


def _beam_pairs(sc):
    """(m, 2) point indices of the beams' segments and (m,) their cells."""
    pairs, owner = [], []
    for c, (_, k, idx) in enumerate(sc.cells):
        if k == "beam":
            for a, b in zip(idx[:-1], idx[1:]):
                pairs.append((a, b))
                owner.append(c)
    return np.array(pairs, int).reshape(-1, 2), np.array(owner, int)


def _segment_values(sc, color_by, pairs, owner):
    """(k, m) value of every beam segment at every frame, in the unit of COLOR_BY."""
    name, scale, _, _ = COLOR_BY[color_by]
    if name is None:
        return None
    if name == "deviation":
        dev = sc.deviation
        return 0.5 * (dev[:, pairs[:, 0]] + dev[:, pairs[:, 1]]) * scale
    v = sc.cell_fields[name][:, owner] * scale
    if not np.any(np.isfinite(v)):
        raise ModelError(f"color_by={color_by!r}: no beam of this case has a {name} (a "
                         "section without a depth has no stress); allowed: "
                         f"{', '.join(COLOR_BY)}")
    return v


def _history_rows(problem, evaluation):
    """[(label, history / upper limit, lower limit / upper limit or None)] of the constrained
    histories with a positive upper limit."""
    if evaluation is None:
        return []
    lower = {}
    for c in problem.description.constraints:
        if c.lower is not None:
            lower[c.response] = max(lower.get(c.response, c.lower), c.lower)
    rows = []
    for name, v, limit in constrained_histories(problem, evaluation.values):
        if limit is not None and limit > 0:
            low = lower.get(name)
            rows.append((f"{name} / {limit:g}", np.asarray(v, float) / limit,
                         None if low is None else low / limit))
    return rows


def _check_evaluation(problem, result, evaluation):
    """ModelError when `evaluation` is not of the motion `result` draws: another design (its
    x against the result's design, Result.design), another problem's variables, or another
    time grid."""
    if evaluation is None:
        return
    names = list(getattr(evaluation, "variables", None) or [])
    if names and names != list(problem.variables):
        raise ModelError(f"evaluation is of the variables {names}, the problem's are "
                         f"{list(problem.variables)}: give the evaluation of the design drawn")
    ex = np.asarray(evaluation.x, float)
    rx = getattr(result, "design", None)
    if rx is not None and (ex.shape != np.shape(rx) or not np.array_equal(ex, rx)):
        raise ModelError(f"evaluation is of design x = {_design_text(ex)}, the motion drawn "
                         f"is of design {_design_text(rx)}: give the evaluation of the "
                         "simulated design (Problem.evaluate(x, store='all') gives both, the "
                         "motion as evaluation.result)")
    t = np.asarray(evaluation.t, float)
    if t.shape != result.t.shape or not np.array_equal(t, result.t):
        raise ModelError(f"evaluation's time grid ({t.size} times up to "
                         f"{t[-1] if t.size else 0:.6g} s) is not the motion's "
                         f"({result.t.size} times up to {result.t[-1]:.6g} s): give the "
                         "evaluation of the simulated design")


def _design_text(x):
    return "[" + ", ".join(f"{v:.6g}" for v in np.ravel(x)) + "]"


def animate(problem, result, path, *, evaluation=None, frames=DEFAULT_FRAMES, fps=DEFAULT_FPS,
            magnification=None, color_by="deviation", dpi=100, title=None):
    """Write the motion of a simulated design to `path` (.gif or .mp4, see FORMATS).

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    result : flexmbs.analysis.simulate.Result of the problem, simulated with store='all'
    path : file name; its suffix chooses the format
    evaluation : flexmbs.problem.Evaluation of the same design, optional: its constrained
        histories are drawn underneath (Problem.evaluate(x, store='all') gives both the
        evaluation and the result, as evaluation.result); one of another design (its x
        against Result.design), of another problem's variables or on another time grid is a
        ModelError
    frames : int >= 2 or None (every step), default DEFAULT_FRAMES
    fps : frames per second of the film, default DEFAULT_FPS
    magnification : float > 0, optional
        Deflection factor; default `default_magnification` (a round number making the largest
        deflection about 8 % of the mechanism's size). Printed on every frame.
    color_by : {'deviation', 'stress', 'none'}
    dpi : pixels per inch of the 8-inch-wide frames
    title : str, optional (default: the case's name)

    Returns
    -------
    Animation
    """
    import time

    t0 = time.perf_counter()
    ext = check_format(path)
    if color_by not in COLOR_BY:
        raise ModelError(f"color_by={color_by!r} is unknown; allowed: {', '.join(COLOR_BY)}")
    if not (isinstance(fps, (int, float)) and 0 < fps <= 120):
        raise ModelError(f"fps must be a number in (0, 120], got {fps!r}")
    if frames is not None and (not isinstance(frames, (int, np.integer)) or frames < 2):
        raise ModelError(f"frames must be an integer >= 2 or None (every step), got {frames!r}")
    _check_evaluation(problem, result, evaluation)
    steps = frame_steps(result.t.size, frames)
    sc = scene(problem, result, steps)
    if magnification is None:
        magnification = default_magnification(sc)
    elif not (isinstance(magnification, (int, float)) and np.isfinite(magnification)
              and magnification > 0):
        raise ModelError(f"magnification must be a positive number, got {magnification!r}")
    pairs, owner = _beam_pairs(sc)
    values = _segment_values(sc, color_by, pairs, owner)
    rows = _history_rows(problem, evaluation)

    fig, draw = _figure(problem, result, sc, magnification, color_by, pairs, values, rows,
                        evaluation, title, dpi)
    with atomic_path(path, suffix=ext) as tmp:
        try:
            _WRITERS[ext](tmp, _frames(fig, draw, steps.size), fps)
        except OSError as exc:      # ENOSPC, EFBIG; ffmpeg ended early (a broken pipe)
            raise write_failure(path, "the film", exc) from None
        if ext == ".mp4":
            _check_film(path, tmp, steps.size)
    vmax = float(np.nanmax(values)) if values is not None else 0.0
    return Animation(path=os.fspath(path), frames=int(steps.size), fps=float(fps), steps=steps,
                     magnification=float(magnification), color_by=color_by, color_max=vmax,
                     unit=COLOR_BY[color_by][2], wall_time=time.perf_counter() - t0)


def _frames(fig, draw, n):
    """The n frames as (h, w, 3) uint8 arrays, h and w even (what H.264 needs). The figure's
    still parts are drawn once; each frame restores them and draws only its moving artists
    (matplotlib's blitting: a full redraw per frame spent 0.24 s, mostly on the tick labels)."""
    canvas = fig.canvas
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    for j in range(n):
        canvas.restore_region(background)
        for artist in draw(j):
            artist.axes.draw_artist(artist)
        rgba = np.asarray(canvas.buffer_rgba())
        h, w = rgba.shape[0] // 2 * 2, rgba.shape[1] // 2 * 2
        yield np.ascontiguousarray(rgba[:h, :w, :3])


def _write_gif(path, frames, fps):
    """Frames to a looping GIF with Pillow (one adaptive palette per frame)."""
    from PIL import Image

    images = [Image.fromarray(f).quantize(colors=256, method=Image.Quantize.FASTOCTREE)
              for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=int(round(1000 / fps)), loop=0, optimize=False)


def _write_mp4(path, frames, fps):
    """Frames to an H.264 MP4 (yuv420p, plays everywhere) with imageio-ffmpeg's ffmpeg."""
    import imageio_ffmpeg

    frames = iter(frames)
    first = next(frames)
    h, w = first.shape[:2]
    out = imageio_ffmpeg.write_frames(path, (w, h), fps=fps, codec="libx264",
                                      pix_fmt_out="yuv420p", macro_block_size=1,
                                      quality=7, ffmpeg_log_level="error")
    out.send(None)
    try:
        out.send(first)
        for f in frames:
            out.send(f)
    finally:
        out.close()


def _check_film(path, tmp, n):
    """ResourceError (naming `path`) unless the MP4 written to `tmp` holds its n frames, as
    ffmpeg reads them back: ffmpeg that cannot write (a full disk, a file size limit) may end
    with a cut file, unplayable without its index, and imageio-ffmpeg does not report it."""
    import imageio_ffmpeg

    try:
        got, _ = imageio_ffmpeg.count_frames_and_secs(tmp)
    except (RuntimeError, OSError):
        got = None
    if got != n:
        size = os.path.getsize(tmp) if os.path.exists(tmp) else 0
        held = "no readable frames" if got is None else f"{got} of its {n} frames"
        raise write_failure(path, "the film", f"ffmpeg wrote {size} bytes holding {held}")


_WRITERS = {".gif": _write_gif, ".mp4": _write_mp4}


def _limits(sc, shown):
    pts = np.concatenate([shown.reshape(-1, 2), sc.rigid.reshape(-1, 2)])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.08 * max(float(np.max(hi - lo)), 1e-9)
    return (lo[0] - pad, hi[0] + pad), (lo[1] - pad, hi[1] + pad)


def _figure(problem, result, sc, magnification, color_by, pairs, values, rows, evaluation,
            title, dpi):
    """The figure and a function drawing frame j into it."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    shown = sc.magnified(magnification)
    xlim, ylim = _limits(sc, shown)
    # the motion panel as high as the mechanism's aspect asks (5.8 inches wide), within limits
    high = float(np.clip(5.8 * (ylim[1] - ylim[0]) / (xlim[1] - xlim[0]), 2.2, 6.0)) + 1.0
    hist_high = 2.0 if rows else 0.0
    fig = Figure(figsize=(8.0, high + hist_high), dpi=dpi)
    FigureCanvasAgg(fig)
    if rows:
        ax, axh = fig.subplots(2, 1, gridspec_kw=dict(height_ratios=[high, hist_high]))
    else:
        ax, axh = fig.add_subplot(), None
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.25)
    mech = problem.mechanism
    ref = mech.reference.q
    for k, (body, point) in enumerate(_followed_points(problem)):
        n = mech.node[(body, point)]
        ax.plot(ref[:, 3 * n], ref[:, 3 * n + 1], ":", color=_RIGID_COLOR, lw=1,
                label="rigid paths of followed points" if k == 0 else None)
    rigid_pairs = [(a, b) for _, k, idx in sc.cells if k in ("beam", "rigid")
                   for a, b in zip(idx[:-1], idx[1:])]
    rigid_pairs = np.array(rigid_pairs, int).reshape(-1, 2)
    ghost = LineCollection([], colors=_RIGID_COLOR, linestyles="--", lw=1.0, zorder=2,
                           label="rigid reference")
    ax.add_collection(ghost)
    cmap = colormaps["viridis"].with_extremes(bad="0.4")
    norm = None
    if values is not None:
        name, _, unit, label = COLOR_BY[color_by]
        norm = Normalize(0.0, max(float(np.nanmax(values)), 1e-300))
    beams = LineCollection([], cmap=cmap if values is not None else None, norm=norm, lw=2.6,
                           colors=None if values is not None else "#1f4e9c", zorder=3,
                           capstyle="round", label=f"flexible, deflection x {magnification:g}")
    ax.add_collection(beams)
    if values is not None:
        cb = fig.colorbar(beams, ax=ax, shrink=0.9, pad=0.02, fraction=0.04)
        cb.set_label(f"{label} ({unit})")
    rpairs = np.array([(a, b) for _, k, idx in sc.cells if k == "rigid"
                       for a, b in zip(idx[:-1], idx[1:])], int).reshape(-1, 2)
    rigid = LineCollection([], colors="0.15", lw=4.0, alpha=0.75, zorder=3,
                           capstyle="round", label="rigid bodies" if rpairs.size else None)
    ax.add_collection(rigid)
    mass_idx = [idx[0] for _, k, idx in sc.cells if k == "mass"]
    masses, = ax.plot([], [], "s", color="0.1", ms=9, zorder=5,
                      label="point masses" if mass_idx else None)
    ground_idx = [i for _, i, g in sc.joints if g]
    hinge_idx = [i for _, i, g in sc.joints if not g]
    grounds, = ax.plot([], [], "^", color="k", ms=9, zorder=6)
    hinges, = ax.plot([], [], "o", color="w", mec="k", ms=6, zorder=6)
    clock = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top", fontsize=11,
                    family="monospace", bbox=dict(fc="w", ec="0.7", alpha=0.85))
    ax.text(0.98, 0.97, f"deflection x {magnification:g}", transform=ax.transAxes, va="top",
            ha="right", fontsize=10, bbox=dict(fc="w", ec="0.7", alpha=0.85))
    ax.legend(fontsize=7, loc="lower right", framealpha=0.85)
    ax.set_title(title if title is not None else problem.description.case.name, fontsize=11)
    marker = dots = None
    if rows:
        t = np.asarray(evaluation.t)
        lines = []
        for k, (label, v, _) in enumerate(rows):
            lines.append(axh.plot(t, v, lw=1.2, ls=("-", "--", ":", "-.")[k % 4], label=label)[0])
        axh.axhline(1.0, color=_LIMIT_COLOR, ls="--", lw=1.0, label="limits")
        lows = sorted({low for _, _, low in rows if low is not None})
        for low in lows:
            axh.axhline(low, color=_LIMIT_COLOR, ls="--", lw=1.0)
        axh.set_xlim(0, float(t[-1]))
        top = max(1.0, max(float(np.nanmax(v)) for _, v, _ in rows))
        bottom = min([0.0] + lows + [float(np.nanmin(v)) for _, v, _ in rows])
        axh.set_ylim(bottom - 0.15 * (top - bottom) * (bottom < 0), 1.15 * top)
        axh.set_xlabel("time (s)")
        axh.set_ylabel("response / limit")
        axh.grid(alpha=0.3)
        axh.legend(fontsize=7, loc="best", framealpha=0.85, ncol=min(len(rows) + 1, 3))
        marker = axh.axvline(0.0, color="k", lw=1.0)
        dots, = axh.plot([], [], "o", color="k", ms=4, zorder=4)
        hist = np.array([v for _, v, _ in rows])
    fig.subplots_adjust(left=0.1, right=0.97 if values is None else 0.89, top=1 - 0.35 / fig.get_figheight(),
                        bottom=0.5 / fig.get_figheight(), hspace=0.9 / (high + hist_high) * 2)

    def draw(j):
        p, r = shown[j], sc.rigid[j]
        ghost.set_segments(r[rigid_pairs])
        beams.set_segments(p[pairs])
        if values is not None:
            beams.set_array(values[j])
        rigid.set_segments(p[rpairs])
        masses.set_data(p[mass_idx, 0], p[mass_idx, 1])
        grounds.set_data(p[ground_idx, 0], p[ground_idx, 1])
        hinges.set_data(p[hinge_idx, 0], p[hinge_idx, 1])
        clock.set_text(f"t = {sc.t[j]:.4f} s")
        if marker is not None:
            k = int(sc.steps[j])
            marker.set_xdata([sc.t[j], sc.t[j]])
            dots.set_data(np.full(len(rows), sc.t[j]), hist[:, k])
        return moving

    moving = [ghost, beams, rigid, masses, grounds, hinges, clock]
    if marker is not None:
        moving += [marker, dots]
    for artist in moving:
        artist.set_animated(True)
    return fig, draw
