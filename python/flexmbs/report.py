"""The reproduction report: figures (PNG) and ``README.md`` of `flexmbs.reproduce`.

`make_figures(report)` draws the paper's figures from the results a `Report` holds and returns
{key: (caption, path relative to the report folder)}; `write_report(report)` writes
``README.md`` (every table beside the paper, the checks, the figures, the timings) and
``comparison.json`` (the same numbers for programs).

Figures (the paper's numbering):

- 5, 6, 8, 9, 11: objective history of both methods and the deviation history of their optimal
  designs (Tables 1, 2, 3, 4, 5);
- 10: the weakly coupled method's oscillation on Table 5's problem (mass per cycle, and the
  deviation of the last cycles' designs);
- 13: Table 7's four starts, both methods; 14: the infeasible start [45, 45, 45, 45];
- 12, 15: design-domain maps of the deviation at step 200 (0.0995 s) and 1338 (0.6685 s) over
  (p2, p4), with the maximum deviation over all steps beside them.

Matplotlib's Agg canvas only: no pyplot, no global backend change.
"""
from __future__ import annotations

import datetime
import json
import platform
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

__all__ = ["make_figures", "write_report", "markdown"]

_LIMIT = "#c0392b"
_METHOD_COLOR = {"weakly": "#1f4e9c", "fully": "#e08a00"}
_START_COLORS = ["#1f4e9c", "#e08a00", "#2a9d4b", "#7b3fa0"]
_STYLES = ["-", "--", "-.", ":"]
_X_UPDATES = "design updates, 0 = start\n(weakly: static optimizations; fully: iterations)"


# ============================================================================ helpers
def _start_text(start):
    return "[" + ", ".join(f"{v:g}" for v in start) + "]"


def _history(row):
    """(iterations, masses, max deviations) of a row's history."""
    h = row.result.get("history") or []
    # x = designs updates done: weakly cycle k analyses the design of k - 1 static problems,
    # fully iteration k is the k-th accepted iterate (0 = the start)
    shift = 1 if row.method == "weakly" else 0
    it = [r.get("iteration", k + shift) - shift for k, r in enumerate(h)]
    return (np.array(it), np.array([r.get("mass_kg") for r in h], float),
            np.array([r.get("max_deviation_m") for r in h], float))


def _time(row):
    dev = np.asarray(row.result["deviation_m"], float)
    return np.arange(dev.size) * float(row.result.get("h_s", 5e-4)), dev


