"""Figures of simulated cases, written to files with matplotlib's Agg canvas.

No pyplot and no global backend change: every function builds its own `Figure` (or draws
into a given Axes) and, if `file` is given, saves it there. The figures:

- `plot_deviation`: deviation history with its limit line, as the paper's Figs. 5(b), 6(b), 8(b);
- `plot_motion`: a few postures of the flexible mechanism over the rigid reference one, with
  the deflection magnified, the points named and the reference paths drawn;
- `plot_case`: both side by side, the overview that `flexmbs simulate --plot` writes.

Example
-------
>>> from flexmbs.cases import load_case
>>> from flexmbs.plots import plot_case
>>> r = load_case("robot_2dof").simulate([39.29, 28.33, 34.94, 25.19])
>>> fig = plot_case(r, "robot_table1.png")
"""
from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

__all__ = ["plot_deviation", "plot_motion", "plot_case", "magnified_postures",
           "nice_magnification"]

_LIMIT_COLOR = "#c0392b"
_RIGID_COLOR = "0.55"


def _save(fig, file):
    if file is not None:
        from flexmbs.batch import save_figure
        save_figure(fig, file, dpi=150, bbox_inches="tight")
    return fig


def plot_deviation(results, file=None, *, labels=None, ax=None, title=None, limit_m=None):
    """Deviation history (mm) of one or several CaseResults, with the limit line.

    Parameters
    ----------
    results : CaseResult or list of CaseResult
        E.g. the weakly and the fully coupled optima, drawn as the paper's Figs. 5(b)-8(b).
    file : path, optional
        Where to save the figure (format from the suffix).
    labels : list of str, optional
        Legend entries (default: the designs in mm).
    ax : matplotlib Axes, optional
        Draw there instead of a new figure.
    title : str, optional
    limit_m : float, optional
        The limit line (default: the first result's limit).

    Returns
    -------
    matplotlib.figure.Figure
    """
    if not isinstance(results, (list, tuple)):
        results = [results]
    if ax is None:
        fig = Figure(figsize=(6.4, 3.8))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    limit = results[0].limit_m if limit_m is None else limit_m
    top = max(r.max_deviation for r in results)
    colors = ["#1f4e9c", "#e08a00", "#2a9d4b", "#7b3fa0", "#555555"]
    for k, r in enumerate(results):
        lab = labels[k] if labels else "p = [" + ", ".join(f"{v:.4g}" for v in r.design_mm) + "] mm"
        lab += f": max {r.max_deviation * 1e3:.4f} mm at {r.t_at_max:.4f} s"
        c = colors[k % len(colors)]
        ax.plot(r.t, r.deviation * 1e3, color=c, lw=1.3, label=lab, ls=("-", "--", ":", "-.")[k % 4])
        ax.plot([r.t_at_max], [r.max_deviation * 1e3], "o", color=c, ms=5, zorder=4)
    if top >= 0.3 * limit:
        ax.axhline(limit * 1e3, color=_LIMIT_COLOR, ls="--", lw=1.2,
                   label=f"limit {limit * 1e3:g} mm")
        ax.set_ylim(0, (1.2 + 0.08 * len(results)) * max(top, limit) * 1e3)   # room for the legend
    else:
        # the limit is far above: keep the history readable and say where the limit is
        ax.set_ylim(0, (1.3 + 0.08 * len(results)) * top * 1e3)
        ax.plot([], [], ls="--", color=_LIMIT_COLOR,
                label=f"limit {limit * 1e3:g} mm (off scale, {limit / top:.0f} x the maximum)")
    ax.set_xlim(0, max(r.t[-1] for r in results))
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"deviation ({results[0].formulation}) (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", framealpha=0.9)
    if title is None:
        title = f"{results[0].case_name}: deviation ({results[0].formulation}) at every time step"
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


def magnified_postures(result, steps, magnification):
    """Node positions of every beam at some steps, flexible (deflection magnified) and rigid.

    The magnified position of a node is rigid + magnification * (flexible - rigid), where
    rigid is the node's place in the rigid reference mechanism at the same time.

    Parameters
    ----------
    result : CaseResult (simulated with store='all')
    steps : list of int
        0-based indices into result.t.
    magnification : float

    Returns
    -------
    dict body -> (flexible (k, nnodes, 2), rigid (k, nnodes, 2))
    """
    case = result.case
    steps = np.asarray(steps, int)
    ref = {k: (v[steps] if isinstance(v, np.ndarray) else v) for k, v in result.reference.items()}
    out = {}
    for b in case.beams:
        body = case.model.body(b)
        rigid = case.rigid_node_positions(ref, b)
        flex = np.stack([result.result.position(n)[steps] for n in body.nodes], axis=1)
        out[b] = (rigid + magnification * (flex - rigid), rigid)
    return out


def _max_deflection(result):
    case = result.case
    d = 0.0
    for b in case.beams:
        body = case.model.body(b)
        rigid = case.rigid_node_positions(result.reference, b)
        flex = np.stack([result.result.position(n) for n in body.nodes], axis=1)
        d = max(d, float(np.max(np.hypot(*(flex - rigid).transpose(2, 0, 1)))))
    return d


