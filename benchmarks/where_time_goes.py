"""Where the time of a flexmbs simulation goes, against a lower bound.

For the robot of docs/paper-cases.md (p = 50 mm, h = 5e-4 s, 0.65 s = 1300 steps, static start) with
2, 8, 32, 128 quadratic elements per arm, in four configurations (dense LAPACK LU or KLU, full
Newton or reuse_jacobian=True):

1. **Python against Fortran.** flexmbs.analysis.simulate is timed as a whole and its call of
   the compiled run separately (`flexmbs.core.simulate_arrays`, wrapped by a timer for the duration of
   the benchmark; nothing in flexmbs is changed). Python set-up = total - core: argument
   checks, compiled arrays, tabulating the drive laws on the grid, building the Result.
2. **Work counters** from Result.stats: Newton iterations (= linear solves), factorizations,
   residual evaluations, per step.
3. **Lower bound: the linear algebra alone**, with the very libraries flexmbs links (found in
   the process's memory map and called through ctypes), on the model's real iteration matrix
   (flexmbs.analysis.simulate.system_matrices at the initial configuration, with the generalized-alpha
   mass coefficient of h): dense `factorizations x dgetrf + iterations x dgetrs`; KLU
   `factorizations x klu_refactor + iterations x klu_solve` (the symbolic analysis is done once
   and not counted). No implementation of the same Newton iteration can go below it; the
   ratio total / bound says how much is spent elsewhere (assembly, copies, Python).
   scipy.linalg.lu_factor / lu_solve (scipy's own OpenBLAS) is shown beside it.
4. **Profile of the core by function** (if `perf` works on the machine): the samples of the
   timed loop only (perf starts disabled and is enabled by the child process after its
   imports and a warm-up run), grouped into element forces (beam2d), assembly / constraints /
   laws, integrator, solver wrapper (copies, checks), LAPACK/OpenBLAS, KLU, libm, libc
   (malloc/free/memset), Python/numpy; multiplied by the measured time per step.
"""
from __future__ import annotations

import contextlib
import ctypes
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from common import format_table, pyplot, robot_flexmbs
from flexmbs.analysis.settings import SimulationSettings

H = 5e-4
T_END = 0.65
NEL_FULL = [2, 8, 32, 128]
NEL_QUICK = [2, 8]
DENSE_MAX_N = 400       # dense runs up to this many unknowns (32 el/arm: 396; 128: 1550 would take ~15 min)
CONFIGS = [("dense", False), ("dense", True), ("klu", False), ("klu", True)]


# ----------------------------------------------------------------------------- core timer
class _CoreTimer:
    """Stands in for flexmbs.analysis.simulate's `simulate_arrays` (the compiled run,
    flexmbs.core): times each call."""

    def __init__(self, run):
        self._run = run
        self.calls = []          # (wall, cpu) of each compiled simulate call

    def __call__(self, *args, **kw):
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            return self._run(*args, **kw)
        finally:
            self.calls.append((time.perf_counter() - w0, time.process_time() - c0))


@contextlib.contextmanager
def core_timer():
    """Wrap flexmbs.analysis.simulate's reference to the compiled run for the duration of a
    block."""
    mod = sys.modules["flexmbs.analysis.simulate"]
    timer = _CoreTimer(mod.simulate_arrays)
    mod.simulate_arrays = timer
    try:
        yield timer
    finally:
        mod.simulate_arrays = timer._run


def measure(model, tip, solver, reuse, repeats=5, budget=3.0, h=H, t_end=T_END):
    """Total and core CPU time of flexmbs.simulate (min over repeats), Python = total - core."""
    import flexmbs as fx
    model.compile()
    model.pattern(solver)
    totals, cores, pys = [], [], []
    res = None
    spent = 0.0
    with core_timer() as ct:
        for _ in range(repeats):
            n0 = len(ct.calls)
            c0, w0 = time.process_time(), time.perf_counter()
            res = fx.simulate(model, t_end, h,
                              settings=SimulationSettings(start="static", store=[tip],
                                                          solver=solver,
                                                          newton="reuse" if reuse else "full"))
            cpu = time.process_time() - c0
            spent += time.perf_counter() - w0
            core = sum(c for _, c in ct.calls[n0:])
            totals.append(cpu)
            cores.append(core)
            pys.append(cpu - core)
            if spent > budget:
                break
    return dict(total=min(totals), core=min(cores), python=float(np.median(pys)), runs=len(totals),
                stats=res.stats)


