"""Scaling of the cost per step with the number of unknowns: dense LAPACK LU against KLU.

Model: one flexible arm, a hollow aluminium tube (d = 20 mm, wall 2 mm, 1 m long) pinned at
the origin, its root rotation driven by theta(t) = 0.5 (1 - cos(pi t / 0.1)) rad (smooth,
starting at rest), 0.5 kg at the tip, gravity -y, static start, h = 5e-4 s, quadratic
elements from 2 to 4000 (unknowns n = 6 n_el + 3 + 3 constraints).

Each (size, solver, Newton variant) runs in its own Python process, so that its peak memory
(VmHWM after the simulations, less the resident memory just before them: the peak is reset
with /proc/self/clear_refs after the model is built) and timing are its own. The
cost per step is (T(N2) - T(N1)) / (N2 - N1) from two runs of N1 and N2 steps (each the min
CPU time of up to 3 repeats): the static start, the Python set-up and KLU's symbolic analysis
cancel. N2 is chosen from a trial run so that the difference takes about a second.

Dense runs stop above DENSE_MAX_N unknowns (a dense factorization of 3000 unknowns already
takes ~1 s on one core, and memory grows as n^2).

The KLU sweep (`klu_sweep`) goes on to ~10^5 unknowns (16 000 elements,
96 006 unknowns) with the default settings (KLU, newton='auto'): time per step, time per step
and unknown, and memory beside it: the process's peak resident memory (getrusage ru_maxrss),
its growth during the simulations and flexmbs's own estimate (flexmbs.analysis.simulate.memory_estimate).
`python benchmarks/scaling.py --klu [--max-elements N]` runs it alone (each size once).
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np

from common import format_table, pyplot
from flexmbs.analysis.settings import SimulationSettings

ELEMENTS_FULL = [2, 4, 8, 16, 32, 64, 125, 250, 500, 1000, 2000, 4000]
ELEMENTS_QUICK = [2, 8, 32, 125, 500]
#: the KLU sweep to ~10^5 unknowns (n = 6 n_el + 6)
ELEMENTS_KLU = [125, 500, 2000, 4000, 8000, 16000]
ELEMENTS_KLU_QUICK = [125, 500, 2000]
DENSE_MAX_N = 3100


def arm_model(elements):
    """The single driven arm (see the module docstring): (model, arm Body)."""
    import flexmbs as fx
    mat = fx.Material(E=72e9, nu=0.3, rho=2700)
    m = fx.Model("arm")
    arm = m.add_beam("arm", (0.0, 0.0), (1.0, 0.0), elements, material=mat,
                     section=fx.Tube.with_wall_ratio(0.02, 0.1))
    w = math.pi / 0.1
    law = fx.TimeLaw(lambda t: 0.5 * (1 - np.cos(w * t)), lambda t: 0.5 * w * np.sin(w * t),
                     lambda t: 0.5 * w * w * np.cos(w * t), name="arm drive")
    m.pin(arm.first)
    m.drive_rotation(arm.first, law)
    m.add_point_mass(arm.last, 0.5)
    m.set_gravity(0.0, -9.81)
    return m, arm


def _peak_rss():
    """Peak resident memory of this process (kB): VmHWM, or ru_maxrss."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1])
    except OSError:
        pass
    import resource
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def _reset_peak_rss():
    """Reset the peak to the current resident memory (Linux clear_refs 5); returns it (kB)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    return _peak_rss()


def _child(cfg):
    """Measure one configuration in this (fresh) process; returns a dict."""
    import time

    import flexmbs as fx
    import resource
    from flexmbs.analysis.simulate import memory_estimate
    m, arm = arm_model(cfg["elements"])
    n = m.compile().n
    m.pattern(cfg["solver"])
    h = 5e-4
    rss0 = _reset_peak_rss()
    newton = cfg.get("newton") or ("reuse" if cfg["reuse"] else "full")

    def timed(steps):
        best, res = float("inf"), None
        for _ in range(cfg["repeats"]):
            c0 = time.process_time()
            res = fx.simulate(m, steps * h, h,
                              settings=SimulationSettings(start="static", store=[arm.last],
                                                          solver=cfg["solver"], newton=newton))
            best = min(best, time.process_time() - c0)
            if best * cfg["repeats"] > 4 * cfg["budget"]:
                break
        return best, res
    n1 = cfg["n1"]
    t1, r1 = timed(n1)
    t_trial, _ = timed(n1 + 8)
    per = max((t_trial - t1) / 8, 1e-7)
    n2 = n1 + int(min(max(cfg["budget"] / per, 8), cfg["max_steps"]))
    t2, r2 = timed(n2)
    rss1 = _peak_rss()
    it = (r2.stats["newton_iterations"] - r1.stats["newton_iterations"]) / (n2 - n1)
    fa = (r2.stats["factorizations"] - r1.stats["factorizations"]) / (n2 - n1)
    est = memory_estimate(m, n2 * h, h,
                          settings=SimulationSettings(store=[arm.last], solver=cfg["solver"]))
    return dict(elements=cfg["elements"], unknowns=n, solver=cfg["solver"], reuse=cfg["reuse"],
                newton=newton, per_step=(t2 - t1) / (n2 - n1), n1=n1, n2=n2, t1=t1, t2=t2,
                iterations_per_step=it, factorizations_per_step=fa,
                peak_rss_mb=rss1 / 1024, base_rss_mb=rss0 / 1024, sim_mb=(rss1 - rss0) / 1024,
                maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                estimate_mb=est.total / 1e6)


def measure(elements, solver, reuse, budget=1.0, repeats=3, timeout=900, newton=None):
    """Run one configuration in a child process; returns its dict or None on failure."""
    cfg = dict(elements=elements, solver=solver, reuse=reuse, budget=budget, repeats=repeats,
               n1=4, max_steps=4000, newton=newton)
    cmd = [sys.executable, os.path.abspath(__file__), "--child", json.dumps(cfg)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return dict(elements=elements, solver=solver, reuse=reuse, error="timeout")
    if p.returncode != 0:
        return dict(elements=elements, solver=solver, reuse=reuse,
                    error=(p.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(p.stdout.strip().splitlines()[-1])


def loglog_slope(x, y):
    """Least-squares slope of log y against log x."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    return float(np.polyfit(x, y, 1)[0])


