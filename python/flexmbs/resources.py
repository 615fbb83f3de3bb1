"""Memory a simulation needs, estimated before it runs, and the memory available.

`estimate_memory` adds up what a run holds at its peak: the stored outputs (q, qd, qdd of the
stored coordinates and the constraint forces mu at every time step, the design derivatives
dq/dp), the time grid and the tabulated laws, the model's arrays in Python and in the core, the
iteration matrix (n^2 values and the n x n LU factors with solver="dense"; the sparse values, the
KLU factors and the pattern with solver="klu"), and the state vectors. `check_memory` compares
it with `available_memory` (or an explicit limit) and raises ResourceError with the estimate and
what to change. The estimate is meant to be within a factor 2 of the real peak: it decides
whether a run can fit, not how much it costs to the byte.

The limit: ``SimulationSettings(memory_limit=...)`` (a case: ``[solver] memory_limit``) in
bytes; None (default) reads the environment variable FLEXMBS_MEMORY_LIMIT (bytes, suffixes
k, M, G, T allowed, e.g. "8G"; "none" or "inf" disables the check), and without it the memory available now (MemAvailable of /proc/meminfo,
else sysconf, bounded by the process's address-space limit, RLIMIT_AS). A limit that a case
file set is a `CaseLimit` (a float naming its key), so that the messages name the key to change
(`limit_hint`).
"""
from __future__ import annotations

import math
import os
import resource
import threading
from dataclasses import dataclass, field

import numpy as np

from flexmbs.errors import ModelError, ResourceError

#: Values of one temporary array of the validity checks (flexmbs.analysis.validity): they run over the
#: stored history in chunks of time points so that their work memory stays bounded whatever the
#: run's length.
CHUNK_VALUES = 250_000
#: Bytes of work memory of the checks at most (a few temporaries of CHUNK_VALUES doubles).
CHECK_WORK_BYTES = 6 * 8 * CHUNK_VALUES

__all__ = ["MAX_STEPS", "time_steps", "MemoryEstimate", "estimate_memory", "available_memory",
           "memory_limit", "check_memory", "limit_source", "limit_hint", "CaseLimit",
           "format_bytes", "format_seconds", "stack_limit", "thread_stack", "DENSE_MAX_ORDER",
           "STACK_BYTES_PER_UNKNOWN"]

#: Largest order of a dense system: the core indexes the n x n values with 32-bit integers.
DENSE_MAX_ORDER = 46340

#: Bytes of stack per unknown: the core's work vectors of one Newton iteration (residual,
#: increment, accelerations, forces; about 12 vectors of n doubles) are automatic arrays on the
#: stack (-fstack-arrays). Above the calling thread's stack (8 MB: about 87 000 unknowns) the
#: core runs in a helper thread with a stack of this size (see flexmbs.core.run_interruptible).
STACK_BYTES_PER_UNKNOWN = 12 * 8

_SUFFIX = {"k": 1e3, "m": 1e6, "g": 1e9, "t": 1e12}


def format_bytes(b):
    """'12.8 GB', '640 MB', '3.2 kB' (decimal units)."""
    b = float(b)
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(b) >= scale:
            return f"{b / scale:.3g} {unit}"
    return f"{b:.0f} B"


def _proc_status_kb(key):
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def available_memory():
    """Bytes this process can still use: MemAvailable (or free pages from sysconf), bounded
    by the address-space limit RLIMIT_AS minus the current virtual size. inf if unknown."""
    avail = math.inf
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if not math.isfinite(avail):
        try:
            avail = float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        vm = _proc_status_kb("VmSize") or 0.0
        avail = min(avail, max(float(soft) - vm, 0.0))
    return avail


def memory_limit(limit=None):
    """The limit a run is checked against (bytes; inf: no check).

    limit: a number of bytes, None (FLEXMBS_MEMORY_LIMIT, else `available_memory()`), or
    math.inf / False to disable the check.
    """
    if limit is None:
        env = os.environ.get("FLEXMBS_MEMORY_LIMIT", "").strip()
        if not env:
            return available_memory()
        if env.lower() in ("none", "inf", "off"):
            return math.inf
        text, scale = env, 1.0
        if text[-1].lower() in _SUFFIX:
            text, scale = text[:-1], _SUFFIX[text[-1].lower()]
        elif text[-1].lower() == "b" and len(text) > 1 and text[-2].lower() in _SUFFIX:
            text, scale = text[:-2], _SUFFIX[text[-2].lower()]
        try:
            value = float(text) * scale
        except ValueError:
            value = -1.0
        if not (value > 0):
            raise ModelError(f"environment variable FLEXMBS_MEMORY_LIMIT must be a positive number "
                             f"of bytes (suffix k, M, G or T allowed, e.g. 8G) or 'none', "
                             f"got {env!r}")
        return value
    if limit is False:
        return math.inf
    if isinstance(limit, bool) or not isinstance(limit, (int, float)) or math.isnan(limit) \
            or not limit > 0:
        raise ModelError(f"memory_limit must be a positive number of bytes, None (the memory "
                         f"available) or math.inf (no check), got {limit!r}")
    return float(limit)