# ----------------------------------------------------------------------------- lower bound
def _loaded_library(fragment):
    """Path of a shared library mapped into this process whose name contains `fragment`."""
    import flexmbs._core  # noqa: F401  (maps the libraries flexmbs links)
    with open("/proc/self/maps") as f:
        for line in f:
            path = line.split()[-1] if len(line.split()) >= 6 else ""
            if fragment in os.path.basename(path):
                return path
    return None


def iteration_matrix(model, h=H, rho_inf=0.5):
    """Dense iteration matrix of eq. (7) at the reference configuration, as flexmbs scales it."""
    from flexmbs.analysis.simulate import system_matrices
    am = (2 * rho_inf - 1) / (rho_inf + 1)
    af = rho_inf / (rho_inf + 1)
    gamma = 0.5 - am + af
    beta = 0.25 * (gamma + 0.5) ** 2
    betap = (1 - am) / (beta * h * h * (1 - af))
    q = model.reference_coordinates()
    _, s0 = system_matrices(model, q, cm=betap)
    nd = model.compile().ndof
    k = float(np.mean(np.abs(np.diag(s0)[:nd])))
    _, s = system_matrices(model, q, cm=betap, kscale=k, penalty=k)
    return s


def _best_time(fn, n, repeats=9):
    """Smallest CPU time per call of fn() over `repeats` batches of n calls."""
    best = float("inf")
    for _ in range(repeats):
        c0 = time.process_time()
        for _ in range(n):
            fn()
        best = min(best, (time.process_time() - c0) / n)
    return best


def dense_costs(a):
    """CPU seconds of one dgetrf and one dgetrs (nrhs = 1) of `a` with flexmbs's LAPACK, and
    the same with scipy.linalg.lu_factor / lu_solve."""
    import scipy.linalg as sla
    n = a.shape[0]
    reps = max(3, min(2000, int(2e7 / n ** 2.5)))
    out = {}
    path = _loaded_library("liblapack") or _loaded_library("libopenblas")
    if path:
        lib = ctypes.CDLL(path)
        c_int = ctypes.c_int
        nn, info = c_int(n), c_int(0)
        work = np.asfortranarray(a.copy())
        src = np.asfortranarray(a)
        ipiv = np.zeros(n, np.int32)
        b = np.ones(n)
        pa = work.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
        pp = ipiv.ctypes.data_as(ctypes.POINTER(c_int))
        pb = b.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
        one, trans = c_int(1), ctypes.c_char_p(b"N")

        def fac():
            np.copyto(work, src)
            lib.dgetrf_(ctypes.byref(nn), ctypes.byref(nn), pa, ctypes.byref(nn), pp, ctypes.byref(info))

        def copy_only():
            np.copyto(work, src)

        def sol():
            lib.dgetrs_(trans, ctypes.byref(nn), ctypes.byref(one), pa, ctypes.byref(nn), pp, pb,
                        ctypes.byref(nn), ctypes.byref(info), ctypes.c_size_t(1))
        fac()
        out["factor"] = max(_best_time(fac, reps) - _best_time(copy_only, reps), 0.0)
        out["solve"] = _best_time(sol, reps * 4)
        out["library"] = os.path.basename(path)
    lu = sla.lu_factor(a)
    rhs = np.ones(n)
    out["scipy_factor"] = _best_time(lambda: sla.lu_factor(a, check_finite=False), reps)
    out["scipy_solve"] = _best_time(lambda: sla.lu_solve(lu, rhs, check_finite=False), reps * 4)
    return out


