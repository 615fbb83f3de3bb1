"""Reference values of an independent code (Exudyn) quoted by the test suite.

    .venv/bin/python -m pip install exudyn        # the `bench` extra; 1.13.6 when recorded
    .venv/bin/python benchmarks/reference_values.py

prints, for the robot of docs/paper-cases.md built in Exudyn by `common.ExudynRobot` (p = 50 mm,
2 quadratic ObjectBeamGeometricallyExact2D elements per arm, absolute drives, static start,
generalized-alpha, fixed steps, Newton relative tolerance 1e-8), the peak of deviation (30)
of the tip over 0.64 s at h = 6.25e-5 s for every rho_inf of
tests/test_robustness.py::test_rho_inf_second_order, and the same at h = 3.125e-5 s (the
change estimates the time-discretisation error of the value at 6.25e-5 s, second order:
(value(h) - value(h/2)) * 4/3).

The test quotes these numbers (Exudyn version and date in its comment); rerun this script
after a change of the model or of Exudyn and update them there.
"""
from __future__ import annotations

import datetime
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ExudynRobot, deviation30, exudyn_available  # noqa: E402

T_END = 0.64
H = 6.25e-5
RHO_INFS = (0.0, 0.3, 0.5, 0.8, 1.0)


def peak_deviation30(h, rho_inf, t_end=T_END):
    """Exudyn's maximum over [0, t_end] of deviation (30) (m) of the robot at p = 50 mm."""
    rob = ExudynRobot(2, p=0.05)
    t, tip = rob.run(rob.settings(h, t_end, rho_inf=rho_inf))
    return float(deviation30(t, tip).max())


def main():
    ok, version = exudyn_available()
    if not ok:
        print(f"Exudyn is not available ({version}): pip install exudyn", file=sys.stderr)
        return 1
    print(f"Exudyn {version}, {datetime.date.today().isoformat()}; robot of docs/paper-cases.md at "
          f"p = 50 mm, 2 quadratic elements per arm, t_end = {T_END} s")
    print("rho_inf   peak dev (30) at h = 6.25e-5 s (mm)   at h/2 (mm)   est. time error (mm)")
    for rho in RHO_INFS:
        a = peak_deviation30(H, rho)
        b = peak_deviation30(H / 2, rho)
        print(f"{rho:7.1f}   {a * 1e3:.9f}                      {b * 1e3:.9f}   "
              f"{(a - b) * 4 / 3 * 1e3:+.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
