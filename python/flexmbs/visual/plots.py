"""Figures of simulated problems, written to files with matplotlib's Agg canvas.

No pyplot and no global backend change: every function builds its own `Figure` (or draws
into a given Axes) and, if `file` is given, saves it there. The figures:

- `plot_histories`: response histories (e.g. deviations) with their limit line, as the paper's
  Figs. 5(b), 6(b), 8(b);
- `plot_motion`: a few postures of the flexible mechanism over its rigid reference, with the
  deflection magnified, the named points marked and the rigid paths of the points that a
  deviation response follows;
- `plot_overview`: both side by side, the figure that ``flexmbs simulate --plot`` writes.

Examples
--------
>>> from flexmbs.problem import Problem
>>> from flexmbs.visual.plots import plot_overview
>>> prob = Problem("robot_2dof")
>>> x = [39.29, 28.33, 34.94, 25.19]
>>> fig = plot_overview(prob, prob.simulate(x, store="all"), prob.evaluate(x, gradient=False),
...                     "robot_table1.png")                                # doctest: +SKIP
"""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from flexmbs.files import save_figure
from flexmbs.visual.scene import scene
from flexmbs.model.description import Deviation

__all__ = ["plot_histories", "plot_motion", "plot_overview", "magnified_postures",
           "nice_magnification", "constrained_histories", "place_labels"]

_LIMIT_COLOR = "#c0392b"
_RIGID_COLOR = "0.55"


def _save(fig, file):
    if file is not None:
        save_figure(fig, file, dpi=150, bbox_inches="tight")
    return fig


def constrained_histories(problem, values):
    """[(name, history, upper limit or None)] of the constrained time-history responses of an
    Evaluation's values (deviations first)."""
    resp = {r.name: r for r in problem.description.responses}
    out = {}
    for c in problem.description.constraints:
        v = values.get(c.response)
        if v is None or np.ndim(v) == 0:
            continue
        lim = out.get(c.response, (None, None, None))[2]
        if c.upper is not None:
            lim = c.upper if lim is None else min(lim, c.upper)
        out[c.response] = (c.response, np.asarray(v, float), lim)
    return sorted(out.values(), key=lambda e: not isinstance(resp[e[0]], Deviation))


def plot_histories(t, histories, file=None, *, ax=None, title=None, scale=1e3, unit="mm"):
    """Histories of responses with their limit lines and maxima.

    Parameters
    ----------
    t : (nt,) time
    histories : list of (label, (nt,) values, limit or None)
    scale, unit : the values are drawn as value * scale in `unit` (default m -> mm)
    """
    if ax is None:
        fig = Figure(figsize=(6.4, 3.8))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    colors = ["#1f4e9c", "#e08a00", "#2a9d4b", "#7b3fa0", "#555555"]
    top = 0.0
    for k, (label, v, limit) in enumerate(histories):
        c = colors[k % len(colors)]
        j = int(np.argmax(v))
        top = max(top, float(v[j]))
        ax.plot(t, v * scale, color=c, lw=1.3, ls=("-", "--", ":", "-.")[k % 4],
                label=f"{label}: max {v[j] * scale:.4g} {unit} at {t[j]:.4f} s")
        ax.plot([t[j]], [v[j] * scale], "o", color=c, ms=5, zorder=4)
        if limit is not None and limit > 0:
            if top >= 0.3 * limit:
                ax.axhline(limit * scale, color=_LIMIT_COLOR, ls="--", lw=1.2,
                           label=f"limit of {label} {limit * scale:g} {unit}")
                top = max(top, limit)
            else:
                ax.plot([], [], ls="--", color=_LIMIT_COLOR,
                        label=f"limit of {label} {limit * scale:g} {unit} (off scale, "
                              f"{limit / v[j]:.0f} x the maximum)")
    ax.set_ylim(0, (1.25 + 0.08 * len(histories)) * max(top, 1e-300) * scale)
    ax.set_xlim(0, float(t[-1]))
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"({unit})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", framealpha=0.9)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, file)


def nice_magnification(value):
    """The largest number of the form 1, 2 or 5 x 10^k that is <= value (at least 1)."""
    if not (value > 1):
        return 1.0
    e = math.floor(math.log10(value))
    for m in (5, 2, 1):
        if m * 10 ** e <= value:
            return float(m * 10 ** e)
    return float(10 ** e)  # pragma: no cover