def klu_costs(model, a):
    """CPU seconds of one klu_refactor and one klu_solve on the model's KLU pattern with the
    values of the dense matrix `a` (libklu of flexmbs, through ctypes)."""
    path = _loaded_library("libklu")
    if not path:
        return {}
    lib = ctypes.CDLL(path)
    pat = model.pattern("klu")
    ap = np.ascontiguousarray(pat["ap"], np.int32)
    ai = np.ascontiguousarray(pat["ai"], np.int32)
    n = ap.size - 1
    cols = np.repeat(np.arange(n), np.diff(ap))
    ax = np.ascontiguousarray(a[ai, cols], float)
    common = ctypes.create_string_buffer(8192)          # klu_common (< 1 kB)
    lib.klu_defaults(common)
    lib.klu_analyze.restype = ctypes.c_void_p
    lib.klu_factor.restype = ctypes.c_void_p
    P = ctypes.c_void_p
    pap, pai, pax = (x.ctypes.data_as(P) for x in (ap, ai, ax))
    sym = lib.klu_analyze(ctypes.c_int(n), pap, pai, common)
    num = lib.klu_factor(pap, pai, pax, P(sym), common)
    if not sym or not num:
        return {}
    b = np.ones(n)
    pb = b.ctypes.data_as(P)
    reps = max(5, min(5000, int(3e6 / max(ax.size, 1))))

    def refac():
        lib.klu_refactor(pap, pai, pax, P(sym), P(num), common)

    def sol():
        lib.klu_solve(P(sym), P(num), ctypes.c_int(n), ctypes.c_int(1), pb, common)
    out = dict(factor=_best_time(refac, reps), solve=_best_time(sol, reps * 4),
               library=os.path.basename(path), nnz=int(ax.size))
    lib.klu_free_numeric(ctypes.byref(P(num)), common)
    lib.klu_free_symbolic(ctypes.byref(P(sym)), common)
    return out


# ----------------------------------------------------------------------------- perf profile
CATEGORIES = [
    ("element forces (beam2d)", ("__beam2d_MOD",)),
    ("assembly/constraints/laws", ("__assembly_MOD", "__constraints_MOD", "__model_data_MOD")),
    ("integrator (generalized_alpha)", ("__generalized_alpha_MOD",)),
    ("solver wrapper (copies, checks)", ("__linear_solver_MOD", "fx_klu")),
]
DSO_CATEGORIES = [
    ("dense LU (LAPACK/OpenBLAS)", ("openblas", "lapack", "blas")),
    ("KLU (SuiteSparse)", ("klu", "amd", "btf", "colamd", "suitesparse")),
    ("libm (sin, cos, ...)", ("libm.",)),
    ("libc (malloc, free, memset)", ("libc.",)),
    ("Python / numpy", ("python", "_multiarray", "numpy", "libgfortran")),
]

_CHILD = r'''
import json, os, sys, time
cfg = json.loads(os.environ["FX_PERF_CFG"])
sys.path.insert(0, cfg["bench_dir"])
import flexmbs as fx
from common import robot_flexmbs
m, a1, a2 = robot_flexmbs(cfg["nel"])
run = lambda: fx.simulate(m, cfg["t_end"], cfg["h"],
                          fx.SimulationSettings(start="static", store=[a2.last],
                                                solver=cfg["solver"], newton=cfg["newton"]))
run()
ctl = open(cfg["ctl"], "w"); ack = open(cfg["ack"], "r")
ctl.write("enable\n"); ctl.flush(); ack.readline()
t0 = time.perf_counter(); k = 0
while time.perf_counter() - t0 < cfg["seconds"] or k < 2:
    run(); k += 1
ctl.write("disable\n"); ctl.flush(); ack.readline()
print(k)
'''


def perf_available():
    """True if `perf record` can sample this user's processes."""
    if shutil.which("perf") is None:
        return False
    try:
        with open("/proc/sys/kernel/perf_event_paranoid") as f:
            return int(f.read().strip()) <= 2
    except (OSError, ValueError):
        return False


