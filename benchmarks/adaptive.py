"""Error-controlled steps (time.h = "auto", flexmbs.analysis.adaptive) against the best fixed step.

For each case, the relative error of its response histories (max over time and responses of
|r - r_ref|, over max |r_ref|) against a reference: fixed steps h/32 and h/64 combined by
Richardson extrapolation (second order), compared on the case's response grid. Fixed steps
sweep h = 4 h0 .. h0 / 32 (h0 the case's step); adaptive runs sweep rtol. The steps and the
CPU seconds that reach 1e-2, 1e-3 and 1e-4 are interpolated log-log between neighbouring runs
of each sweep; the adaptive run's seconds are given without and with its one-time grid choice
(the pilot runs at 2 h0 and h0, made once per optimization run and frozen: flexmbs.analysis.adaptive;
timed warm, like the runs: the problem's rigid reference and KLU analysis already built).

Cases: the robot (cases/robot_2dof.toml, 0.65 s: a cycloid move of 0.5 s, then its residual
vibration, undamped), the four-bar (cases/fourbar.toml), the press and the damped press
(cases/slider_crank_press*.toml), and a motion with a quiet phase: the robot's
point-to-point move of 0.25 s, then a dwell to 0.8 s in which its damped vibration decays
(cases/robot_2dof_dwell.toml), also with 8 elements per arm (robot_dwell_fine: more work per
step, so that the CPU time follows the steps rather than the per-run overhead of these small
models, a few milliseconds).
"""
from __future__ import annotations

import json
import os
import time

import numpy as np

from flexmbs.problem import Problem

TARGETS = (1e-2, 1e-3, 1e-4)

CASES = {
    "robot": ("robot_2dof", {}),
    "fourbar": ("fourbar", {}),
    "press": ("slider_crank_press", {}),
    "press_damped": ("slider_crank_press_damped", {}),
    "robot_dwell": ("robot_2dof_dwell", {}),
    "robot_dwell_fine": ("robot_2dof_dwell", {"bodies.arm1.elements": 8,
                                              "bodies.arm2.elements": 8}),
}


def _histories(ev, stride=1):
    return {n: np.asarray(v, float)[::stride] for n, v in ev.values.items() if np.ndim(v) >= 1}


def _error(hist, ref):
    return max(float(np.abs(hist[n] - ref[n]).max() / np.abs(ref[n]).max()) for n in ref)


def _timed(problem, x=None, repeat=3):
    """The evaluation and its CPU seconds, the least of `repeat` (the first call also builds
    what a problem makes once: the rigid reference on its grid, the KLU analysis)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.process_time()
        ev = problem.evaluate(x, gradient=False)
        best = min(best, time.process_time() - t0)
    return ev, best


def _reach(points, target):
    """(steps, seconds) interpolated log-log at error `target` from (error, steps, seconds)
    points, or None when the sweep does not bracket it."""
    pts = sorted(points, key=lambda p: p[1])
    for a, b in zip(pts[:-1], pts[1:]):
        ea, eb = a[0], b[0]
        if (ea - target) * (eb - target) <= 0 and ea != eb and ea > 0 and eb > 0:
            s = np.log(target / ea) / np.log(eb / ea)
            steps = np.exp(np.log(a[1]) + s * (np.log(b[1]) - np.log(a[1])))
            sec = np.exp(np.log(a[2]) + s * (np.log(b[2]) - np.log(a[2])))
            return float(steps), float(sec)
    return None


def measure(name, case, over, quick, log):
    base = Problem(case, over)
    h0 = base.description.time.h
    fine = [Problem(case, {**over, "time.h": h0 / k}).evaluate(None, gradient=False)
            for k in (32, 64)]
    rc, rf = _histories(fine[0], 32), _histories(fine[1], 64)
    ref = {n: rf[n] + (rf[n] - rc[n]) / 3 for n in rf}
    ref_err = _error(rf, ref)
    fixed = []
    for k in ([-2, -1, 0, 1, 2, 3, 4, 5] if not quick else [-2, -1, 0, 1, 2, 3, 4]):
        h = h0 * 2.0 ** -k
        n = base.mechanism.t.size - 1
        if k < 0 and n % 2 ** -k:
            continue
        ev, sec = _timed(Problem(case, {**over, "time.h": h}))
        if k < 0:      # outputs every 2^-k points of the reference's grid
            hist, refk = _histories(ev), {n_: v[::2 ** -k] for n_, v in ref.items()}
        else:
            hist, refk = _histories(ev, 2 ** k), ref
        fixed.append((_error(hist, refk), ev.stats["steps"], sec))
    adaptive, choice = [], []
    for rtol in ([3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5] if not quick
                 else [1e-2, 1e-3, 1e-4, 3e-5]):
        p = Problem(case, {**over, "time.h": "auto", "time.rtol": rtol})
        info = {}
        p.adapt(None, info)      # the first call also builds the problem's one-time parts
        t0 = time.process_time()
        p.adapt(None, info)
        choice.append(time.process_time() - t0)
        ev, sec = _timed(p)
        adaptive.append((_error(_histories(ev), ref), ev.stats["steps"], sec, rtol))
    log(f"\n{name} ({case}{', ' + str(over) if over else ''}): reference error "
        f"{ref_err:.1e} (h0/64 against the extrapolation)")
    log("  fixed h        steps     CPU s    error")
    for (e, n, s) in fixed:
        log(f"  {base.mechanism.t_end / n:9.3g} {n:9d} {s:9.3f} {e:9.2e}")
    log("  adaptive rtol  steps     CPU s    error   (grid choice CPU s)")
    for (e, n, s, r), c in zip(adaptive, choice):
        log(f"  {r:9.0e} {n:9d} {s:9.3f} {e:9.2e}   ({c:.3f})")
    rows = []
    log("  error    fixed steps / CPU s    adaptive steps / CPU s (+ choice)   "
        "step ratio  CPU ratio (with choice)")
    for target in TARGETS:
        f = _reach(fixed, target)
        a = _reach([p[:3] for p in adaptive], target)
        row = dict(target=target, fixed=f, adaptive=a, choice=float(np.median(choice)))
        rows.append(row)
        if f is None or a is None:
            log(f"  {target:.0e}   {'not bracketed' if f is None else f'{f[0]:.0f} / {f[1]:.3f}'}"
                f"    {'not bracketed' if a is None else f'{a[0]:.0f} / {a[1]:.3f}'}")
            continue
        c = row["choice"]
        log(f"  {target:.0e}   {f[0]:9.0f} / {f[1]:.3f}      {a[0]:9.0f} / {a[1]:.3f} "
            f"(+{c:.3f})      {f[0] / a[0]:6.2f}    {f[1] / a[1]:6.2f} ({f[1] / (a[1] + c):.2f})")
    return dict(case=case, overrides=over, reference_error=ref_err, fixed=fixed,
                adaptive=adaptive, choice=choice, rows=rows)


def run(quick=False, outdir="results", log=print):
    names = ["robot", "press_damped", "robot_dwell"] if quick else list(CASES)
    out = {}
    for name in names:
        case, over = CASES[name]
        out[name] = measure(name, case, over, quick, log)
    path = os.path.join(outdir, f"adaptive{'_quick' if quick else ''}.json")
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1, default=float)
    log(f"\n(numbers in {path})")


if __name__ == "__main__":
    import sys
    run(quick="--quick" in sys.argv, outdir=os.path.join(os.path.dirname(__file__), "results"))