def plot_motion(result, file=None, *, ax=None, postures=6, magnification=None, title=None):
    """Postures of the flexible mechanism over the rigid one, deflection magnified.

    Parameters
    ----------
    result : CaseResult
        Simulated with store='all' (the default of Case.simulate).
    file : path, optional
    ax : matplotlib Axes, optional
    postures : int, default 6
        Number of instants, evenly spread over the simulation; the instant of the maximum
        deviation is added and drawn in red.
    magnification : float, optional
        Deflection scale; default: a round number that makes the largest deflection about 6 %
        of the mechanism's size.
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    case = result.case
    if ax is None:
        fig = Figure(figsize=(6.4, 5.6))
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    nt = result.t.size
    steps = sorted(set(np.linspace(0, nt - 1, postures).round().astype(int).tolist()))
    kmax = int(result.step_at_max - 1)
    # the instant of the maximum replaces an evenly spread one that is too close to it
    near = [k for k in steps if abs(k - kmax) < 0.4 * (nt - 1) / max(postures - 1, 1)]
    steps = sorted([k for k in steps if k not in near or k == 0] + [kmax])
    steps = sorted(set(steps))
    q = case.model.reference_coordinates().reshape(-1, 3)
    size = float(np.ptp(q[:, 0]) + np.ptp(q[:, 1])) / 2
    if case.mechanism == "robot_2dof":
        size = float(sum(case.parameters["arm_lengths_m"]))
    if magnification is None:
        dmax = _max_deflection(result)
        magnification = nice_magnification(0.06 * size / dmax) if dmax > 0 else 1.0
    # drop instants whose rigid posture nearly repeats an earlier one (a crank turning more
    # than once), keeping the instant of the maximum
    rig = magnified_postures(result, steps, 1.0)
    allpts = np.concatenate([r for _, r in rig.values()], axis=1)      # (k, nodes, 2)
    keep = []
    for j in sorted(range(len(steps)), key=lambda j: steps[j] != kmax):
        if all(np.max(np.hypot(*(allpts[j] - allpts[i]).T)) > 0.05 * size for i in keep):
            keep.append(j)
    steps = [steps[j] for j in sorted(keep)]
    post = magnified_postures(result, steps, magnification)
    ref = result.reference

    # reference paths of the named points
    if case.mechanism == "robot_2dof":
        ax.plot(ref["x_tip"], ref["y_tip"], ":", color=_RIGID_COLOR, lw=1, label="ideal tip path")
        ax.plot(ref["x_A"], ref["y_A"], ":", color="0.75", lw=1)
    else:
        ax.plot(ref["x_A"], ref["y_A"], ":", color=_RIGID_COLOR, lw=1, label="rigid paths of A, B")
        ax.plot(ref["x_B"], ref["y_B"], ":", color=_RIGID_COLOR, lw=1)
        ax.plot([0, case.parameters["ground_length_m"]], [0, 0], color="0.3", lw=3,
                solid_capstyle="butt", alpha=0.35)
    cmap = _colormap()
    for j, k in enumerate(steps):
        is_max = k == kmax
        color = _LIMIT_COLOR if is_max else cmap(j / max(len(steps) - 1, 1))
        for b, (flex, rigid) in post.items():
            ax.plot(rigid[j, :, 0], rigid[j, :, 1], "--", color=_RIGID_COLOR, lw=1.0, zorder=2)
            ax.plot(flex[j, :, 0], flex[j, :, 1], "-", color=color, lw=2.2 if is_max else 1.6,
                    zorder=3, solid_capstyle="round")
        # label each posture at the end of its last beam
        last = post[case.beams[-1]][0][j]
        tip = last[-1] if case.mechanism == "robot_2dof" else post["crank"][0][j][-1]
        ax.annotate(f"{result.t[k]:.2f} s" + (" (max)" if is_max else ""), tip,
                    textcoords="offset points", xytext=(5, 4), fontsize=7, color=color, zorder=5)
    # joints at t = 0 and ground pivots
    pts = case.points
    for name, node in pts.items():
        x, y = q[node, :2]
        ground = name in ("O", "C")
        ax.plot([x], [y], "^" if ground else "o", color="k" if ground else "w", mec="k",
                ms=8 if ground else 5, zorder=6)
        ax.annotate(name, (x, y), textcoords="offset points", xytext=(-12, -12) if ground else (-12, 6),
                    fontsize=9, weight="bold", zorder=6)
    ax.plot([], [], "--", color=_RIGID_COLOR, label="rigid reference")
    ax.plot([], [], "-", color=cmap(0.5), label=f"flexible, deflection x {magnification:g}")
    ax.plot([], [], "-", color=_LIMIT_COLOR, lw=2.2, label="at the maximum deviation")
    ax.margins(0.07)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.25)
    ax.legend(fontsize=7, loc="best", framealpha=0.85)
    if title is None:
        title = f"{case.name}: motion, deflection magnified {magnification:g} times"
    ax.set_title(title, fontsize=10)
    return _save(fig, file)


def _colormap():
    from matplotlib import colormaps
    base = colormaps["viridis"]
    return lambda x: base(0.05 + 0.8 * float(x))


def plot_case(result, file=None, *, magnification=None):
    """Overview of a simulated case: motion (left) and deviation history (right)."""
    fig = Figure(figsize=(12.5, 5.2))
    ax1, ax2 = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=[1.05, 1]))
    plot_motion(result, ax=ax1, magnification=magnification)
    plot_deviation(result, ax=ax2)
    design = ", ".join(f"{n} = {v:.4g}" for n, v in zip(result.case.design_names, result.design_mm))
    fig.suptitle(f"{result.case_name}: {design} mm, beam mass {result.mass:.4g} kg, "
                 f"max deviation {result.max_deviation * 1e3:.4g} mm "
                 f"(limit {result.limit_m * 1e3:g} mm)", fontsize=11)
    fig.tight_layout()
    return _save(fig, file)