def perf_profile(nel, solver, reuse, seconds=3.0, h=H, t_end=T_END, newton=None, python=None):
    """Share of the CPU samples of the timed simulate loop in each category (percent).
    newton: simulate's `newton` (default 'reuse' or 'full' after `reuse`); python: the
    interpreter to run (another checkout's venv: its flexmbs, these benchmark helpers)."""
    bench_dir = os.path.dirname(os.path.abspath(__file__))
    with tempfile.TemporaryDirectory() as tmp:
        ctl, ack = os.path.join(tmp, "ctl"), os.path.join(tmp, "ack")
        os.mkfifo(ctl)
        os.mkfifo(ack)
        data = os.path.join(tmp, "perf.data")
        script = os.path.join(tmp, "child.py")
        with open(script, "w") as f:
            f.write(_CHILD)
        env = dict(os.environ, FX_PERF_CFG=json.dumps(dict(
            bench_dir=bench_dir, nel=nel, solver=solver, seconds=seconds, h=h, t_end=t_end,
            newton=newton or ("reuse" if reuse else "full"), ctl=ctl, ack=ack)))
        cmd = ["perf", "record", "-q", "-F", "4000", "-D", "-1", f"--control=fifo:{ctl},{ack}",
               "-o", data, python or sys.executable, script]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        if proc.returncode != 0 or not os.path.exists(data):
            return None
        rep = subprocess.run(["perf", "report", "-i", data, "--no-children", "--sort", "dso,sym",
                              "--stdio", "-q", "--percent-limit", "0"],
                             capture_output=True, text=True, timeout=600)
    shares = {name: 0.0 for name, _ in CATEGORIES + DSO_CATEGORIES}
    shares["other"] = 0.0
    for line in rep.stdout.splitlines():
        parts = line.split()
        if len(parts) < 3 or not parts[0].endswith("%"):
            continue
        try:
            pct = float(parts[0].rstrip("%"))
        except ValueError:
            continue
        dso = parts[1]
        sym = " ".join(parts[2:])
        name = next((n for n, keys in CATEGORIES if any(k in sym for k in keys)), None)
        if name is None:
            name = next((n for n, keys in DSO_CATEGORIES if any(k in dso for k in keys)), "other")
        shares[name] += pct
    return shares