@dataclass
class MemoryEstimate:
    """Bytes a run needs at its peak, by part (see `estimate_memory`)."""
    parts: dict = field(default_factory=dict)
    n: int = 0
    nt: int = 0
    solver: str = "klu"
    stack: float = 0.0
    seconds: float = 0.0      #: rough run time (see `estimate_memory`)

    @property
    def total(self):
        return float(sum(self.parts.values()))

    def largest(self, k=3):
        """The k largest parts as 'name size' strings."""
        items = sorted(self.parts.items(), key=lambda kv: -kv[1])[:k]
        return ", ".join(f"{name} {format_bytes(v)}" for name, v in items if v > 0)


def estimate_memory(*, n, ndof, nc, nel, nt, nout, solver, nlaw=0, nv=0, nsens=0, dmu=False):
    """Peak bytes of a simulation of n = ndof + nc unknowns, nel elements, on nt grid points,
    storing nout coordinates (and nsens x nv design derivatives; with dmu, the nc x nv
    derivatives of the constraint forces)."""
    f8 = 8.0
    nca = max(nc, 1)
    nela = max(nel, 1)
    p = {}
    # outputs, allocated by the wrapper in Fortran order and returned as views (no copies)
    p["stored q, qd, qdd"] = 3 * f8 * nout * nt
    p["constraint forces mu"] = f8 * nca * nt
    if nv:
        p["design derivatives dq/dp"] = f8 * nsens * nv * nt + f8 * 5 * nela * nv * 2
        if dmu:
            p["design derivatives dmu/dp"] = f8 * nca * nv * nt
    # time grid (and its transient) and the tabulated laws (Python table + core copy)
    p["time grid and laws"] = 2 * f8 * nt + 4 * f8 * nlaw * nt
    # model arrays: compiled arrays in Python (~120 B/element), value maps (81 int32 per element
    # in Python and in the core), element mass matrices and strains in the core (3 x 81 + 6 doubles)
    p["model arrays"] = nela * (120 + 2 * 4 * 81 + f8 * (3 * 81 + 6)) + nca * (2 * 4 * 35 + 100) \
        + ndof * 8 * 8
    if solver == "dense":
        # values n^2 (core) and LU factors n^2 (core)
        p["dense matrix and LU factors"] = 2 * f8 * n * n + 4.0 * n
    else:
        # upper bound of the stored values (a row: 2 x 5 coupling and 5 x 5 Hessian entries)
        nnz = 81 * nela + ndof + 35 * nca
        # pattern build in Python (int64 row/col/key arrays and sorts, transient), CSC pattern,
        # values, and the KLU factors (fill of a banded beam matrix: a few times nnz)
        p["sparse matrix, pattern and KLU factors"] = nnz * (6 * 8 + 4 + f8) + 4 * nnz * (f8 + 4)
    # the validity checks of the result (flexmbs.analysis.validity), chunked over the time points
    p["validity checks"] = min(float(CHECK_WORK_BYTES), 6 * f8 * nt * max(ndof, nout, nca))
    # state vectors (two states, work vectors) and sensitivity work arrays
    p["state and work vectors"] = f8 * n * (20 + 10 * nv) + STACK_BYTES_PER_UNKNOWN * n
    # rough time: 2 Newton iterations per step; KLU about 0.8 us per unknown and iteration
    # (measured 0.3-1 us from 66 to 60 000 unknowns, 35-90 us per step on the 36-unknown robot),
    # dense LU 2/3 n^3 flops at ~5 GFlop/s
    per_iteration = 15e-6 + 0.8e-6 * n + (n ** 3 / 7.5e9 if solver == "dense" else 0.0)
    seconds = 2.0 * max(nt - 1, 1) * per_iteration * (1 + nv / 10)
    return MemoryEstimate(parts=p, n=n, nt=nt, solver=solver, stack=STACK_BYTES_PER_UNKNOWN * n,
                          seconds=seconds)


def format_seconds(s):
    """'42 s', '3.5 min', '2.1 h', '4.2 days' (rough)."""
    for unit, scale in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if s >= 2 * scale:
            return f"{s / scale:.2g} {unit}"
    return f"{s:.2g} s"