def _positions(q, nodes, steps=None):
    """(k, len(nodes), 2) node positions from coordinates q (nt, ndof)."""
    qq = q if steps is None else q[steps]
    return np.stack([qq[:, 3 * n:3 * n + 2] for n in nodes], axis=1)


def magnified_postures(problem, result, steps, magnification):
    """Node positions of every beam at some steps, flexible (deflection magnified) and rigid.

    The magnified position of a node is rigid + magnification * (flexible - rigid), rigid being
    the node's place in the rigid reference mechanism at the same time.

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    result : flexmbs.analysis.simulate.Result of the problem, simulated with store='all'
    steps : list of int (0-based)
    magnification : float

    Returns
    -------
    dict beam -> (flexible (k, nnodes, 2), rigid (k, nnodes, 2))
    """
    mech = problem.mechanism
    steps = np.asarray(steps, int)
    out = {}
    for b in mech.beams:
        nodes = mech.model.body(b).nodes
        rigid = _positions(mech.reference.q, nodes, steps)
        flex = np.stack([result.position(n)[steps] for n in nodes], axis=1)
        out[b] = (rigid + magnification * (flex - rigid), rigid)
    return out


def _max_deflection(problem, result):
    mech = problem.mechanism
    d = 0.0
    for b in mech.beams:
        nodes = mech.model.body(b).nodes
        rigid = _positions(mech.reference.q, nodes)
        flex = np.stack([result.position(n) for n in nodes], axis=1)
        d = max(d, float(np.max(np.hypot(*(flex - rigid).transpose(2, 0, 1)))))
    return d


def _followed_points(problem):
    """(body, point) of every deviation term at a named point (not a station), in order,
    without repeats."""
    out = []
    for r in problem.description.responses:
        if isinstance(r, Deviation):
            for term in r.terms:
                if isinstance(term.at, str) and (term.body, term.at) not in out:
                    out.append((term.body, term.at))
    return out


