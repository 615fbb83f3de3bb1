"""Error estimates against measured errors (flexmbs.analysis.accuracy).

For each case and several steps h, every response's estimated time-discretisation error
(Richardson on h, h/2, h/4: `Problem.evaluate(x, error=True)`) beside its true error, the
difference from a run at h0/16 (h0 the case's step; h0/32 where asked to check that reference),
and their ratio estimate / true (>= 1: over-estimate; the library promises no under-estimate
worse than 1/2 for a response in its asymptotic range, and a 'not asymptotic' verdict otherwise).

    .venv/bin/python benchmarks/error_estimates.py [--quick] [--out results/error_estimates.txt]

Cases: the robot (its start design), the four-bar at a light design near its limit, the press
(without and with 2 % material damping of the rod),
the three-arm robot, a stiff robot (E x 100: its vibrations are far above what h resolves), and
the spin-up beam of Simo & Vu-Quoc (tip deflection in the hub frame; flexmbs.analysis.simulate with the
library's `richardson` on the histories).
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from flexmbs import GivenSection, Model, Problem, TimeLaw, simulate
from flexmbs.analysis.accuracy import estimate_errors, peak_sampling, richardson
from flexmbs.analysis.settings import SimulationSettings

CASES = [
    ("robot_2dof", None, {}),
    ("fourbar", [54.11, 15.14, 16.19], {}),
    ("slider_crank_press", None, {}),
    ("slider_crank_press_damped", None, {}),
    ("three_arm_robot", None, {}),
    ("robot_2dof", None, {"materials.aluminium.E": 72e11}),
]


def _row(label, name, est, true):
    ratio = est.error / true if true > 0 else math.inf
    flag = "" if est.reliable else "  <- says not asymptotic"
    if est.reliable and ratio < 0.5:
        flag = "  <- UNDER-ESTIMATE"
    return (f"{label:34s} {name:18s} {est.value:12.6g} {est.error:10.3g} {true:10.3g} "
            f"{ratio:8.3g}  {est.status:15s}{flag}")


def case_rows(case, x, overrides, factors):
    prob = Problem(case, overrides=overrides or None)
    h0 = prob.description.time.h
    ref = prob.refined(16).evaluate(x, gradient=False)
    rows = []
    for f in factors:
        p = prob.refined(f)
        evs = [p.refined(2 ** k).evaluate(x, gradient=False) for k in range(3)]
        resp, _, _ = estimate_errors(evs, [h0 / f / 2 ** k for k in range(3)])
        label = f"{case}{' (stiff)' if overrides else ''} h0/{f}"
        for name, est in resp.items():
            v = ref.values[name]
            true = abs(est.value - (float(np.max(v)) if np.ndim(v) else float(v)))
            if est.error == 0 and true == 0:
                continue           # design-only responses (mass)
            rows.append(_row(label, name, est, true))
    return rows


def spin_up(elements=8, t_end=20.0):
    L, EA, GA, EI, rhoA, rhoI, Ts, w = 10.0, 2.8e7, 1e7, 1.4e4, 1.2, 6e-4, 15.0, 4.0

    def th(t):
        return np.where(t < Ts, (w / Ts) * (t ** 2 / 2 + (Ts / (2 * np.pi)) ** 2
                                            * (np.cos(2 * np.pi * t / Ts) - 1)),
                        w * (t - Ts / 2))

    def rate(t):
        return np.where(t < Ts, (w / Ts) * (t - Ts / (2 * np.pi) * np.sin(2 * np.pi * t / Ts)),
                        w + 0 * t)

    def acc(t):
        return np.where(t < Ts, (w / Ts) * (1 - np.cos(2 * np.pi * t / Ts)), 0 * t)

    law = TimeLaw(th, rate, acc, name="spin-up")

    def tip(h):
        m = Model("spin-up")
        b = m.add_beam("beam", (0.0, 0.0), (L, 0.0), elements=elements,
                       section=GivenSection(EA, GA, EI, rhoA, rhoI))
        m.pin(b.first)
        m.drive_rotation(b.first, law)
        r = simulate(m, settings=SimulationSettings(rho_inf=0.5), t_end=t_end, h=h)
        d = r.position(b.last) - r.position(b.first)
        a = law.value(r.t)
        return -d[:, 0] * np.sin(a) + d[:, 1] * np.cos(a)

    rows = []
    h0 = 0.01
    ref = tip(h0 / 16)
    for f in (1, 2):
        hs = [h0 / f / 2 ** k for k in range(3)]
        runs = [tip(h) for h in hs]
        n0 = runs[0].size
        common = [r[::2 ** k][:n0] for k, r in enumerate(runs)]
        peak = richardson([float(np.max(np.abs(c))) for c in common], hs)
        peak.error += peak_sampling(np.abs(common[0]))
        true = abs(peak.value - float(np.max(np.abs(ref))))
        rows.append(_row(f"spin-up h0/{f}", "max |tip defl.|", peak, true))
        est = richardson(common, hs)
        truth = float(np.max(np.abs(common[0] - ref[::16 // f][:n0])))
        rows.append(_row(f"spin-up h0/{f}", "tip defl. history", est, truth))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the cases' own step only")
    ap.add_argument("--out", help="also write the table to this file")
    args = ap.parse_args(argv)
    factors = (1,) if args.quick else (1, 2)
    t0 = time.perf_counter()
    lines = [f"{'case, step':34s} {'response':18s} {'value':>12s} {'estimate':>10s} "
             f"{'true':>10s} {'est/true':>8s}  status"]
    for case, x, ov in CASES:
        lines += case_rows(case, x, ov, factors)
        print("\n".join(lines[-6:]), file=sys.stderr)
    lines += spin_up()
    lines.append(f"wall time {time.perf_counter() - t0:.1f} s")
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