# ----------------------------------------------------------------------------- main
def run(quick=False, outdir="benchmarks/results", log=print):
    """Run the breakdown; prints tables, writes where_time_goes.json and a bar plot."""
    nel_list = NEL_QUICK if quick else NEL_FULL
    repeats, budget = (2, 1.0) if quick else (5, 3.0)
    steps = int(round(T_END / H))
    rows, rows_lb, results = [], [], []
    for nel in nel_list:
        model, _, a2 = robot_flexmbs(nel)
        n = model.compile().n
        a = iteration_matrix(model)
        dense = dense_costs(a) if n <= 2000 else {}
        klu = klu_costs(model, a)
        rows_lb.append([nel, n, dense.get("factor", np.nan) * 1e6, dense.get("solve", np.nan) * 1e6,
                        dense.get("scipy_factor", np.nan) * 1e6, dense.get("scipy_solve", np.nan) * 1e6,
                        klu.get("factor", np.nan) * 1e6, klu.get("solve", np.nan) * 1e6, klu.get("nnz")])
        for solver, reuse in CONFIGS:
            if solver == "dense" and n > DENSE_MAX_N:
                continue
            r = measure(model, a2.last, solver, reuse, repeats, budget)
            st = r["stats"]
            lib = dense if solver == "dense" else klu
            nf, ni = st["factorizations"], st["newton_iterations"] + st["static_iterations"]
            bound = nf * lib.get("factor", np.nan) + ni * lib.get("solve", np.nan)
            res = dict(elements=nel, unknowns=n, solver=solver, reuse=reuse, steps=steps,
                       total=r["total"], core=r["core"], python=r["python"], runs=r["runs"],
                       iterations=st["newton_iterations"], factorizations=nf,
                       residuals=st["residual_evaluations"], bound=bound)
            results.append(res)
            rows.append([nel, n, f"{solver}{' reuse' if reuse else ''}", r["total"] / steps * 1e6,
                         r["core"] / steps * 1e6, r["python"] * 1e3, r["python"] / r["total"] * 100,
                         st["newton_iterations"] / steps, nf / steps, st["residual_evaluations"] / steps,
                         bound / steps * 1e6, r["total"] / bound if bound > 0 else None])
            log(f"  {nel} el/arm {solver} reuse={reuse}: {r['total'] * 1e3:.1f} ms")
    log(format_table(["el/arm", "unknowns", "solver", "total us/step", "core us/step",
                      "Python ms/call", "Python %", "iter/step", "fact/step", "resid/step",
                      "LA bound us/step", "total/bound"], rows,
                     title="\nflexmbs.simulate on the robot, h = 5e-4 s, 1300 steps (CPU time, min of "
                           "repeats; Python = simulate - the compiled run)"))
    log(format_table(["el/arm", "unknowns", "dgetrf us", "dgetrs us", "scipy lu_factor us",
                      "scipy lu_solve us", "klu_refactor us", "klu_solve us", "KLU nnz"], rows_lb,
                     title="\nLinear algebra alone on the model's iteration matrix (same libraries as "
                           "flexmbs, through ctypes; scipy's own OpenBLAS beside)"))
    profiles = []
    if perf_available():
        picks = [(nel, s, r) for nel in nel_list for s, r in CONFIGS
                 if not (s == "dense" and nel > 32)]
        if quick:
            picks = [p for p in picks if p[0] == 2]
        prow = []
        names = [n for n, _ in CATEGORIES + DSO_CATEGORIES] + ["other"]
        for nel, solver, reuse in picks:
            sh = perf_profile(nel, solver, reuse, seconds=1.0 if quick else 3.0)
            if sh is None:
                log("  perf record failed: no profile")
                break
            tot = sum(sh.values()) or 1.0
            per_step = next(x["total"] for x in results if x["elements"] == nel
                            and x["solver"] == solver and x["reuse"] == reuse) / steps * 1e6
            profiles.append(dict(elements=nel, solver=solver, reuse=reuse, shares=sh,
                                 us_per_step=per_step))
            prow.append([nel, f"{solver}{' reuse' if reuse else ''}", per_step]
                        + [sh[k] / tot * 100 for k in names])
        if prow:
            short = ["beam2d", "assembly", "integrator", "wrapper", "LAPACK", "KLU", "libm", "libc",
                     "Python", "other"]
            log(format_table(["el/arm", "config", "us/step"] + [f"{s} %" for s in short], prow,
                             title="\nperf profile of the timed loop (% of samples): " + "; ".join(
                                 f"{s} = {n}" for s, n in zip(short, names))))
    else:
        log("perf not available: no profile by function")
    os.makedirs(outdir, exist_ok=True)
    with open(os.path.join(outdir, "where_time_goes.json"), "w") as f:
        json.dump(dict(runs=results, linear_algebra=rows_lb, profiles=profiles), f, indent=1,
                  default=float)
    _plot(results, profiles, outdir, log)
    return dict(runs=results, profiles=profiles)


def _plot(results, profiles, outdir, log):
    plt = pyplot()
    if plt is None or not profiles:
        return
    names = [n for n, _ in CATEGORIES + DSO_CATEGORIES] + ["other"]
    fig, ax = plt.subplots(figsize=(12, 0.45 * len(profiles) + 1.8))
    labels = [f"{p['elements']} el/arm {p['solver']}{' reuse' if p['reuse'] else ''} "
              f"({p['us_per_step']:.0f} us/step)" for p in profiles]
    left = np.zeros(len(profiles))
    cmap = plt.get_cmap("tab10")
    for i, name in enumerate(names):
        vals = np.array([p["shares"][name] / (sum(p["shares"].values()) or 1) * 100 for p in profiles])
        ax.barh(labels, vals, left=left, color=cmap(i % 10), label=name)
        left += vals
    ax.set_xlim(0, 100)
    ax.set_xlabel("share of the CPU samples of the timed loop (%)")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    ax.set_title("Where the time goes: robot, h = 5e-4 s, 1300 steps")
    fig.tight_layout()
    path = os.path.join(outdir, "where_time_goes.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    log(f"wrote {path}")
