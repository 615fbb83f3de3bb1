"""``flexmbs reproduce`` and ``flexmbs demo``: a study's tables (the paper's by default,
flexmbs.paper.study) run as jobs (flexmbs.paper.reproduce), then their figures and report
(flexmbs.paper.report.publish)."""
from __future__ import annotations

import sys
from pathlib import Path

from flexmbs.batch import check_dask
from flexmbs.cli.common import path_text, positive_int, printable
from flexmbs.errors import ModelError
from flexmbs.optimizers.library import preload
from flexmbs.paper.report import publish
from flexmbs.paper.reproduce import reproduce
from flexmbs.paper.study import load_study

__all__ = ["register", "run_reproduce", "register_demo", "run_demo", "interrupted",
           "print_report"]


def register(subparsers):
    """Add the ``reproduce`` subcommand (listed in flexmbs.cli.main.COMMANDS)."""
    p = subparsers.add_parser(
        "reproduce", help="reproduce the paper's tables and figures (or another study's), "
                          "with a report",
        description="Run the optimizations behind a study's tables (the paper's by default; "
                    "each starting point x method is one job, on local worker processes or a "
                    "Dask cluster), print every row beside the published one, draw the figures "
                    "and write DIR/README.md. Finished jobs are saved under DIR/jobs/ and not "
                    "run again.")
    p.add_argument("--study", type=path_text, metavar="FILE",
                   help="a study file (docs/study-format.md) or the name of a shipped study; "
                        "default: the paper's (cases/studies/paper.toml)")
    p.add_argument("--table", type=int, nargs="+", action="extend",
                   metavar="N", help="tables to reproduce (numbers of the study's tables, "
                                     "repeatable); default: all")
    p.add_argument("--all", action="store_true", help="every table (the default)")
    p.add_argument("--out", type=path_text, default="reproduction", metavar="DIR",
                   help="output folder (default: reproduction)")
    ex = p.add_mutually_exclusive_group()
    ex.add_argument("--workers", type=positive_int, metavar="N",
                    help="local worker processes (default: one per core; 1: serial)")
    ex.add_argument("--dask", metavar="ADDRESS",
                    help="run the jobs on a Dask cluster: a scheduler address (tcp://host:8786, "
                         "e.g. from `dask scheduler` or dask-jobqueue) or 'local' (LocalCluster)")
    p.add_argument("--quick", action="store_true",
                   help="coarse design-domain maps (11 x 11 instead of 41 x 41 simulations)")
    p.add_argument("--grid", type=int, metavar="N",
                   help="points per axis of the design-domain maps (overrides --quick)")
    p.add_argument("--force", action="store_true",
                   help="run the optimizations again even when DIR/jobs/ holds their results")
    p.add_argument("--no-figures", action="store_true", help="tables only, no PNG")
    p.set_defaults(func=run_reproduce)


def run_reproduce(args):
    tables = None if (args.all or not args.table) else args.table
    grid = args.grid if args.grid is not None else (11 if args.quick else 41)
    if grid < 2:
        raise ModelError(f"--grid must be an integer >= 2, got {grid}")
    check_dask(args.dask, "--dask")
    study = load_study(args.study)
    if tables is not None:
        bad = [t for t in tables if t not in study.tables]
        if bad:
            raise ModelError(f"--table must be among the study's tables "
                             f"{', '.join(map(str, study.tables))} ({study.path}), got "
                             f"{', '.join(map(str, bad))}")
    preload()      # a Ctrl-C mid-run must not land in a first import (library.preload)
    try:
        log = lambda s: print(printable(s, True), flush=True)        # noqa: E731
        report = reproduce(tables, args.out, workers=args.workers, dask=args.dask, grid=grid,
                           force=args.force, log=log, study=study)
        publish(report, figures=not args.no_figures, log=log)
    except KeyboardInterrupt:
        interrupted(args.command, args.out, "run the same command again to resume "
                    "(finished jobs are not run again)")
        return 130
    print_report(report)
    return 1 if report.failures else 0