def plot_motion(problem, result, file=None, *, ax=None, postures=6, magnification=None,
                title=None, highlight=None):
    """Postures of the flexible mechanism over the rigid one, deflection magnified.

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    result : flexmbs.analysis.simulate.Result of the problem, simulated with store='all'
    file : path, optional
    ax : matplotlib Axes, optional
    postures : int, default 6
        Number of instants, evenly spread over the simulation.
    magnification : float, optional
        Deflection scale; default: a round number that makes the largest deflection about 6 %
        of the mechanism's size.
    title : str, optional
    highlight : int, optional
        A 0-based step added and drawn in red (e.g. the step of the largest deviation).

    Returns
    -------
    matplotlib.figure.Figure
    """
    mech = problem.mechanism
    if ax is None:
        fig = Figure(figsize=(6.4, 5.6))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    nt = result.t.size
    steps = sorted(set(np.linspace(0, nt - 1, postures).round().astype(int).tolist()))
    if highlight is not None:
        near = [k for k in steps if abs(k - highlight) < 0.4 * (nt - 1) / max(postures - 1, 1)]
        steps = sorted(set([k for k in steps if k not in near or k == 0] + [int(highlight)]))
    ref = mech.reference.q
    allnodes = sorted({n for b in mech.beams for n in mech.model.body(b).nodes})
    pts0 = _positions(ref[:1], allnodes)[0]
    size = max(float(np.ptp(pts0[:, 0]) + np.ptp(pts0[:, 1])) / 2, 1e-9)
    if magnification is None:
        dmax = _max_deflection(problem, result)
        magnification = nice_magnification(0.06 * size / dmax) if dmax > 0 else 1.0
    # drop instants whose rigid posture nearly repeats an earlier one (a crank turning more
    # than once), keeping the highlighted instant
    rig = magnified_postures(problem, result, steps, 1.0)
    allpts = np.concatenate([r for _, r in rig.values()], axis=1)
    keep = []
    for j in sorted(range(len(steps)), key=lambda j: steps[j] != highlight):
        if all(np.max(np.hypot(*(allpts[j] - allpts[i]).T)) > 0.05 * size for i in keep):
            keep.append(j)
    steps = [steps[j] for j in sorted(keep)]
    post = magnified_postures(problem, result, steps, magnification)
    # rigid paths of the points that deviation responses follow
    followed = _followed_points(problem)
    for k, (body, point) in enumerate(followed):
        n = mech.node[(body, point)]
        ax.plot(ref[:, 3 * n], ref[:, 3 * n + 1], ":", color=_RIGID_COLOR, lw=1,
                label="rigid paths of " + ", ".join(p for _, p in followed) if k == 0 else None)
    cmap = _colormap()
    label_node = mech.node[followed[0]] if followed else None
    outlines = _rigid_outlines(problem, result, steps, magnification)
    labels = []
    for j, k in enumerate(steps):
        is_hi = k == highlight
        color = _LIMIT_COLOR if is_hi else cmap(j / max(len(steps) - 1, 1))
        for b, (flex, rigid) in post.items():
            ax.plot(rigid[j, :, 0], rigid[j, :, 1], "--", color=_RIGID_COLOR, lw=1.0, zorder=2)
            ax.plot(flex[j, :, 0], flex[j, :, 1], "-", color=color, lw=2.2 if is_hi else 1.6,
                    zorder=3, solid_capstyle="round")
        for flex, rigid in outlines:
            ax.plot(rigid[j, :, 0], rigid[j, :, 1], "--", color=_RIGID_COLOR, lw=1.0, zorder=2)
            ax.plot(flex[j, :, 0], flex[j, :, 1], "-", color=color, lw=4.0, alpha=0.55,
                    zorder=3, solid_capstyle="round")
        if label_node is not None:
            labels.append((f"{result.t[k]:.2f} s" + (" (max)" if is_hi else ""),
                           result.position(label_node)[k], color, is_hi))
    # named points at t = 0; ground pivots as triangles
    grounded = {j.at for j in problem.description.joints if j.type in ("pin", "clamp")}
    drawn = set()
    names = []
    for (body, name), node in mech.node.items():
        if name in drawn:
            continue
        drawn.add(name)
        x, y = ref[0, 3 * node:3 * node + 2]
        ground = name in grounded
        ax.plot([x], [y], "^" if ground else "o", color="k" if ground else "w", mec="k",
                ms=8 if ground else 5, zorder=6)
        names.append(ax.annotate(name, (x, y), textcoords="offset points",
                                 xytext=(-12, -12) if ground else (-12, 6), fontsize=9,
                                 weight="bold", zorder=6))
    ax.plot([], [], "--", color=_RIGID_COLOR, label="rigid reference")
    ax.plot([], [], "-", color=cmap(0.5), label=f"flexible, deflection x {magnification:g}")
    if outlines:
        ax.plot([], [], "-", color=cmap(0.5), lw=4.0, alpha=0.55, label="rigid bodies")
    if highlight is not None:
        ax.plot([], [], "-", color=_LIMIT_COLOR, lw=2.2, label="at the largest deviation")
    ax.margins(0.07)
    ax.set_aspect("equal", adjustable="datalim")
    unplaced = place_labels(ax, sorted(labels, key=lambda e: not e[3]), names)
    if unplaced:
        ax.plot([], [], " ", label="postures also at " + ", ".join(unplaced))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.25)
    ax.legend(fontsize=7, loc="best", framealpha=0.85)
    if title is None:
        title = (f"{problem.description.case.name}: motion, deflection magnified "
                 f"{magnification:g} times")
    ax.set_title(title, fontsize=10)
    return _save(fig, file)


def _rigid_outlines(problem, result, steps, magnification):
    """[(flexible (k, m, 2) magnified, rigid (k, m, 2))] outline of every rigid body at the
    steps (flexmbs.visual.scene)."""
    if not any(b.kind == "rigid" for b in problem.mechanism.model.bodies.values()):
        return []
    sc = scene(problem, result, steps)
    shown = sc.magnified(magnification)
    return [(shown[:, idx], sc.rigid[:, idx]) for _, kind, idx in sc.cells if kind == "rigid"]


#: where `place_labels` tries a label: offsets (points) from its anchor and the side of the
#: anchor the text stands on, nearest first
_LABEL_OFFSETS = [(5, 4, "left"), (5, -11, "left"), (-5, 4, "right"), (-5, -11, "right")] + [
    (dx, dy, ha) for k in range(1, 6) for dy in (4 + 12 * k, -11 - 12 * k)
    for dx, ha in ((5, "left"), (-5, "right"))]