def run(quick=False, outdir="benchmarks/results", log=print):
    """Sweep sizes for dense and KLU, full Newton and reuse_jacobian; print, plot, save JSON."""
    from flexmbs.analysis.simulate import DENSE_MAX_UNKNOWNS
    elements = ELEMENTS_QUICK if quick else ELEMENTS_FULL
    budget, repeats = (0.25, 2) if quick else (1.0, 3)
    results = []
    for nel in elements:
        for reuse in (False, True):
            for solver in ("dense", "klu"):
                n = 6 * nel + 6
                if solver == "dense" and n > DENSE_MAX_N:
                    continue
                r = measure(nel, solver, reuse, budget, repeats)
                results.append(r)
                if "error" in r:
                    log(f"  {nel} el {solver} reuse={reuse}: FAILED {r['error']}")
                else:
                    log(f"  {nel:5d} el  n={r['unknowns']:6d}  {solver:5s} reuse={reuse!s:5s} "
                        f"{r['per_step'] * 1e6:10.1f} us/step  it/step {r['iterations_per_step']:.2f}  "
                        f"+{r['sim_mb']:.1f} MB")
    ok = [r for r in results if "error" not in r]
    rows, cross = [], {}
    for reuse in (False, True):
        for nel in elements:
            d = next((r for r in ok if r["elements"] == nel and r["solver"] == "dense" and r["reuse"] == reuse), None)
            k = next((r for r in ok if r["elements"] == nel and r["solver"] == "klu" and r["reuse"] == reuse), None)
            if k is None and d is None:
                continue
            n = (k or d)["unknowns"]
            auto = "dense" if n <= DENSE_MAX_UNKNOWNS else "klu"
            faster = None
            if d and k:
                faster = "dense" if d["per_step"] < k["per_step"] else "klu"
            elif k:
                faster = "klu"
            rows.append([nel, n, "yes" if reuse else "no",
                         d["per_step"] * 1e6 if d else None, k["per_step"] * 1e6 if k else None,
                         (d["per_step"] / k["per_step"]) if d and k else None,
                         k["per_step"] / nel * 1e6 if k else None,
                         k["iterations_per_step"] if k else None,
                         d["sim_mb"] if d else None, k["sim_mb"] if k else None,
                         auto, faster, "ok" if auto == faster or faster is None else "WRONG"])
            cross.setdefault(reuse, []).append((n, faster))
    log(format_table(["el", "unknowns", "reuse", "dense us/step", "KLU us/step", "dense/KLU",
                      "KLU us/step/el", "KLU it/step", "dense +MB", "KLU +MB",
                      f"auto (<= {DENSE_MAX_UNKNOWNS})", "faster", "auto pick"], rows,
                     title="\nCost per step (CPU, (T(N2) - T(N1)) / (N2 - N1)) and memory "
                           "(peak RSS growth of the process during the simulations)"))
    summary = {}
    for reuse in (False, True):
        ks = sorted((r["unknowns"], r["per_step"], r["elements"]) for r in ok
                    if r["solver"] == "klu" and r["reuse"] == reuse)
        big = [(n, t) for n, t, e in ks if e >= 64]
        slope = loglog_slope(*zip(*big)) if len(big) >= 2 else None
        pairs = cross.get(reuse, [])
        dense_wins = [n for n, f in pairs if f == "dense"]
        klu_wins = [n for n, f in pairs if f == "klu"]
        last_dense = max(dense_wins) if dense_wins else None
        first_klu_after = min((n for n in klu_wins if last_dense is None or n > last_dense), default=None)
        summary["reuse" if reuse else "full"] = dict(klu_slope=slope, largest_n_dense_faster=last_dense,
                                                    smallest_n_klu_faster_after=first_klu_after,
                                                    dense_wins_at=dense_wins)
    log(format_table(["Newton", "KLU cost slope (log-log, >= 64 el)", "largest n dense faster",
                      "next n (KLU faster)", "dense faster at n ="],
                     [[k, v["klu_slope"], v["largest_n_dense_faster"], v["smallest_n_klu_faster_after"],
                       ", ".join(map(str, v["dense_wins_at"])) or "none"] for k, v in summary.items()],
                     title="\nCrossover and growth (slope 1 = cost linear in the number of elements)"))
    os.makedirs(outdir, exist_ok=True)
    with open(os.path.join(outdir, "scaling.json"), "w") as f:
        json.dump(dict(runs=results, summary=summary, dense_max_unknowns=DENSE_MAX_UNKNOWNS), f,
                  indent=1, default=float)
    _plot(ok, outdir, log)
    large = klu_sweep(ELEMENTS_KLU_QUICK if quick else ELEMENTS_KLU, budget, log)
    with open(os.path.join(outdir, "scaling_klu.json"), "w") as f:
        json.dump(large, f, indent=1, default=float)
    return dict(runs=results, summary=summary, klu=large)