def interrupted(command, out, how):
    """The one-line message of a reproduction stopped by Ctrl-C: where the finished jobs are
    and how to resume (stderr)."""
    store = Path(out) / "jobs"
    n = sum(f.name != "timings.json" for f in store.rglob("*.json")) if store.is_dir() else 0
    print(f"flexmbs {command}: interrupted; {n} finished job result(s) kept in {store}; "
          f"{how}", file=sys.stderr, flush=True)


def print_report(report):
    """Print every table beside the paper, the checks and where the report is."""
    for t in report.tables:
        print()
        print(printable(report.text(t), True))
    checks = [c for c in report.all_checks if c.ok is not None]
    print()
    if checks:
        print(printable(
            f"{sum(c.ok for c in checks)} of {len(checks)} findings of the paper reproduced"
            + ("" if all(c.ok for c in checks) else "; differing: "
               + "; ".join(f"Table {c.table}: {c.what}" for c in checks if not c.ok))))
    times = ", ".join(f"Table {t} {report.table_time(t):.1f} s" for t in report.row_tables)
    print(f"serial wall time of the runs: {times}")
    print("elapsed: " + ", ".join(f"{k} {v:.1f} s" for k, v in report.elapsed.items()))
    print(f"report: {report.out / 'README.md'}"
          + (f" ({len(report.figures)} figures in {report.out / 'figures'})"
             if report.figures else ""))


# ----------------------------------------------------------------------------- demo
def register_demo(subparsers):
    p = subparsers.add_parser(
        "demo", help="reproduce the demo table of the paper's study with both methods (under a "
                     "minute)",
        description="The demo table of the shipped study (the paper's first table, "
                    "cases/studies/paper.toml): optimize it with the weakly and the fully "
                    "coupled methods from its start design, print the results beside the "
                    "paper's, draw its figure and write a report (DIR/README.md). `flexmbs "
                    "reproduce` does the same for every table.")
    p.add_argument("--out", type=path_text, default="reproduction/demo", metavar="DIR",
                   help="output folder (default: reproduction/demo)")
    p.add_argument("--workers", type=positive_int, default=2, metavar="N",
                   help="local worker processes (default 2: one per method; 1: serial)")
    p.set_defaults(func=run_demo)


def _design_text(p):
    return "[" + ", ".join(f"{v:.2f}" for v in p) + "]"


def run_demo(args):
    study = load_study()
    demo = study.demo
    if demo is None:
        raise ModelError(f"{study.path}: the study names no demo table (key 'study.demo')")
    n = demo.table
    spec = study.tables[n]
    unit = spec.units[0] if len(set(spec.units)) == 1 else ""
    start = "[" + ", ".join(f"{v:g}" for v in spec.starts[0]) + "]"
    print(f"flexmbs demo: the paper's Table {n} ({printable(demo.about)}), weakly and fully coupled "
          f"optimizations from p = {start}{f' {unit}' if unit else ''}", flush=True)
    preload()
    try:
        log = lambda s: print(printable(s, True), flush=True)        # noqa: E731
        report = publish(reproduce([n], args.out, workers=args.workers, force=True, log=log,
                                   study=study), log=log)
    except KeyboardInterrupt:
        interrupted(args.command, args.out, "the demo starts again from the beginning "
                    f"(`flexmbs reproduce --table {n}` keeps finished jobs)")
        return 130
    print_report(report)
    print()
    u = f" {unit}" if unit else ""
    for r in report.rows.get(n, []):
        paper = (f"paper {r.paper['mass']:.3f} kg, p = {_design_text(r.paper['p'])}{u}"
                 if r.paper.get("mass") is not None and r.paper.get("p") else "paper: -")
        print(f"Table {n}, {r.method} coupled optimum: flexmbs {r.mass_kg:.4f} kg, "
              f"p = {_design_text(r.design_mm)}{u}; {paper}")
    return 1 if report.failures else 0
