"""The reproduction report: figures (PNG) and ``README.md`` of `flexmbs.paper.reproduce`.

`make_figures(report)` draws the figures its study declares from the results a `Report` holds
and returns {key: (caption, path relative to the report folder)}; `write_report(report)` writes
``README.md`` (every table beside the published one, the checks, the figures, the timings) and
``comparison.json`` (the same numbers for programs).

Figure kinds (``docs/study-format.md``):

- two_methods: objective history of a table's runs and the deviation history of their optima;
- oscillation: a run that does not converge (mass and critical time per cycle, and the
  deviation of the last cycles' designs);
- starts: every start of a table, both methods; start_detail: both methods from one start;
- map: a design-domain map of the deviation at one time step over two design variables, with
  the maximum deviation over all steps beside it.

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

from flexmbs.files import jsonable, save_figure, write_atomic
from flexmbs.paper.reproduce import paper_design_text, scan_key, verification_text
from flexmbs.sweep import max_deviation_job
from flexmbs.version import __version__

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
    spans_decades = bool(masses) and max(masses) > 5 * min(masses)
    _objective_axes(a1, rows, labels, colors, styles, log=spans_decades)
    a1.set_title("objective history", fontsize=10)
    # solid lines: fast oscillating deviations leave dashes unreadable
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


def _fig_oscillation(report, spec):
    """A run that does not converge (the first of the figure's method in its table): mass and
    critical time per cycle, and the deviation histories of the last cycles' designs
    (re-simulated)."""
    rows = [r for r in report.rows.get(spec.table, []) if r.method == spec.method]
    if not rows:
        return None
    r = rows[0]
    h = r.result.get("history") or []
    it = np.array([rec["iteration"] for rec in h])
    m = np.array([rec["mass_kg"] for rec in h], float)
    tmax = np.array([rec.get("t_at_max_s", np.nan) for rec in h], float)
    fig = Figure(figsize=(13, 4.8))
    a1, a2 = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=[1, 1.25]))
    keep = it >= 2                     # cycle 1 is the start design: off scale
    a1.plot(it[keep], m[keep], "o-", color=_METHOD_COLOR[spec.method], ms=5, label="beam mass")
    a1.set_xlabel(f"cycle (cycle 1, the start design, {m[0]:.2f} kg, is off scale)")
    a1.set_ylabel("beam mass (kg)", color=_METHOD_COLOR[spec.method])
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
    a1.set_title(f"{spec.method} coupled: {'converged' if r.converged else 'NOT converged'} "
                 f"after {r.iterations} cycles", fontsize=10)
    # the last cycles' designs, simulated again
    last = h[-spec.last:]
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
    a2.set_ylabel(spec.deviation_label)
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7.5, loc="upper left")
    a2.set_title("deviation of the designs of the last cycles", fontsize=10)
    fig.suptitle(spec.title, fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", spec.key)
    return spec.caption, path


def _fig_starts(report, spec):
    """Every start of a table: one row of panels per method."""
    rows = report.rows.get(spec.table, [])
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
    fig.suptitle(spec.title, fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", spec.key)
    return spec.caption, path


def _fig_start_detail(report, spec):
    """Both methods from one start of a table: mass, maximum deviation per iterate, optima."""
    rows = [r for r in report.rows.get(spec.table, [])
            if list(r.start_mm) == [float(v) for v in spec.start]]
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
    fig.suptitle(spec.title, fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", spec.key)
    return spec.caption, path


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


def _fig_map(report, key, fig_key=None):
    m = report.maps.get(key)
    if m is None:
        return None
    s = m.spec
    h = m.h_s
    fig = Figure(figsize=(13, 10.5))
    axes = fig.subplots(2, 2)
    unit = m.units[0] if len(set(m.units)) == 1 else ""
    u = f" {unit}" if unit else ""
    fixed = ", ".join(f"{k} = {v:g}" for k, v in s.fixed)
    over = f"({m.names[0]}, {m.names[1]})"
    step_txt = f"deviation at step {s.step} (t = {(s.step - 1) * h:.4f} s)"
    for row, region in enumerate(("full", "zoom")):
        a, b, at, mx = m.grids[region]
        where = "box of the bounds" if region == "full" else "zoom near the optima"
        for col, (z, what) in enumerate(((at, step_txt), (mx, "maximum deviation over all steps"))):
            ax = axes[row, col]
            _map_panel(fig, ax, a, b, z, f"{what}: {where}")
            ax.set_xlabel(f"{m.names[0]} ({m.units[0]})" if m.units[0] else m.names[0])
            ax.set_ylabel(f"{m.names[1]} ({m.units[1]})" if m.units[1] else m.names[1])
            _map_markers(ax, report, m)
            ax.set_xlim(a[0], a[-1])
            ax.set_ylim(b[0], b[-1])
        if region == "full":
            (a0, a1), (b0, b1) = s.zoom
            for ax in axes[0]:
                ax.plot([a0, a1, a1, a0, a0], [b0, b0, b1, b1, b0], "w--", lw=1.0)
    axes[1, 0].legend(fontsize=8, loc="upper right", framealpha=0.9)
    n = m.grids["full"][0].size
    fig.suptitle(f"Fig. {s.figure} (Table {s.table}): design domain over {over}, {fixed}{u}; "
                 f"two {n} x {n} grids, one simulation per point", fontsize=11)
    fig.tight_layout()
    path = _save(fig, report.out / "figures", fig_key or key)
    return (f"Fig. {s.figure}: deviation at time step {s.step} (t = {(s.step - 1) * h:.4f} s, "
            f"left) and maximum deviation over all steps (right) over {over} with {fixed}{u}; "
            f"top: the whole box of the bounds (dashed: the zoom), bottom: the zoom near the "
            f"optima; red: the 1 mm limit; colours clipped at 2 mm; markers: Table {s.table}'s "
            f"optima, paper (x) and flexmbs (o) (their {', '.join(k for k, _ in s.fixed)} differ "
            f"slightly from the map's).",
            path)


def _map_markers(ax, report, m):
    rows = report.rows.get(m.spec.table, [])
    i, j = m.indices
    done = set()
    for r in rows:
        for who, p, mk in (("paper", r.paper.get("p"), "x"), ("flexmbs", r.design_mm, "o")):
            if p is None or p[i] is None:
                continue
            key = (who, r.method)
            lab = None if key in done else f"{who}, {r.method} coupled optima"
            done.add(key)
            ax.plot(p[i], p[j], mk, color=_METHOD_COLOR[r.method], mec="k" if mk == "o" else None,
                    ms=6, mew=1.2, label=lab, zorder=5)


def make_figures(report):
    """Draw every figure the report's tables allow; return {key: (caption, relative path)}."""
    folder = report.out / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    makers = []
    for fig in report.study.figures:
        if fig.kind == "two_methods":
            make = (lambda f: lambda: _fig_two_methods(report, f.table, f.key, f.number,
                                                       f.what))(fig)
        elif fig.kind == "map":
            make = (lambda f: lambda: _fig_map(report, f.map, f.key))(fig)
        else:
            draw = {"oscillation": _fig_oscillation, "starts": _fig_starts,
                    "start_detail": _fig_start_detail}[fig.kind]
            make = (lambda d, f: lambda: d(report, f))(draw, fig)
        makers.append((fig.key, make))
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
    for r in rows:
        pd = paper_design_text(r)
        ver = verification_text(r.result)
        lines.append(f"- {r.method} coupled from {_start_text(r.start_mm)}: "
                     f"{'converged' if r.converged else '**not converged**'} ({r.reason}); "
                     f"maximum deviation of the final design {r.max_deviation_m * 1e3:.4f} mm; "
                     f"{r.result.get('simulations')} simulations, {r.wall_time_s:.1f} s"
                     + (f"; {pd}" if pd else "") + (f"; {ver}." if ver else "."))
    missing = [n.name for n in report.study.tables[table].runs() if n.name not in report.results]
    for name in missing:
        lines.append(f"- **no result** for {name}: {report.failures.get(name, 'not run')}")
    return "\n".join(lines) + "\n"


def _md_variants(report, table):
    """A table's variants (`[[tables.N.variants]]`): each beside the published optimum of its
    method, then one line per variant (its options, status and, for a multi-start, the spread
    of the local optima)."""
    spec = report.study.tables[table]
    vrows = report.variants.get(table) or []
    if not spec.variants:
        return ""
    nv = len(spec.variables)
    unit = spec.units[0] if len(set(spec.units)) == 1 and spec.units[0] else ""
    L = ["Variants: the same problem run with other options, beside the paper's optimum of "
         "the method (extra rows; the rows above are the paper's settings).", "",
         "| variant | method | | mass (kg) | " + " | ".join(spec.variables) + " |",
         "|" + "---|" * (4 + nv)]
    for v in vrows:
        pp = v.paper.get("p") or [None] * nv
        L.append(f"| {v.label} | {v.method} | paper | {_num(v.paper.get('mass'), '.3f')} | "
                 + " | ".join(_num(x, ".2f") for x in pp) + " |")
        d = v.design_mm
        L.append("| | | **flexmbs** | " + ("–" if v.mass_kg is None else f"**{v.mass_kg:.4f}**")
                 + " | " + " | ".join("–" if d is None else f"**{x:.2f}**"
                                      for x in (d if d is not None else [None] * nv)) + " |")
        if v.mass_difference is not None:
            L.append("| | | Δ % | " + _pct(v.mass_difference) + " | "
                     + " | ".join(_pct(x) for x in (v.design_differences or [None] * nv)) + " |")
    L.append("")
    for v in vrows:
        how = (f"multi-start: {v.variant.options_text}" if v.is_multistart
               else f"from {_start_text(v.variant.start_mm)}{f' {unit}' if unit else ''}; "
                    f"options: {v.variant.options_text}")
        L.append(f"- {v.label} (`jobs/variants/{v.variant.name}.json`; {how}): {v.status()}.")
    names = {v.variant.name for v in vrows}
    for v in spec.variants:
        if v.name not in names:
            L.append(f"- **no result** for variant {v.label} ({v.name}): "
                     f"{report.failures.get(v.name, 'not run')}")
    return "\n".join(L) + "\n"


def _md_scan(spec, scan):
    """A table's scan (`flexmbs.paper.reproduce.design_scan`): maximum deviation over one design
    variable, one line per setting of the others."""
    sc = spec.scan
    i = spec.index(sc.variable)
    keys = [f"{n}_{u}" if u else n for n, u in zip(spec.variables, spec.units)]
    rest = [k for k in range(len(keys)) if k != i]
    tails = sorted({tuple(r[keys[k]] for k in rest) for r in scan})
    values = sorted({r[keys[i]] for r in scan})
    val = {(r[keys[i]], tuple(r[keys[k]] for k in rest)): r for r in scan}
    unit = spec.units[i]
    others = ", ".join(spec.variables[k] for k in rest)
    ru = {spec.units[k] for k in rest}
    u = f" {ru.pop()}" if len(ru) == 1 and "" not in ru else ""
    L = [sc.caption, "",
         f"| {sc.variable}{f' ({unit})' if unit else ''} | "
         + " | ".join(f"{v:g}" for v in values) + " |",
         "|---|" + "---|" * len(values)]
    for tail in tails:
        L.append(f"| {others} = {', '.join(f'{v:g}' for v in tail)}{u} | " + " | ".join(
            f"{val[(v, tail)]['max_deviation_m'] * 1e3:.3f}" for v in values) + " |")
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


def _shared_run_example(study):
    """A table whose single start is the first start of another table of the same problem,
    as a clause of the wall-time note ('' when no table shares its runs)."""
    rows = [t for t in study.tables.values() if t.kind == "rows"]
    for a in rows:
        for b in rows:
            if (a.number != b.number and len(a.starts) == 1 and len(b.starts) > 1
                    and a.case == b.case and a.overrides == b.overrides
                    and a.starts[0] == b.starts[0]):
                return f", e.g. Table {a.number} = Table {b.number}'s first start,"
    return ""


def markdown(report):
    """The report as Markdown text."""
    study = report.study
    now = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    tabs = ", ".join(map(str, report.tables))
    word = "Tables" if len(report.tables) > 1 else "Table"
    L = [f"# flexmbs reproduction of {study.reference or study.name}, {word} {tabs}", ""]
    if study.introduction:
        L += [study.introduction, ""]
    L += [f"flexmbs {__version__}, Python {platform.python_version()}, {now}; "
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
        spec = study.tables[t]
        L += [f"## Table {t}: {spec.title}", ""]
        if spec.kind == "active_steps":
            L += ["Active time steps (1-based, t = (n - 1) h) per cycle (weakly coupled) / "
                  "iteration (fully coupled). flexmbs, weakly coupled: the steps active at the "
                  "solution of the static problem that produced the cycle's design, and the "
                  "steps where the cycle's full simulation is within 0.1 % of the limit; fully "
                  "coupled: the iterate's steps within 0.1 % of the limit (iteration 0 is the "
                  "start).", "",
                  "| iter. | paper, weakly | flexmbs, weakly (static problem) | flexmbs, weakly "
                  "(simulation) | paper, fully | flexmbs, fully |", "|---|---|---|---|---|---|"]
            for r in report.active_steps.get(t) or []:
                L.append("| " + " | ".join(str(v) for v in r) + " |")
            L.append("")
            continue
        L.append(_md_table(report, t))
        if spec.variants:
            L.append(_md_variants(report, t))
        if spec.scan is not None and report.extra.get(scan_key(spec)):
            L.append(_md_scan(spec, report.extra[scan_key(spec)]))
        ch = report.checks.get(t)
        if ch:
            L += [_md_checks(ch)]
        numbers = {f.key: f.number for f in study.figures}
        for key in spec.figures:
            if key in report.figures:
                cap, path = report.figures[key]
                L += [f"![Fig. {numbers[key]}]({path})", "", f"*{cap}*", ""]
        for key, m in study.maps.items():
            if m.table == t and key in report.maps:
                mp = report.maps[key]
                L.append(f"Maps of Fig. {m.figure}: {mp.simulations} simulations in "
                         f"{mp.wall_time_s:.0f} s; stored in `jobs/{key}/`.")
                L.append("")
    L += ["## Wall times", "",
          "| table | runs | serial wall time of its runs (s) |", "|---|---|---|"]
    for t in report.row_tables:
        runs = {r.name for r in study.tables[t].runs()}
        L.append(f"| {t} | {len(runs)} | {report.table_time(t):.1f} |")
        vrows = report.variants.get(t) or []
        if vrows:
            L.append(f"| {t}, variants | {len(vrows)} | "
                     f"{sum(float(v.result.get('wall_time_s') or 0.0) for v in vrows):.1f} |")
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
          f"several tables{_shared_run_example(study)} is computed once and counted in "
          "each). The phases' times are those of the call that computed their jobs (stored "
          "results are not computed again).", ""]
    return "\n".join(L)


def _map_axes(m, g):
    """{'p2_mm': grid values, 'p4_mm': ...} of a map's region (name_unit keys)."""
    return {(f"{n}_{u}" if u else n): v for n, u, v in zip(m.names, m.units, g[:2])}


def write_report(report):
    """Write ``README.md`` and ``comparison.json`` into report.out; return the README path."""
    out = Path(report.out)
    write_atomic(out / "README.md", markdown(report))
    data = dict(
        tables=report.tables, settings=report.settings, elapsed_s=report.elapsed,
        timings=report.timings, extra=report.extra,
        rows={str(t): [r.to_dict() for r in rows] for t, rows in report.rows.items()},
        variants={str(t): [v.to_dict() for v in rows] for t, rows in report.variants.items()},
        checks=[dict(table=c.table, what=c.what, paper=c.paper, flexmbs=c.flexmbs, ok=c.ok)
                for c in report.all_checks],
        **{f"table{t}": report.active_steps.get(t) for t, spec in report.study.tables.items()
           if spec.kind == "active_steps"},
        failures=report.failures,
        figures={k: v[1] for k, v in report.figures.items()},
        maps={k: dict(step=m.spec.step, fixed=dict(m.spec.fixed),
                      **{region: {**_map_axes(m, g), "deviation_at_step_m": g[2],
                                  "max_deviation_m": g[3]} for region, g in m.grids.items()})
              for k, m in report.maps.items()})
    write_atomic(out / "comparison.json", json.dumps(jsonable(data), indent=1))
    return out / "README.md"


def publish(report, figures=True, log=None):
    """Draw the figures of a reproduction (figures/*.png) and write its README.md and
    comparison.json: the second half of `flexmbs reproduce`, after
    `flexmbs.paper.reproduce.reproduce` has run the jobs."""
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