def stack_limit():
    """Bytes of stack of the calling thread (inf if unlimited)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_STACK)
    main = threading.current_thread() is threading.main_thread()
    if main:
        return math.inf if soft == resource.RLIM_INFINITY else float(soft)
    return thread_stack()


def thread_stack():
    """Bytes of stack a new thread gets (threading.stack_size, else glibc's default)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_STACK)
    size = threading.stack_size()
    if size:
        return float(size)
    # glibc: new threads get RLIMIT_STACK (2 MiB when unlimited)
    return 2.0 * 2**20 if soft == resource.RLIM_INFINITY else float(soft)


_GRID_PARTS = ("stored q, qd, qdd", "constraint forces mu", "time grid and laws",
               "design derivatives dq/dp")


class CaseLimit(float):
    """A memory limit (bytes) that a case file set: a float that also names its key
    (`setting`, e.g. '[solver] memory_limit') for the messages of `limit_hint`."""

    def __new__(cls, value, setting="[solver] memory_limit"):
        self = super().__new__(cls, value)
        self.setting = setting
        return self

    def __reduce__(self):
        return (CaseLimit, (float(self), self.setting))


def limit_hint(limit=None, setting=None):
    """What sets the limit, for the end of a message: the case key of a CaseLimit, the
    SimulationSettings field for another explicit limit, FLEXMBS_MEMORY_LIMIT when the
    environment variable set it, and when the limit is the memory available, `setting` (what
    the caller's user sets, e.g. a case key; default the SimulationSettings field) or the
    environment variable."""
    if isinstance(limit, CaseLimit):
        return f"{limit.setting} (bytes) sets the limit"
    if limit is not None:
        return "SimulationSettings(memory_limit=bytes) sets the limit (math.inf: no check)"
    if os.environ.get("FLEXMBS_MEMORY_LIMIT", "").strip():
        return "FLEXMBS_MEMORY_LIMIT sets the limit ('none': no check)"
    if setting is not None:
        return f"{setting} (bytes) or FLEXMBS_MEMORY_LIMIT sets the limit"
    return ("SimulationSettings(memory_limit=bytes) or FLEXMBS_MEMORY_LIMIT sets the limit "
            "(math.inf / 'none': no check)")


def limit_source(limit=None):
    """'the memory limit' (explicit or FLEXMBS_MEMORY_LIMIT) or 'the memory available'."""
    if limit is not None or os.environ.get("FLEXMBS_MEMORY_LIMIT", "").strip():
        return "the memory limit"
    return "the memory available"


def check_memory(est: MemoryEstimate, limit=None, what="this run"):
    """Raise ResourceError if `est` does not fit in the limit (see `memory_limit`)."""
    if est.solver == "dense" and est.n > DENSE_MAX_ORDER:
        raise ResourceError(
            f"{what}: dense LU of {est.n} unknowns needs {est.n}^2 matrix entries, beyond the "
            f"core's 32-bit indexing (at most {DENSE_MAX_ORDER} unknowns) and "
            f"{format_bytes(est.parts['dense matrix and LU factors'])}: use solver='klu'",
            required=est.total, available=None)
    avail = memory_limit(limit)
    total = est.total
    if total <= avail:
        return
    hints = []
    parts = est.parts
    if est.solver == "dense" and parts.get("dense matrix and LU factors", 0) > 0.25 * total:
        hints.append("use solver='klu' (sparse: memory grows like n, not n^2)")
    if sum(v for k, v in parts.items() if k in _GRID_PARTS) > 0.25 * total:
        hints.append("store fewer outputs (store=[nodes or bodies]), use a coarser step h or a "
                     f"shorter t_end ({est.nt} time points)")
    if total - sum(v for k, v in parts.items() if k in _GRID_PARTS) > 0.25 * total or not hints:
        hints.append(f"use fewer elements ({est.n} unknowns)")
    src = limit_source(limit)
    raise ResourceError(
        f"{what} needs about {format_bytes(total)} ({est.largest()}; and roughly "
        f"{format_seconds(est.seconds)} of computing), more than {src} "
        f"({format_bytes(avail)}): " + "; or ".join(hints) + f". {limit_hint(limit)}",
        required=total, available=avail)


#: Most time steps the core counts (32-bit integers).
MAX_STEPS = 2**31 - 2


def time_steps(t_end, h, limit=None):
    """Number of steps of the grid t_j = j h up to t_end, checked without building the grid.

    Raises ModelError if t_end is not a whole number of steps, ResourceError if the grid is too
    long for the core (MAX_STEPS) or cannot fit: a run on it holds at least 40 bytes per point
    (the grid, its transient, and q, qd, qdd of one stored coordinate); `limit` is the
    memory limit as `memory_limit` takes it (None: the process's).
    """
    for name, v in (("h", h), ("t_end", t_end)):
        if not (isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool)
                and math.isfinite(v) and v > 0):
            raise ModelError(f"{name} must be a positive finite number, got {v!r}")
    ratio = t_end / h
    if not math.isfinite(ratio) or ratio > MAX_STEPS:
        raise ResourceError(f"t_end = {t_end} s with h = {h} s is {ratio:.3g} time steps, more than "
                            f"the core's {MAX_STEPS}: use a coarser step h or a shorter t_end",
                            required=40.0 * ratio, available=None)
    nsteps = int(round(ratio))
    if nsteps < 1 or abs(nsteps * h - t_end) > 1e-9 * max(1.0, t_end):
        raise ModelError(f"t_end = {t_end} s is not a whole number of steps h = {h} s "
                         f"(nearest: {nsteps * h:.10g} s)")
    need = 40.0 * (nsteps + 1)
    avail = memory_limit(limit)
    if need > avail:
        raise ResourceError(f"t_end = {t_end} s with h = {h} s is {nsteps + 1} time points: the grid "
                            f"and one stored coordinate alone need {format_bytes(need)}, more than "
                            f"{limit_source(limit)} ({format_bytes(avail)}): use a coarser "
                            "step h or "
                            "a shorter t_end", required=need, available=avail)
    return nsteps