def _objective_axes(ax, rows, labels, colors, styles, paper=True, log=False):
    for r, lab, c, ls in zip(rows, labels, colors, styles):
        it, m, _ = _history(r)
        ax.plot(it, m, ls, color=c, marker="o", ms=3.5, lw=1.4, label=lab)
        pm = r.paper.get("mass")
        if paper and pm is not None:
            ax.axhline(pm, color=c, ls=":", lw=1.0, alpha=0.8)
    if paper and any(r.paper.get("mass") is not None for r in rows):
        ax.plot([], [], ":", color="0.3", label="paper's optimum (dotted)")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel(_X_UPDATES)
    ax.set_ylabel("beam mass (kg)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, framealpha=0.9)


def _deviation_axes(ax, rows, labels, colors, styles, limit_m=1e-3):
    top = 0.0
    for k, (r, lab, c, ls) in enumerate(zip(rows, labels, colors, styles)):
        t, dev = _time(r)
        # solid curves that coincide stay visible: the first ones are drawn wider
        lw = max(2.2 - 0.7 * k, 0.9) if ls == "-" else 1.2
        ax.plot(t, dev * 1e3, ls, color=c, lw=lw,
                label=f"{lab}: max {dev.max() * 1e3:.3f} mm at {t[int(np.argmax(dev))]:.4f} s")
        top = max(top, dev.max())
    ax.axhline(limit_m * 1e3, color=_LIMIT, ls="--", lw=1.1, label=f"limit {limit_m * 1e3:g} mm")
    # room above the curves for the legend (one line per design and the limit)
    ax.set_ylim(0, (1.2 + 0.11 * (len(rows) + 1)) * max(top, limit_m) * 1e3)
    ax.set_xlim(0, max(_time(r)[0][-1] for r in rows))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("deviation (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper left", framealpha=0.9)


def _save(fig, folder, key):
    from flexmbs.batch import save_figure
    return save_figure(fig, Path(folder) / f"{key}.png", dpi=130, bbox_inches="tight")


# ============================================================================ figures
def _fig_two_methods(report, table, key, number, what):
    rows = report.rows.get(table, [])
    if not rows:
        return None
    fig = Figure(figsize=(12.5, 4.6))
    a1, a2 = fig.subplots(1, 2)
    labels = [f"{r.method} coupled: {r.mass_kg:.4f} kg" for r in rows]
    colors = [_METHOD_COLOR[r.method] for r in rows]
    styles = ["-" if r.method == "weakly" else "--" for r in rows]
    masses = [m for r in rows for m in _history(r)[1] if np.isfinite(m)]
    spans_decades = bool(masses) and max(masses) > 5 * min(masses)    # e.g. the four-bar's
    _objective_axes(a1, rows, labels, colors, styles, log=spans_decades)
    a1.set_title("objective history", fontsize=10)
    # solid lines: the four-bar's deviations oscillate too fast for dashes
    _deviation_axes(a2, rows, [f"{r.method} coupled" for r in rows], colors, ["-"] * len(rows))
    a2.set_title("deviation of the optimal designs at every time step", fontsize=10)
    fig.suptitle(f"Fig. {number} (Table {table}): {what}", fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", key)
    return (f"Fig. {number}: {what}. Left: beam mass of each design, from the start (0) through "
            f"the static optimizations (weakly coupled) or the iterations (fully coupled)"
            + ("; dotted: the paper's optima" if any(r.paper.get("mass") for r in rows) else "")
            + ". Right: deviation of the final designs in the full simulation, with the 1 mm "
              "limit.", path)


def _fig10(report):
    """The weakly coupled oscillation of Table 5: mass and critical time per cycle, and the
    deviation histories of the last cycles' designs (re-simulated)."""
    rows = [r for r in report.rows.get(5, []) if r.method == "weakly"]
    if not rows:
        return None
    from flexmbs.batch import max_deviation_job
    r = rows[0]
    h = r.result.get("history") or []
    it = np.array([rec["iteration"] for rec in h])
    m = np.array([rec["mass_kg"] for rec in h], float)
    tmax = np.array([rec.get("t_at_max_s", np.nan) for rec in h], float)
    fig = Figure(figsize=(13, 4.8))
    a1, a2 = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=[1, 1.25]))
    keep = it >= 2                     # cycle 1 is the start design (2.29 kg): off scale
    a1.plot(it[keep], m[keep], "o-", color=_METHOD_COLOR["weakly"], ms=5, label="beam mass")
    a1.set_xlabel(f"cycle (cycle 1, the start design, {m[0]:.2f} kg, is off scale)")
    a1.set_ylabel("beam mass (kg)", color=_METHOD_COLOR["weakly"])
    lo, hi = m[keep].min(), m[keep].max()
    a1.set_ylim(lo - 0.35 * (hi - lo), hi + 0.6 * (hi - lo))
    a1.grid(alpha=0.3)
    b1 = a1.twinx()
    b1.plot(it[keep], tmax[keep], "s", color="0.35", ms=6, mfc="none",
            label="time of the maximum deviation (right axis)")
    b1.set_ylabel("time of the maximum deviation (s)", color="0.35")
    b1.set_ylim(0, 0.8)
    lines = a1.get_lines() + b1.get_lines()
    a1.legend(lines, [ln.get_label() for ln in lines], fontsize=8, loc="upper left",
              framealpha=0.9)
    a1.set_title(f"weakly coupled: {'converged' if r.converged else 'NOT converged'} "
                 f"after {r.iterations} cycles", fontsize=10)
    # the last (up to) four cycles' designs, simulated again (50 ms each)
    last = h[-4:]
    t_end = 0.0
    for k, rec in enumerate(last):
        cr = max_deviation_job(r.run.case, rec["design"], dict(r.run.overrides), steps="all")
        dev = np.asarray(cr["deviation_m"])
        t = np.arange(dev.size) * float(r.result["h_s"])
        t_end = t[-1]
        a2.plot(t, dev * 1e3, _STYLES[k % 4], color=_START_COLORS[k % 4], lw=1.2,
                label=f"cycle {rec['iteration']}: {rec['mass_kg']:.4f} kg, max "
                      f"{cr['max_deviation_m'] * 1e3:.3f} mm at {cr['t_at_max_s']:.3f} s")
    a2.axhline(1.0, color=_LIMIT, ls="--", lw=1.1, label="limit 1 mm")
    a2.set_ylim(0, 1.2 + 0.11 * (len(last) + 1))
    a2.set_xlim(0, t_end)
    a2.set_xlabel("time (s)")
    a2.set_ylabel("deviation (28) (mm)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7.5, loc="upper left")
    a2.set_title("deviation of the designs of the last cycles", fontsize=10)
    fig.suptitle("Fig. 10 (Table 5, 0.66 s): the weakly coupled method oscillates between designs",
                 fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", "fig10")
    return ("Fig. 10: the weakly coupled method on the 0.66 s problem. Left: beam mass and time "
            "of the maximum deviation per cycle. Right: deviation histories of the designs of "
            "the last cycles (the critical time alternates between the peak near 0.1 s and the "
            "last step, as the paper describes).", path)


def _fig13(report):
    rows = report.rows.get(7, [])
    if not rows:
        return None
    fig = Figure(figsize=(13, 8.6))
    axes = fig.subplots(2, 2)
    for k, method in enumerate(("weakly", "fully")):
        rr = [r for r in rows if r.method == method]
        if not rr:
            continue
        labels = [f"start {_start_text(r.start_mm)}: {r.mass_kg:.4f} kg" for r in rr]
        colors = _START_COLORS[:len(rr)]
        styles = _STYLES[:len(rr)]
        _objective_axes(axes[k, 0], rr, labels, colors, styles, paper=False)
        axes[k, 0].set_title(f"{method} coupled: objective history", fontsize=10)
        _deviation_axes(axes[k, 1], rr, [f"start {_start_text(r.start_mm)}" for r in rr],
                        colors, styles)
        axes[k, 1].set_title(f"{method} coupled: deviation of the optimal designs", fontsize=10)
    fig.suptitle("Fig. 13 (Table 7, 0.6685 s = 1338 steps): influence of the starting point",
                 fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", "fig13")
    return ("Fig. 13: Table 7's problem from the four starting points. Top: weakly coupled; "
            "bottom: fully coupled. Left: beam mass per cycle / iteration; right: deviation of "
            "the final designs.", path)


def _fig14(report):
    rows = [r for r in report.rows.get(7, []) if list(r.start_mm) == [45.0] * 4]
    if not rows:
        return None
    fig = Figure(figsize=(15, 4.6))
    a1, a2, a3 = fig.subplots(1, 3)
    colors = [_METHOD_COLOR[r.method] for r in rows]
    styles = ["-" if r.method == "weakly" else "--" for r in rows]
    _objective_axes(a1, rows, [f"{r.method} coupled: {r.mass_kg:.4f} kg" for r in rows],
                    colors, styles)
    a1.set_title("objective history", fontsize=10)
    for r, c, ls in zip(rows, colors, styles):
        it, _, mx = _history(r)
        a2.plot(it, mx * 1e3, ls, color=c, marker="o", ms=3.5, label=f"{r.method} coupled")
    a2.axhline(1.0, color=_LIMIT, ls="--", lw=1.1, label="limit 1 mm")
    a2.set_xlabel(_X_UPDATES)
    a2.set_ylabel("maximum deviation (mm)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    a2.set_title("maximum deviation of each design (start infeasible)", fontsize=10)
    _deviation_axes(a3, rows, [f"{r.method} coupled" for r in rows], colors, styles)
    a3.set_title("deviation of the optimal designs", fontsize=10)
    fig.suptitle("Fig. 14 (Table 7): infeasible starting point [45, 45, 45, 45]", fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", "fig14")
    return ("Fig. 14: Table 7's problem from the infeasible start [45, 45, 45, 45] (1.26 mm). "
            "Left: beam mass; middle: maximum deviation of each iterate; right: deviation of the "
            "final designs.", path)


def _nice_step(span, n=20):
    """A round contour step (1, 2 or 5 x 10^k) giving about n levels over span."""
    raw = span / n
    e = np.floor(np.log10(raw))
    for m in (1, 2, 5, 10):
        if m * 10 ** e >= raw:
            return m * 10 ** e
    return 10 ** (e + 1)    # pragma: no cover


def _map_panel(fig, ax, a, b, z_m, title, limit=1.0):
    """Filled contours of z (m -> mm) over (a, b), clipped at 2 x the limit, the limit bold."""
    A, B = np.meshgrid(a, b, indexing="ij")
    z = z_m * 1e3
    top = min(float(np.nanmax(z)), 2.0 * limit)
    bottom = float(np.nanmin(z))
    step = _nice_step(max(top - bottom, 0.05 * limit))
    levels = np.arange(np.floor(bottom / step) * step, top + step, step)
    if levels.size < 3:
        levels = np.linspace(bottom, max(top, bottom + 0.1), 5)
    cs = ax.contourf(A, B, z, levels=levels, cmap="viridis", extend="max")
    fig.colorbar(cs, ax=ax, label="deviation (mm)")
    if levels[0] < limit < np.nanmax(z):
        c1 = ax.contour(A, B, z, levels=[limit], colors=_LIMIT, linewidths=2.0)
        ax.clabel(c1, fmt={limit: f"{limit:g} mm"}, fontsize=8)
    ax.set_title(title, fontsize=10)


def _fig_map(report, key):
    m = report.maps.get(key)
    if m is None:
        return None
    s = m.spec
    h = 5e-4
    fig = Figure(figsize=(13, 10.5))
    axes = fig.subplots(2, 2)
    fixed = ", ".join(f"p{k + 1} = {v:g}" for k, v in s.fixed)
    step_txt = f"deviation at step {s.step} (t = {(s.step - 1) * h:.4f} s)"
    for row, region in enumerate(("full", "zoom")):
        a, b, at, mx = m.grids[region]
        where = "box of the bounds" if region == "full" else "zoom near the optima"
        for col, (z, what) in enumerate(((at, step_txt), (mx, "maximum deviation over all steps"))):
            ax = axes[row, col]
            _map_panel(fig, ax, a, b, z, f"{what}: {where}")
            ax.set_xlabel(f"{m.names[0]} (mm)")
            ax.set_ylabel(f"{m.names[1]} (mm)")
            _map_markers(ax, report, s)
            ax.set_xlim(a[0], a[-1])
            ax.set_ylim(b[0], b[-1])
        if region == "full":
            (a0, a1), (b0, b1) = s.zoom
            for ax in axes[0]:
                ax.plot([a0, a1, a1, a0, a0], [b0, b0, b1, b1, b0], "w--", lw=1.0)
    axes[1, 0].legend(fontsize=8, loc="upper right", framealpha=0.9)
    n = m.grids["full"][0].size
    fig.suptitle(f"Fig. {s.figure} (Table {s.table}): design domain over (p2, p4), {fixed} mm; "
                 f"two {n} x {n} grids, one simulation per point", fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", key)
    return (f"Fig. {s.figure}: deviation at time step {s.step} (t = {(s.step - 1) * h:.4f} s, "
            f"left) and maximum deviation over all steps (right) over (p2, p4) with {fixed} mm; "
            f"top: the whole box of the bounds (dashed: the zoom), bottom: the zoom near the "
            f"optima; red: the 1 mm limit; colours clipped at 2 mm; markers: Table {s.table}'s "
            f"optima, paper (x) and flexmbs (o) (their p1, p3 differ slightly from the map's).",
            path)


def _map_markers(ax, report, spec):
    rows = report.rows.get(spec.table, [])
    done = set()
    for r in rows:
        for who, p, mk in (("paper", r.paper.get("p"), "x"), ("flexmbs", r.design_mm, "o")):
            if p is None or p[1] is None:
                continue
            key = (who, r.method)
            lab = None if key in done else f"{who}, {r.method} coupled optima"
            done.add(key)
            ax.plot(p[1], p[3], mk, color=_METHOD_COLOR[r.method], mec="k" if mk == "o" else None,
                    ms=6, mew=1.2, label=lab, zorder=5)


def make_figures(report):
    """Draw every figure the report's tables allow; return {key: (caption, relative path)}."""
    folder = report.out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    makers = [
        ("fig05", lambda: _fig_two_methods(report, 1, "fig05", 5,
                                           "2-dof robot, deviation (28), 0.65 s")),
        ("fig06", lambda: _fig_two_methods(report, 2, "fig06", 6,
                                           "2-dof robot, tracking deviation (30), 0.65 s")),
        ("fig08", lambda: _fig_two_methods(report, 3, "fig08", 8,
                                           "four-bar mechanism with lumped masses")),
        ("fig09", lambda: _fig_two_methods(report, 4, "fig09", 9,
                                           "four-bar mechanism without lumped masses")),
        ("fig10", lambda: _fig10(report)),
        ("fig11", lambda: _fig_two_methods(report, 5, "fig11", 11,
                                           "2-dof robot, deviation (28), 0.66 s")),
        ("fig12", lambda: _fig_map(report, "fig12")),
        ("fig13", lambda: _fig13(report)),
        ("fig14", lambda: _fig14(report)),
        ("fig15", lambda: _fig_map(report, "fig15")),
    ]
    out = {}
    for key, make in makers:
        res = make()
        if res is not None:
            caption, path = res
            out[key] = (caption, str(Path(path).relative_to(report.out)))
    return out


# ============================================================================ markdown
def _pct(v):
    return "" if v is None else f"{100 * v + 0.0:+.2f}".replace("-0.00", "+0.00")


def _num(v, spec):
    return "–" if v is None else format(v, spec)


def _md_table(report, table):
    from flexmbs.reproduce import TABLES
    rows = report.rows.get(table, [])
    if not rows:
        return "_no result_\n"
    nv = len(rows[0].design_mm)
    head = ["method", "start (mm)", "", "mass (kg)", "Iter.", "Inner iter."] + \
        [f"p{k + 1}" for k in range(nv)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        pp = r.paper.get("p") or [None] * nv
        start = _start_text(r.start_mm)
        if r.paper.get("mass") is None and all(v is None for v in pp):
            lines.append(f"| {r.method} | {start} | paper | " + " | ".join(
                [r.paper.get("behaviour", "–"), "", ""] + [""] * nv) + " |")
        else:
            lines.append(f"| {r.method} | {start} | paper | " + " | ".join(
                [_num(r.paper.get("mass"), ".3f"), _num(r.paper.get("iter"), "d"),
                 _num(r.paper.get("inner_iter"), "d")] + [_num(v, ".2f") for v in pp]) + " |")
        lines.append("| | | **flexmbs** | " + " | ".join(
            [f"**{r.mass_kg:.4f}**", f"{r.iterations}", _num(r.inner_iterations, "d")]
            + [f"**{v:.2f}**" for v in r.design_mm]) + " |")
        if r.mass_difference is not None or r.paper.get("p"):
            lines.append("| | | Δ % | " + " | ".join(
                [_pct(r.mass_difference), "", ""] + [_pct(v) for v in r.design_differences]) + " |")
    lines.append("")
    from flexmbs.reproduce import paper_design_text
    for r in rows:
        pd = paper_design_text(r)
        lines.append(f"- {r.method} coupled from {_start_text(r.start_mm)}: "
                     f"{'converged' if r.converged else '**not converged**'} ({r.reason}); "
                     f"maximum deviation of the final design {r.max_deviation_m * 1e3:.4f} mm; "
                     f"{r.result.get('simulations')} simulations, {r.wall_time_s:.1f} s"
                     + (f"; {pd}." if pd else "."))
    missing = [n.name for n in TABLES[table].runs() if n.name not in report.results]
    for name in missing:
        lines.append(f"- **no result** for {name}: {report.failures.get(name, 'not run')}")
    return "\n".join(lines) + "\n"


def _md_scan(scan):
    """The Table 3 diagnostic: maximum deviation over p1 for two (p2, p3)."""
    tails = sorted({(r["p2_mm"], r["p3_mm"]) for r in scan})
    p1s = sorted({r["p1_mm"] for r in scan})
    val = {(r["p1_mm"], r["p2_mm"], r["p3_mm"]): r for r in scan}
    L = ["Why the fully coupled four-bar optimum is sensitive: maximum deviation (mm) of A over "
         "the crank diameter p1 with a slender coupler and follower (simulated by flexmbs; the "
         "peak is a vibration of the slender links, not monotonic in the design):", "",
         "| p1 (mm) | " + " | ".join(f"{v:g}" for v in p1s) + " |",
         "|---|" + "---|" * len(p1s)]
    for p2, p3 in tails:
        L.append(f"| p2, p3 = {p2:g}, {p3:g} mm | " + " | ".join(
            f"{val[(p1, p2, p3)]['max_deviation_m'] * 1e3:.3f}" for p1 in p1s) + " |")
    L.append("")
    return "\n".join(L) + "\n"


def _verdict(c):
    return {True: "yes", False: "**no**", None: "reported (no criterion)"}[c.ok]


def _md_checks(checks):
    if not checks:
        return ""
    lines = ["| finding | paper | flexmbs | reproduced |", "|---|---|---|---|"]
    for c in checks:
        lines.append(f"| {c.what} | {c.paper} | {c.flexmbs} | {_verdict(c)} |")
    return "\n".join(lines) + "\n"


def markdown(report):
    """The report as Markdown text."""
    from flexmbs import __version__
    from flexmbs.reproduce import MAPS, TABLES
    now = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    tabs = ", ".join(map(str, report.tables))
    word = "Tables" if len(report.tables) > 1 else "Table"
    L = [f"# flexmbs reproduction of Tromme, Brüls & Duysinx, {word} {tabs}", "",
         "*Weakly and fully coupled methods for structural optimization of flexible mechanisms*: "
         "every table below puts the published numbers (transcribed in `paper_tables.json`) "
         "beside those flexmbs computes, with the difference in per cent; the figures are "
         "drawn from the same runs. Nothing here needs to be run again to be checked: the "
         "result of every optimization is in `jobs/` (JSON, with its full history) and all "
         "numbers are in `comparison.json`.", "",
         f"flexmbs {__version__}, Python {platform.python_version()}, {now}; "
         f"{report.settings.get('executor', '')}; this report took "
         f"{report.elapsed.get('total', 0):.0f} s (see Wall times for the computations). "
         "Iter. = cycles, i.e. MBS analyses (weakly coupled) or optimizer iterations (fully "
         "coupled); Inner iter. = iterations of the static problems, summed. Modelling choices "
         "the paper leaves open are fixed as in the case files (`cases/*.toml`).", ""]
    checks = [c for c in report.all_checks if c.ok is not None]
    if checks:
        bad = [c for c in checks if not c.ok]
        L += [f"## Summary: {len(checks) - len(bad)} of {len(checks)} findings reproduced", ""]
        if bad:
            L += ["Not reproduced (details under each table):", ""]
            L += [f"- Table {c.table}: {c.what}: paper {c.paper}, flexmbs {c.flexmbs}" for c in bad]
            L.append("")
    if report.failures:
        L += ["Runs without a result:", ""]
        L += [f"- {n}: {e}" for n, e in report.failures.items()]
        L.append("")
    for t in report.tables:
        spec = TABLES[t]
        L += [f"## Table {t}: {spec.title}", ""]
        if t == 8:
            L += ["Active time steps (1-based, t = (n - 1) h) per cycle (weakly coupled) / "
                  "iteration (fully coupled). flexmbs, weakly coupled: the steps active at the "
                  "solution of the static problem that produced the cycle's design, and the "
                  "steps where the cycle's full simulation is within 0.1 % of the limit; fully "
                  "coupled: the iterate's steps within 0.1 % of the limit (iteration 0 is the "
                  "start).", "",
                  "| iter. | paper, weakly | flexmbs, weakly (static problem) | flexmbs, weakly "
                  "(simulation) | paper, fully | flexmbs, fully |", "|---|---|---|---|---|---|"]
            for r in report.table8 or []:
                L.append("| " + " | ".join(str(v) for v in r) + " |")
            L.append("")
            continue
        L.append(_md_table(report, t))
        if t == 3 and report.extra.get("table3_p1_scan"):
            L.append(_md_scan(report.extra["table3_p1_scan"]))
        ch = report.checks.get(t)
        if ch:
            L += [_md_checks(ch)]
        for key in spec.figures:
            if key in report.figures:
                cap, path = report.figures[key]
                L += [f"![Fig. {key[3:].lstrip('0')}]({path})", "", f"*{cap}*", ""]
        for key, m in MAPS.items():
            if m.table == t and key in report.maps:
                mp = report.maps[key]
                L.append(f"Maps of Fig. {m.figure}: {mp.simulations} simulations in "
                         f"{mp.wall_time_s:.0f} s; stored in `jobs/{key}/`.")
                L.append("")
    L += ["## Wall times", "",
          "| table | runs | serial wall time of its runs (s) |", "|---|---|---|"]
    for t in report.tables:
        if t == 8:
            continue
        runs = {r.name for r in TABLES[t].runs()}
        L.append(f"| {t} | {len(runs)} | {report.table_time(t):.1f} |")
    L.append("")
    if report.timings:
        L += ["", "| phase | jobs computed | elapsed (s) | executor | when |", "|---|---|---|---|---|"]
        for k, v in report.timings.items():
            L.append(f"| {k} | {v['jobs_computed']} | {v['elapsed_s']:.1f} | {v['executor']} | "
                     f"{v['date']} |")
    L += ["", "This call: " + ", ".join(f"{k} {v:.1f} s" for k, v in report.elapsed.items())
          + f" ({len(report.settings.get('stored_runs', []))} optimizations were already "
          f"stored)."]
    L += ["", "Serial wall time of a table: the sum of its runs' wall times (a run shared by "
          "several tables, e.g. Table 1 = Table 6's first start, is computed once and counted in "
          "each). The phases' times are those of the call that computed their jobs (stored "
          "results are not computed again).", ""]
    return "\n".join(L)


def write_report(report):
    """Write ``README.md`` and ``comparison.json`` into report.out; return the README path."""
    from flexmbs.optimize.result import jsonable
    out = Path(report.out)
    from flexmbs.batch import write_atomic
    write_atomic(out / "README.md", markdown(report))
    data = dict(
        tables=report.tables, settings=report.settings, elapsed_s=report.elapsed,
        timings=report.timings, extra=report.extra,
        rows={str(t): [r.to_dict() for r in rows] for t, rows in report.rows.items()},
        checks=[dict(table=c.table, what=c.what, paper=c.paper, flexmbs=c.flexmbs, ok=c.ok)
                for c in report.all_checks],
        table8=report.table8, failures=report.failures,
        figures={k: v[1] for k, v in report.figures.items()},
        maps={k: dict(step=m.spec.step, fixed={f"p{i + 1}": v for i, v in m.spec.fixed},
                      **{region: dict(p2_mm=g[0], p4_mm=g[1], deviation_at_step_m=g[2],
                                      max_deviation_m=g[3]) for region, g in m.grids.items()})
              for k, m in report.maps.items()})
    write_atomic(out / "comparison.json", json.dumps(jsonable(data), indent=1))
    return out / "README.md"


def publish(report, figures=True, log=None):
    """Draw the figures of a reproduction (figures/*.png) and write its README.md and
    comparison.json: the second half of `flexmbs reproduce`, after
    `flexmbs.reproduce.reproduce` has run the jobs."""
    say = log or (lambda s: None)
    if figures:
        t0 = time.perf_counter()
        say(f"figures in {report.out / 'figures'}")
        report.figures = make_figures(report)
        total = report.elapsed.pop("total", 0.0)
        report.elapsed["figures"] = time.perf_counter() - t0
        report.elapsed["total"] = total + report.elapsed["figures"]
    write_report(report)
    return report
