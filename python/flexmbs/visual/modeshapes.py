"""Mode shapes drawn over the configuration they belong to (`plot_modes`) and one mode's
oscillation as a film (`animate_mode`), for `flexmbs modes` (flexmbs.analysis.modes.Modes).

Each beam is drawn through its nodes; the configuration in grey, the mode shape on top, its
displacements scaled so that the largest translation is SHAPE_FRACTION of the mechanism's
size (a mode shape has no amplitude of its own)."""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from flexmbs.errors import ModelError
from flexmbs.files import atomic_path, save_figure
from flexmbs.visual.animation import _WRITERS, _frames, check_format

__all__ = ["plot_modes", "animate_mode", "SHAPE_FRACTION"]

#: the largest translation of a drawn mode, as a fraction of the mechanism's size
SHAPE_FRACTION = 0.1


def _chains(model):
    """[(body name, its nodes in order)] of the bodies with two nodes or more."""
    return [(b.name, np.asarray(b.nodes, int)) for b in model.bodies.values()
            if len(b.nodes) >= 2]


def _xy(q):
    q = np.asarray(q, float)
    return np.column_stack([q[0::3], q[1::3]])


def _scale(xy):
    size = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    return SHAPE_FRACTION * (size if size > 0 else 1.0)


def _draw_base(ax, chains, xy):
    for _, nodes in chains:
        ax.plot(xy[nodes, 0], xy[nodes, 1], color="0.7", lw=2.5, solid_capstyle="round")
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def _label(modes, i):
    z = float(modes.damping[i])
    damp = "undamped" if z < 1e-6 else f"damping {100 * z:.2g} %"
    return f"mode {i + 1}: {modes.frequency[i]:.4g} Hz, {damp}"


def plot_modes(model, q, modes, file=None, *, count=None, title=None):
    """One panel per mode (the first `count`, default all, at most 12): the configuration q
    in grey, the mode shape over it. Returns the Figure (saved to `file` when given)."""
    n = min(len(modes) if count is None else int(count), 12)
    if n < 1:
        raise ModelError("plot_modes: there is no mode to draw (the configuration has no "
                         "elastic mode)")
    xy, chains = _xy(q), _chains(model)
    s = _scale(xy)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(4.0 * cols, 3.2 * rows))
    for i in range(n):
        ax = fig.add_subplot(rows, cols, i + 1)
        _draw_base(ax, chains, xy)
        shown = xy + s * modes.shapes[i][:, :2]
        for _, nodes in chains:
            ax.plot(shown[nodes, 0], shown[nodes, 1], color="#1f77b4", lw=1.8)
        ax.set_title(_label(modes, i), fontsize=9)
    fig.suptitle(title or f"modes at t = {modes.t:.4g} s", fontsize=11)
    fig.tight_layout()
    if file is not None:
        save_figure(fig, file, dpi=120)
    return fig


def animate_mode(model, q, modes, index, path, *, frames=40, fps=20, title=None):
    """Write mode `index` (0-based) oscillating about configuration q over one period as a
    film (.gif or .mp4, flexmbs.visual.animation's writers). Returns the path."""
    ext = check_format(path)
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or \
            not 0 <= index < len(modes):
        raise ModelError(f"animate_mode: mode {index!r} is not among the {len(modes)} modes "
                         f"computed (0-based index)")
    xy, chains = _xy(q), _chains(model)
    s = _scale(xy)
    shape = modes.shapes[index][:, :2]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = Figure(figsize=(6.4, 4.8), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    _draw_base(ax, chains, xy)
    lo = np.minimum(xy - s * np.abs(shape), xy).min(axis=0)
    hi = np.maximum(xy + s * np.abs(shape), xy).max(axis=0)
    pad = 0.05 * float(np.max(hi - lo))
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_title(title or f"{_label(modes, index)} (t = {modes.t:.4g} s)", fontsize=10)
    lines = [ax.plot([], [], color="#1f77b4", lw=2.0, animated=True)[0] for _ in chains]

    def draw(j):
        shown = xy + s * math.sin(2.0 * math.pi * j / frames) * shape
        for line, (_, nodes) in zip(lines, chains):
            line.set_data(shown[nodes, 0], shown[nodes, 1])
        return lines

    with atomic_path(path, suffix=ext) as tmp:
        _WRITERS[ext](tmp, _frames(fig, draw, frames), fps)
    return path
