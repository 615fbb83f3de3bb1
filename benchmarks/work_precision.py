"""Work-precision of flexmbs against Exudyn on the robot of docs/paper-cases.md (p = 50 mm, deviation (30)).

Both codes run the same model (see common.py): quadratic 3-node geometrically exact beams,
2, 8, 32, 128 elements per arm, static start, generalized-alpha with rho_inf = 0.5, steps
h = 4e-3 ... 1.25e-4 s, side by side in one process. The error of a run is the largest
difference, over the time grid, between its deviation history (30) and that of one common fine
reference: flexmbs with REF_ELEMENTS quadratic elements per arm at h_ref = h_min / 8.
(h_ref divides every h of the sweep, so no interpolation is needed; its own error is estimated
in the table "reference" by halving h_ref and the mesh.)

Every code runs in each of its configurations (flexmbs: dense / KLU x full / modified Newton;
Exudyn: EXUdense / EigenSparse x full / modified Newton); the time of a point is the smallest
process CPU time of up to 3 repeats. The comparison "at equal error" uses each code's Pareto
front (the cheapest configuration and step that reach a given error), interpolated linearly
in log(time) against log(error).

Exudyn's default Newton tolerance (1e-8 relative to the first residual) lies below the
round-off floor of this stiff model from 8 elements per arm on: its adaptive step control
then cuts the steps by 10-100x and the run changes. Here the fixed-step configurations use the
tightest of 1e-8, 1e-7, ... 1e-4 with which the fixed-step run completes (column rtol), and one
more configuration, "ex sparse modified adaptive", runs under Exudyn's own step control
(adaptiveStep) with the tightest of them at which it keeps to at most 1.5x the fixed steps
(column "ex steps": the steps it took);
the same for its static solver (1e-6 up to 32, 1e-4 at 128 elements per arm). Their effect on
the answer is visible in "|fx-ex|", the difference of the two codes' deviation histories at
equal mesh and step.

flexmbs's error-controlled steps (time.h = "auto", flexmbs.analysis.adaptive) are one more
configuration, "fx auto": per mesh and relative tolerance rtol (ADAPTIVE_RTOLS), the grid that
choose_steps gives for the case cases/robot_2dof.toml (the same robot, p = 50 mm, its
deviation responses (28) and (30), outputs every OUTPUT s) with that mesh, then the same model
as the fixed-step runs integrated on it (simulate's defaults and KLU with modified Newton);
its CPU time is given without and with the grid choice (the two pilot runs, once per
optimization run), and its error is read on the OUTPUT grid against the same reference. The
table "Adaptive steps" sets each of its runs against the fixed-step fronts of both codes at the
error it reached.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np

from common import (ExudynFailed, ExudynRobot, deviation30, exudyn_available, format_table,
                    pyplot, robot_flexmbs, time_call)
from flexmbs.analysis.settings import SimulationSettings

T_END = 0.65
H_FULL = [4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4]
NEL_FULL = [2, 8, 32, 128]
H_QUICK = [2e-3, 1e-3, 5e-4, 2.5e-4]
NEL_QUICK = [2, 8]
EXUDYN_RTOLS = [1e-8, 1e-7, 1e-6, 1e-5, 1e-4]
EXUDYN_STATIC_RTOLS = [1e-8, 1e-7, 1e-6, 1e-5, 1e-4]
# (solver, newton); None, None: flexmbs.analysis.simulate's defaults (solver 'auto', newton 'auto'), as
# `flexmbs simulate` runs; its ratio to Exudyn is also reported alone ("fx default")
FLEXMBS_CONFIGS = [("dense", "full"), ("dense", "reuse"), ("klu", "full"), ("klu", "reuse"),
                   (None, None)]
# (sparse, modified, adaptive): fixed steps, and Exudyn's own step control (adaptiveStep) with
# its fastest fixed-step configuration (sparse, modified Newton) at a workable tolerance
EXUDYN_CONFIGS = [(False, False, False), (False, True, False), (True, False, False),
                  (True, True, False), (True, True, True)]
DENSE_LIMIT_ELEMENTS = 32     # no dense runs (either code) above this many elements per arm
# flexmbs adaptive steps: relative tolerances of the responses, the response grid's spacing (a
# step of every sweep, so that the reference's grid contains it) and the configurations
ADAPTIVE_RTOLS = [1e-2, 3e-3, 1e-3, 3e-4, 1e-4]
ADAPTIVE_RTOLS_QUICK = [1e-2, 1e-3, 1e-4]
OUTPUT = 5e-4
ADAPTIVE_CONFIGS = [("klu", "reuse"), (None, None)]


def steps_for(h, t_end=T_END):
    """Smallest whole number of steps covering t_end (t_end need not be a multiple of h)."""
    return int(math.ceil(t_end / h - 1e-9))


# ----------------------------------------------------------------------------- runs
def run_flexmbs(model, tip_node, h, solver, newton, repeats=3, budget=2.0, steps=None):
    """One flexmbs configuration: (t, dev (m), Timing, stats). newton: 'full', 'reuse', 'auto',
    or True/False for 'reuse'/'full'; solver and newton None: simulate's defaults. steps: a
    step grid (times) to integrate on, outputs every h."""
    import flexmbs as fx
    n = steps_for(h) if steps is None else int(round(steps[-1] / h))
    kw_steps = {} if steps is None else dict(steps=steps)
    if isinstance(newton, bool):
        newton = "reuse" if newton else "full"
    kw = {}
    if solver is not None:
        kw["solver"] = solver
    if newton is not None:
        kw["newton"] = newton
    model.compile()
    model.pattern(solver or "klu")         # one-time structure work, like Exudyn's Assemble

    def call():
        return fx.simulate(model, n * h, h,
                           settings=SimulationSettings(start="static", store=[tip_node], **kw),
                           **kw_steps)
    res, timing = time_call(call, repeats=repeats, budget=budget)
    return res.t, deviation30(res.t, res.position(tip_node)), timing, res.stats


def adaptive_grid(nel, rtol):
    """(times, CPU s of the choice): the step grid flexmbs.analysis.adaptive.choose_steps gives for
    the robot case (cases/robot_2dof.toml at its start, p = 50 mm, as robot_flexmbs) with `nel`
    elements per arm, T_END, outputs every OUTPUT s, at relative tolerance `rtol`; the choice
    timed warm (the problem's one-time parts built by a first choice)."""
    import time as _time
    from flexmbs.problem import Problem
    p = Problem("robot_2dof", {"time.t_end": T_END, "time.h": "auto", "time.rtol": rtol,
                               "time.output": OUTPUT, "bodies.arm1.elements": nel,
                               "bodies.arm2.elements": nel})
    p.adapt()
    c0 = _time.process_time()
    grid = p.adapt()
    return grid, _time.process_time() - c0


def run_exudyn(nel, h, sparse, modified, rtols, repeats=3, budget=2.0, adaptive=False):
    """One Exudyn configuration with the tightest working Newton tolerances: dynamic from
    `rtols`, static from EXUDYN_STATIC_RTOLS (the working one is remembered per mesh).
    adaptive=True: Exudyn's own step control; a tolerance then "works" when the run keeps to
    at most 1.5 times the fixed steps (with 1e-8, Exudyn's default, it cut them 10-20x at 8
    elements per arm: 14 000 steps instead of 1300, 4-8 s, off the output grid).

    Returns (t, dev, Timing, stats) or None if no tolerance works.
    """
    n = steps_for(h)
    srtol = _static_rtol(nel)
    for rtol in rtols:
        def setup():
            rob = ExudynRobot(nel)
            return rob, rob.settings(h, n * h, modified_newton=modified, sparse=sparse, rtol=rtol,
                                     static_rtol=srtol, adaptive=adaptive)

        def call(arg):
            rob, ss = arg
            t, tip = rob.run(ss)
            if adaptive and rob.stats["steps"] > 1.5 * n:
                raise ExudynFailed(f"adaptive steps: {rob.stats['steps']} for {n} fixed ones")
            return t, tip, rob.stats
        try:
            (t, tip, stats), timing = time_call(call, repeats=repeats, budget=budget, setup=setup)
        except ExudynFailed:
            continue
        stats = dict(stats, rtol=rtol, static_rtol=srtol)
        return t, deviation30(t, tip), timing, stats
    return None


_STATIC_RTOL = {}


def _static_rtol(nel):
    """Tightest static Newton tolerance of EXUDYN_STATIC_RTOLS with which Exudyn's static
    solver converges on this mesh (cached)."""
    if nel not in _STATIC_RTOL:
        _STATIC_RTOL[nel] = EXUDYN_STATIC_RTOLS[-1]
        for srtol in EXUDYN_STATIC_RTOLS:
            rob = ExudynRobot(nel)
            ss = rob.settings(1e-3, 1e-3, static_rtol=srtol)
            rob.exu.SetWriteToConsole(False)
            try:
                ok = rob.mbs.SolveStatic(ss)
            except Exception:
                ok = False
            finally:
                rob.exu.SetWriteToConsole(True)
            if ok:
                _STATIC_RTOL[nel] = srtol
                break
    return _STATIC_RTOL[nel]


def history_error(t, dev, ref_t, ref_dev, t_max=T_END):
    """max |dev(t) - dev_ref(t)| over the run's grid points t <= t_max (reference grid ⊇ run grid)."""
    h_ref = ref_t[1] - ref_t[0]
    sel = t <= t_max + 1e-9
    idx = np.rint(t[sel] / h_ref).astype(int)
    if np.any(np.abs(ref_t[idx] - t[sel]) > 1e-9):
        raise ValueError("the reference grid does not contain the run's grid")
    return float(np.max(np.abs(dev[sel] - ref_dev[idx])))


# ----------------------------------------------------------------------------- Pareto / ratio
EQUAL_ERROR_RTOL = 0.05   # errors within 5 % count as equal (Newton-tolerance noise between configs)


def pareto_front(points, rtol=EQUAL_ERROR_RTOL):
    """Cheapest way to each error level: points (err, time) -> front sorted by time, errors falling.

    A point joins the front only if its error is more than `rtol` below the previous one's:
    configurations of one mesh and step differ only by their Newton tolerances.
    """
    front = []
    for err, t in sorted(points, key=lambda p: (p[1], p[0])):
        if err > 0 and (not front or err < front[-1][0] * (1 - rtol)):
            front.append((err, t))
    return front


def time_at_error(front, err, rtol=EQUAL_ERROR_RTOL):
    """Time to reach error `err` on a front, log-log interpolated between its points.

    Errors within `rtol` of the front's best count as reached by it; None if the front never
    gets that accurate.
    """
    if not front or err * (1 + rtol) < front[-1][0]:
        return None
    if err <= front[-1][0]:
        return front[-1][1]
    if err >= front[0][0]:
        return front[0][1]
    for (e0, t0), (e1, t1) in zip(front[:-1], front[1:]):
        if e1 <= err <= e0:
            s = (math.log(err) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + s * (math.log(t1) - math.log(t0)))
    return None


# ----------------------------------------------------------------------------- main
def run(quick=False, outdir="benchmarks/results", log=print, elements=None, ref_elements=None):
    """Run the work-precision benchmark; prints tables, writes plots and a JSON of all numbers.
    elements, ref_elements: the meshes (elements per arm) and the reference's instead of the
    sweep's (quick: 2, 8 and 32; else 2, 8, 32, 128 and 128)."""
    h_list = H_QUICK if quick else H_FULL
    nel_list = elements or (NEL_QUICK if quick else NEL_FULL)
    ref_nel = ref_elements or (32 if quick else 128)
    h_ref = min(h_list) / 8
    repeats, budget = (1, 0.5) if quick else (3, 2.0)
    have_exudyn, exu_info = exudyn_available()
    log(f"Exudyn: {exu_info if have_exudyn else 'NOT AVAILABLE - ' + exu_info}")
    out = dict(h=h_list, elements=nel_list, ref_elements=ref_nel, h_ref=h_ref, t_end=T_END,
               exudyn=exu_info if have_exudyn else None, runs=[], reference={})

    # --- the common reference and estimates of its own error
    log(f"reference: flexmbs, {ref_nel} quadratic elements per arm, h = {h_ref:g} s, "
        f"{steps_for(h_ref)} steps ...")
    m_ref, _, a2_ref = robot_flexmbs(ref_nel)
    ref_t, ref_dev, ref_timing, _ = run_flexmbs(m_ref, a2_ref.last, h_ref, "klu", True, repeats=1)
    m_half, _, a2_half = robot_flexmbs(ref_nel // 2)
    t_h, dev_h, _, _ = run_flexmbs(m_half, a2_half.last, h_ref, "klu", True, repeats=1)
    t_2, dev_2, _, _ = run_flexmbs(m_ref, a2_ref.last, 2 * h_ref, "klu", True, repeats=1)
    e_mesh = history_error(ref_t, dev_h, ref_t, ref_dev)
    e_step = history_error(t_2, dev_2, ref_t, ref_dev)
    out["reference"] = dict(cpu=ref_timing.best, max_dev_mm=float(ref_dev.max() * 1e3),
                            diff_half_mesh_mm=e_mesh * 1e3, diff_double_step_mm=e_step * 1e3)
    log(format_table(
        ["reference", "max dev (mm)", "|ref - half mesh| (mm)", "|ref - 2 h_ref| (mm)",
         "est. ref error (mm)", "cpu (s)"],
        [[f"{ref_nel} el/arm, h={h_ref:g}", ref_dev.max() * 1e3, e_mesh * 1e3, e_step * 1e3,
          max(e_step / 3, e_mesh / 3) * 1e3, ref_timing.best]],
        title="Reference (error estimate: second order in h, >= 2nd order in the mesh: diff / 3)"))

    # --- same-mesh fine runs (temporal error alone)
    same_mesh = {}
    for nel in nel_list:
        if nel == ref_nel:
            same_mesh[nel] = (ref_t, ref_dev)
            continue
        m, _, a2 = robot_flexmbs(nel)
        t, dev, _, _ = run_flexmbs(m, a2.last, h_ref, "klu", True, repeats=1)
        same_mesh[nel] = (t, dev)

    # --- the sweep
    rows_all = []
    for nel in nel_list:
        m, _, a2 = robot_flexmbs(nel)
        rtol_start = {cfg: 0 for cfg in EXUDYN_CONFIGS}
        for h in h_list:
            results = {}
            for solver, newton in FLEXMBS_CONFIGS:
                if solver == "dense" and nel > DENSE_LIMIT_ELEMENTS:
                    continue
                t, dev, timing, st = run_flexmbs(m, a2.last, h, solver, newton, repeats, budget)
                name = "fx default" if solver is None else \
                    f"fx {solver}{' reuse' if newton == 'reuse' else ''}"
                results[name] = (t, dev, timing, dict(iterations=st["newton_iterations"],
                                                       factorizations=st["factorizations"],
                                                       unknowns=st["unknowns"]))
            if have_exudyn:
                for cfg in EXUDYN_CONFIGS:
                    sparse, modified, adaptive = cfg
                    if not sparse and nel > DENSE_LIMIT_ELEMENTS:
                        continue
                    r = run_exudyn(nel, h, sparse, modified, EXUDYN_RTOLS[rtol_start[cfg]:],
                                   repeats, budget, adaptive=adaptive)
                    name = (f"ex {'sparse' if sparse else 'dense'}{' modified' if modified else ''}"
                            f"{' adaptive' if adaptive else ''}")
                    if r is None:
                        log(f"  Exudyn {name}: no Newton tolerance up to 1e-4 completes "
                            f"{nel} el/arm at h = {h:g}")
                        continue
                    t, dev, timing, st = r
                    rtol_start[cfg] = EXUDYN_RTOLS.index(st["rtol"])
                    results[name] = (t, dev, timing, dict(iterations=st["newton_iterations"],
                                                           factorizations=st["jacobians"],
                                                           rtol=st["rtol"], static_rtol=st["static_rtol"],
                                                           steps=st["steps"] - 1))
            fx_dev_ref = None
            for name, (t, dev, timing, st) in results.items():
                err = history_error(t, dev, ref_t, ref_dev)
                st_t, st_dev = same_mesh[nel]
                err_time = history_error(t, dev, st_t, st_dev)
                if name.startswith("fx") and fx_dev_ref is None:
                    fx_dev_ref = (t, dev)
                diff = None
                if fx_dev_ref is not None and name.startswith("ex"):
                    diff = float(np.max(np.abs(dev - fx_dev_ref[1])))
                row = dict(elements=nel, h=h, config=name, code=name[:2], err_mm=err * 1e3,
                           err_same_mesh_mm=err_time * 1e3, cpu=timing.cpu_min,
                           cpu_median=timing.cpu_median, wall=timing.wall_min, repeats=timing.runs,
                           diff_fx_mm=None if diff is None else diff * 1e3, **st)
                out["runs"].append(row)
                rows_all.append(row)
            log(f"  {nel:4d} el/arm  h = {h:<8g} done: " + ", ".join(
                f"{k} {v[2].best * 1e3:.1f} ms" for k, v in results.items()))
        # --- flexmbs with error-controlled steps
        for rtol in (ADAPTIVE_RTOLS_QUICK if quick else ADAPTIVE_RTOLS):
            grid, choice = adaptive_grid(nel, rtol)
            for solver, newton in ADAPTIVE_CONFIGS:
                t, dev, timing, st = run_flexmbs(m, a2.last, OUTPUT, solver, newton,
                                                 repeats, budget, steps=grid)
                name = "fx auto" + ("" if solver is None else
                                    f" {solver}{' reuse' if newton == 'reuse' else ''}")
                err = history_error(t, dev, ref_t, ref_dev)
                st_t, st_dev = same_mesh[nel]
                out["runs"].append(dict(
                    elements=nel, h=None, rtol=rtol, config=name, code="fa",
                    err_mm=err * 1e3,
                    err_same_mesh_mm=history_error(t, dev, st_t, st_dev) * 1e3,
                    cpu=timing.cpu_min, cpu_median=timing.cpu_median, wall=timing.wall_min,
                    repeats=timing.runs, choice_cpu=choice, steps=int(grid.size - 1),
                    iterations=st["newton_iterations"], factorizations=st["factorizations"],
                    unknowns=st["unknowns"]))
            log(f"  {nel:4d} el/arm  rtol = {rtol:<8g} done: {grid.size - 1} steps, "
                f"choice {choice * 1e3:.0f} ms")

    report(out, log)
    _save(out, outdir, log)
    plot(out, outdir, log)
    return out


def _best(runs, code, nel, h):
    cand = [r for r in runs if r["code"] == code and r["elements"] == nel and r["h"] == h]
    return min(cand, key=lambda r: r["cpu"]) if cand else None


def report(out, log=print):
    """Print the tables of a finished (or loaded) work-precision run."""
    adaptive_runs = [r for r in out["runs"] if r["code"] == "fa"]
    runs = [r for r in out["runs"] if r["code"] != "fa"]
    # all configurations
    rows = []
    for r in runs:
        rows.append([r["elements"], r["h"], r["config"], r["cpu"] * 1e3, r["wall"] * 1e3,
                     r["err_mm"], r["err_same_mesh_mm"], r.get("iterations"), r.get("factorizations"),
                     f"{r['rtol']:.0e}/{r['static_rtol']:.0e}" if "rtol" in r else "",
                     r.get("steps", "")])
    log(format_table(["el/arm", "h (s)", "config", "cpu (ms)", "wall (ms)", "err (mm)",
                      "err same mesh (mm)", "Newton it", "factor./Jac", "ex rtol dyn/static",
                      "ex steps"], rows,
                     title="\nAll runs (cpu = min process CPU time over the repeats; err = max |dev - dev_ref| "
                           "over t <= 0.65 s)"))
    # best of each code per point, and ratio
    rows = []
    for nel in out["elements"]:
        for h in out["h"]:
            f, e = _best(runs, "fx", nel, h), _best(runs, "ex", nel, h)
            if f is None:
                continue
            rows.append([nel, h, f["config"], f["cpu"] * 1e3, f["err_mm"],
                         e["config"] if e else "-", e["cpu"] * 1e3 if e else None,
                         e["err_mm"] if e else None, e["diff_fx_mm"] if e else None,
                         e["cpu"] / f["cpu"] if e else None])
    log(format_table(["el/arm", "h (s)", "fx best", "fx cpu (ms)", "fx err (mm)", "ex best",
                      "ex cpu (ms)", "ex err (mm)", "|fx-ex| (mm)", "ex/fx time"], rows,
                     title="\nBest configuration of each code at equal mesh and step "
                           "(|fx-ex|: max difference of the two deviation histories)"))
    # equal error, per mesh and overall
    rows = []
    summary = {}
    groups = [(nel, [r for r in runs if r["elements"] == nel]) for nel in out["elements"]]
    groups.append(("all", runs))
    groups += [(f"{key} default", [r for r in rs if r["code"] == "ex" or r["config"] == "fx default"])
               for key, rs in list(groups)]
    for key, rs in groups:
        ffront = pareto_front([(r["err_mm"], r["cpu"]) for r in rs if r["code"] == "fx"])
        efront = pareto_front([(r["err_mm"], r["cpu"]) for r in rs if r["code"] == "ex"])
        ratios = []
        for err, t_ex in efront:
            t_fx = time_at_error(ffront, err)
            ratio = None if t_fx is None else t_ex / t_fx
            if ratio is not None:
                ratios.append(ratio)
            rows.append([key, err, t_ex * 1e3, None if t_fx is None else t_fx * 1e3, ratio])
        if ratios:
            summary[str(key)] = dict(min=min(ratios), max=max(ratios),
                                     geomean=float(np.exp(np.mean(np.log(ratios)))))
    log(format_table(["el/arm", "ex err (mm)", "ex cpu (ms)", "fx cpu at that err (ms)",
                      "ratio ex/fx"], rows,
                     title="\nTime ratio at equal error: Exudyn's Pareto points against flexmbs's "
                           "front (log-log interpolation; '-' = flexmbs never that accurate)"))
    log(format_table(["el/arm", "min ratio", "geo-mean ratio", "max ratio"],
                     [[k, v["min"], v["geomean"], v["max"]] for k, v in summary.items()],
                     title="\nSummary of ex/fx time ratios at equal error (target: >= 10 "
                           "everywhere; 'N default': flexmbs with simulate's defaults alone)"))
    out["ratio_summary"] = summary
    if adaptive_runs:
        report_adaptive(out, adaptive_runs, runs, log)


def report_adaptive(out, adaptive_runs, runs, log=print):
    """The table of flexmbs's adaptive runs against both codes' fixed-step fronts (the same
    mesh) at the error each reached."""
    rows, table = [], []
    for r in adaptive_runs:
        same = [q for q in runs if q["elements"] == r["elements"]]
        fixed = pareto_front([(q["err_mm"], q["cpu"]) for q in same if q["code"] == "fx"])
        exu = pareto_front([(q["err_mm"], q["cpu"]) for q in same if q["code"] == "ex"])
        t_fx, t_ex = time_at_error(fixed, r["err_mm"]), time_at_error(exu, r["err_mm"])
        # the steps of flexmbs's fixed-step runs that reach this error (log-log in h)
        pts = sorted({(q["h"], q["err_mm"]) for q in same if q["config"] == "fx default"})
        n_fx = None
        for (h0, e0), (h1, e1) in zip(pts[:-1], pts[1:]):
            if min(e0, e1) <= r["err_mm"] <= max(e0, e1) and e0 != e1:
                u = (math.log(r["err_mm"]) - math.log(e0)) / (math.log(e1) - math.log(e0))
                n_fx = T_END / math.exp(math.log(h0) + u * (math.log(h1) - math.log(h0)))
        row = dict(elements=r["elements"], rtol=r["rtol"], config=r["config"],
                   steps=r["steps"], err_mm=r["err_mm"], cpu=r["cpu"],
                   choice_cpu=r["choice_cpu"], fixed_steps=n_fx, fixed_cpu=t_fx, exudyn_cpu=t_ex)
        table.append(row)
        rows.append([r["elements"], r["rtol"], r["config"], r["steps"],
                     None if n_fx is None else round(n_fx), r["err_mm"], r["cpu"] * 1e3,
                     r["choice_cpu"] * 1e3,
                     None if t_fx is None else t_fx * 1e3,
                     None if t_ex is None else t_ex * 1e3,
                     None if t_fx is None else t_fx / r["cpu"],
                     None if t_fx is None else t_fx / (r["cpu"] + r["choice_cpu"]),
                     None if t_ex is None else t_ex / r["cpu"]])
    log(format_table(["el/arm", "rtol", "config", "steps", "fx fixed steps at that err",
                      "err (mm)", "cpu (ms)", "choice cpu (ms)", "fx fixed cpu at that err (ms)",
                      "ex cpu at that err (ms)", "fixed/auto", "fixed/(auto+choice)",
                      "ex/auto"], rows,
                     title="\nAdaptive steps (flexmbs time.h = \"auto\") against the fixed-step "
                           "fronts of the same mesh at the error reached (log-log "
                           "interpolation; '-' = that front never that accurate or not that "
                           "coarse)"))
    out["adaptive"] = table


def _save(out, outdir, log):
    os.makedirs(outdir, exist_ok=True)
    path = os.path.join(outdir, "work_precision.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1, default=float)
    log(f"wrote {path}")


def plot(out, outdir, log=print):
    """Work-precision and convergence plots (PNG) into outdir."""
    plt = pyplot()
    if plt is None:
        log("matplotlib missing: no plots")
        return
    runs = out["runs"]
    colors = dict(zip(out["elements"], ["tab:blue", "tab:orange", "tab:green", "tab:red"]))
    fig, ax = plt.subplots(1, 2, figsize=(13, 5.2))
    for nel in out["elements"]:
        for code, mk, ls in (("fx", "o", "-"), ("ex", "s", "--")):
            pts = [_best(runs, code, nel, h) for h in out["h"]]
            pts = [p for p in pts if p]
            if not pts:
                continue
            ax[0].loglog([p["err_mm"] for p in pts], [p["cpu"] for p in pts], mk + ls,
                         color=colors[nel], label=f"{'flexmbs' if code == 'fx' else 'Exudyn'} {nel} el/arm",
                         mfc="none" if code == "ex" else None)
            ax[1].loglog([p["h"] for p in pts], [p["err_same_mesh_mm"] for p in pts], mk + ls,
                         color=colors[nel], mfc="none" if code == "ex" else None,
                         label=f"{'flexmbs' if code == 'fx' else 'Exudyn'} {nel} el/arm")
    for nel in out["elements"]:
        pts = sorted((r for r in runs if r["code"] == "fa" and r["elements"] == nel
                      and r["config"] == "fx auto"), key=lambda r: r["rtol"])
        if pts:
            ax[0].loglog([p["err_mm"] for p in pts], [p["cpu"] for p in pts], "^:",
                         color=colors[nel], label=f"flexmbs auto steps {nel} el/arm")
    hh = np.array(out["h"])
    some = [r["err_same_mesh_mm"] for r in runs if r["h"] == hh.min()]
    if some:
        ax[1].loglog(hh, 0.5 * min(some) * (hh / hh.min()) ** 2, "k:", label="slope 2")
    from matplotlib.ticker import NullFormatter
    ax[1].xaxis.set_minor_formatter(NullFormatter())
    ax[0].set_xlabel("error of the deviation history vs common reference (mm)")
    ax[0].set_ylabel("CPU time, best configuration (s)")
    ax[0].set_title("Work-precision, robot p = 50 mm, 0.65 s")
    ax[0].grid(True, which="both", alpha=0.3)
    ax[0].legend(fontsize=7)
    ax[1].set_xlabel("h (s)")
    ax[1].set_ylabel("error vs same mesh at h_ref (mm)")
    ax[1].set_title("Convergence in h of both codes")
    ax[1].grid(True, which="both", alpha=0.3)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    path = os.path.join(outdir, "work_precision.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    log(f"wrote {path}")
