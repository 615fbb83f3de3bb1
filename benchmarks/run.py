"""Run the flexmbs benchmarks: `python benchmarks/run.py [--quick] [--only NAME]`.

NAME is one of: work_precision, where_time_goes, scaling, sensitivity, optimization, newton,
damping, adaptive, continuation_grids
(default: all, in that order).
Tables go to standard output; PNG plots and JSON files of every number to benchmarks/results/
(or --out DIR). See benchmarks/README.md for what each benchmark measures.

Every run is single-threaded: OPENBLAS_NUM_THREADS=1 is set before numpy loads (pass
--blas-threads N to change it), so that timings on the shared 2-core machine are not
distorted by idle-spinning BLAS threads; times are process CPU seconds (min of repeats).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

BENCHMARKS = ("work_precision", "where_time_goes", "scaling", "sensitivity", "optimization", "newton",
              "damping", "adaptive", "continuation_grids")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sweeps (a minute or two in all)")
    ap.add_argument("--only", choices=BENCHMARKS, action="append",
                    help="run only this benchmark (repeatable)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"),
                    help="directory for plots and JSON (default: benchmarks/results)")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="OPENBLAS_NUM_THREADS / OMP_NUM_THREADS for this run (default 1)")
    args = ap.parse_args(argv)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.blas_threads)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

    import importlib

    from common import machine_summary
    print(f"flexmbs benchmarks{' (quick)' if args.quick else ''}: {machine_summary()}")
    os.makedirs(args.out, exist_ok=True)
    for name in args.only or BENCHMARKS:
        print(f"\n{'=' * 100}\n{name}\n{'=' * 100}", flush=True)
        t0 = time.perf_counter()
        mod = importlib.import_module(name)
        mod.run(quick=args.quick, outdir=args.out, log=lambda s: print(s, flush=True))
        print(f"[{name}: {time.perf_counter() - t0:.1f} s]", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