def place_labels(ax, labels, obstacles=()):
    """Annotate each (text, anchor (x, y), colour, emphasised) of `labels` in order at the
    first offset of _LABEL_OFFSETS where its box overlaps no label placed before it nor the
    `obstacles` (Text artists) and stays inside the axes; a label placed away from its anchor
    gets a thin leader line. Returns the texts that found no place (not drawn). The axes'
    position and limits must be final (the figure laid out) for the boxes to hold."""
    fig = ax.figure
    renderer = _renderer(fig)
    fig.draw_without_rendering()    # the limits as they will be drawn (aspect, autoscaling)
    inside = ax.get_window_extent(renderer).padded(-6)     # text metrics vary with the dpi
    taken = [o.get_window_extent(renderer) for o in obstacles]
    unplaced = []
    for text, xy, color, strong in labels:
        for dx, dy, ha in _LABEL_OFFSETS:
            far = abs(dy) > 12
            a = ax.annotate(text, xy, textcoords="offset points", xytext=(dx, dy), fontsize=7,
                            ha=ha, color=color, zorder=5, weight="bold" if strong else None,
                            arrowprops=dict(arrowstyle="-", lw=0.5, color=color,
                                            shrinkA=0, shrinkB=2) if far else None)
            box = a.get_window_extent(renderer).expanded(1.05, 1.1)
            if inside.contains(box.x0, box.y0) and inside.contains(box.x1, box.y1) and \
                    not any(box.overlaps(t) for t in taken):
                taken.append(box)
                break
            a.remove()
        else:
            unplaced.append(text)
    return unplaced


def _renderer(fig):
    """The figure's renderer (an Agg canvas is attached to a bare Figure)."""
    if not hasattr(fig.canvas, "get_renderer"):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        FigureCanvasAgg(fig)
    return fig.canvas.get_renderer()


def _colormap():
    from matplotlib import colormaps
    base = colormaps["viridis"]
    return lambda x: base(0.05 + 0.8 * float(x))


def plot_overview(problem, result, evaluation, file=None, *, magnification=None):
    """Overview of a simulated design: motion (left) and the constrained histories (right).

    result: `Problem.simulate(x, store='all')`; evaluation: `Problem.evaluate(x)` of the
    same design."""
    hist = constrained_histories(problem, evaluation.values)
    if hist:
        fig = Figure(figsize=(12.5, 5.2))
        ax1, ax2 = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=[1.05, 1]))
        fig.subplots_adjust(left=0.06, right=0.98, bottom=0.1, top=0.86, wspace=0.2)
    else:       # no constrained history: the motion alone
        fig = Figure(figsize=(6.8, 5.6))
        ax1, ax2 = fig.add_subplot(), None
        fig.subplots_adjust(left=0.12, right=0.96, bottom=0.1, top=0.86)
    devs = [h for h in hist if isinstance(
        {r.name: r for r in problem.description.responses}[h[0]], Deviation)]
    highlight = int(np.argmax(devs[0][1])) if devs else None
    plot_motion(problem, result, ax=ax1, magnification=magnification, highlight=highlight)
    if devs:
        plot_histories(evaluation.t, devs, ax=ax2, title="deviation at every time step")
        ax2.set_ylabel("deviation (mm)")
    elif hist:
        plot_histories(evaluation.t, hist[:3], ax=ax2, scale=1.0, unit="",
                       title="constrained responses")
    d = problem.description
    design = ", ".join(f"{n} = {v:.4g} {u}" for n, v, u in
                       zip(problem.variables, evaluation.x, problem.mechanism.units))
    unit = (getattr(evaluation, "units", None) or {}).get("objective")
    obj = "" if evaluation.objective is None else \
        f", {d.objective.response} {evaluation.objective:.4g}{' ' + unit if unit else ''}"
    state = ("" if not evaluation.constraints.size else
             (", feasible" if evaluation.feasible else ", INFEASIBLE")
             + f" at h = {d.time.grid_h:g} s")
    fig.suptitle(f"{d.case.name}: {design}{obj}{state}", fontsize=11)
    return _save(fig, file)