def klu_sweep(elements=ELEMENTS_KLU, budget=1.0, log=print):
    """KLU with the default settings (newton='auto') up to ~10^5 unknowns, each size once in a
    fresh process (one repeat above 2000 elements): time per step and memory side by side."""
    rows, runs = [], []
    for nel in elements:
        r = measure(nel, "klu", False, budget, 1 if nel > 2000 else 3, newton="auto")
        runs.append(r)
        if "error" in r:
            log(f"  {nel} el: FAILED {r['error']}")
            continue
        rows.append([nel, r["unknowns"], r["per_step"] * 1e3, r["per_step"] / r["unknowns"] * 1e6,
                     r["iterations_per_step"], r["factorizations_per_step"], r["n2"] - r["n1"],
                     r["maxrss_mb"], r["sim_mb"], r["estimate_mb"]])
        log(f"  {nel:6d} el  n={r['unknowns']:6d}  {r['per_step'] * 1e3:9.3f} ms/step  "
            f"peak RSS {r['maxrss_mb']:.0f} MB", )
    ok = [r for r in runs if "error" not in r]
    big = [(r["unknowns"], r["per_step"]) for r in ok if r["elements"] >= 500]
    slope = loglog_slope(*zip(*big)) if len(big) >= 2 else None
    log(format_table(["el", "unknowns", "ms/step", "us/step/unknown", "it/step", "fact/step",
                      "steps timed", "peak RSS MB", "RSS growth MB", "flexmbs estimate MB"],
                     rows, title="\nKLU, newton='auto' (the defaults): CPU time per step "
                                 "((T(N2) - T(N1)) / (N2 - N1)) and memory"))
    if slope is not None:
        log(f"log-log slope of the time per step against the unknowns (>= 500 elements): "
            f"{slope:.3f} (1 = linear)")
    return dict(runs=runs, slope=slope)


def _plot(ok, outdir, log):
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(1, 2, figsize=(13, 5))
    for solver, c in (("dense", "tab:blue"), ("klu", "tab:red")):
        for reuse, ls in ((False, "-"), (True, "--")):
            rs = sorted((r for r in ok if r["solver"] == solver and r["reuse"] == reuse),
                        key=lambda r: r["unknowns"])
            if not rs:
                continue
            lab = f"{solver}{' reuse_jacobian' if reuse else ' full Newton'}"
            ax[0].loglog([r["unknowns"] for r in rs], [r["per_step"] * 1e6 for r in rs], "o" + ls,
                         color=c, label=lab)
            ax[1].loglog([r["unknowns"] for r in rs], [max(r["sim_mb"], 0.05) for r in rs], "o" + ls,
                         color=c, label=lab)
    nn = np.array([30, 24000.0])
    ax[0].loglog(nn, 2.0 * nn, "k:", label="slope 1")
    ax[0].loglog(nn, 1e-3 * nn ** 3 / 30, "k-.", label="slope 3")
    ax[0].set_ylim(1, None)
    ax[0].set_xlabel("unknowns (coordinates + constraints)")
    ax[0].set_ylabel("CPU time per step (us)")
    ax[0].set_title("One driven flexible arm, h = 5e-4 s")
    ax[1].set_xlabel("unknowns")
    ax[1].set_ylabel("peak RSS growth during the simulations (MB)")
    ax[1].set_title("Memory")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    path = os.path.join(outdir, "scaling.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    log(f"wrote {path}")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        print(json.dumps(_child(json.loads(sys.argv[2]))))
    elif len(sys.argv) >= 2 and sys.argv[1] == "--klu":
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from common import machine_summary
        top = int(sys.argv[sys.argv.index("--max-elements") + 1]) \
            if "--max-elements" in sys.argv else max(ELEMENTS_KLU)
        print(f"scaling, KLU sweep: {machine_summary()}")
        klu_sweep([e for e in ELEMENTS_KLU if e <= top])
    else:
        print("run through benchmarks/run.py --only scaling", file=sys.stderr)
        sys.exit(2)
