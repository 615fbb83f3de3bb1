"""The layer over the compiled Fortran core (flexmbs._core): a model sent to the core once
(CoreModel, an opaque handle) and a run's arguments (the design, the law tables of its time
grid), the compiled runs with their outputs by name, and the residual and iteration matrix at
a state. `simulate` (simulate.py)
and the diagnoses of failed runs (validity.py) both build on it."""
from __future__ import annotations

import math
import threading
import weakref
from enum import IntEnum
from typing import NamedTuple

import numpy as np

import flexmbs._core as _core
from flexmbs.errors import Interrupted, ModelError, ResourceError
from flexmbs.model.arrays import Model
from flexmbs.resources import format_bytes, limit_source, stack_limit, thread_stack
from flexmbs.resources import memory_limit as _memory_limit

__all__ = ["Status", "SolverStatus", "KluAnalysis", "CoreModel", "core_model", "core_model_args",
           "klu_analysis", "system_matrices",
           "simulate_arrays", "simulate_adjoint_arrays", "run_interruptible", "cancel_flag",
           "beam_element", "RunOutput", "AdjointOutput"]

class Status(IntEnum):
    """What a compiled run returns: the GA_* codes of fortran/generalized_alpha.f90 (one table
    for both languages: tests/test_core_status.py reads the Fortran's and compares)."""
    OK = 0                    #: simulation completed
    NEWTON_FAILED = 1         #: Newton failed after all step cuts
    SINGULAR = 2              #: singular iteration matrix after all cuts
    STATIC_FAILED = 3         #: static equilibrium not found
    INITIAL_SINGULAR = 4      #: [M Phi_q^T; Phi_q 0] singular at t = 0
    INCONSISTENT_INITIAL = 5  #: q0 violates a constraint (rest start)
    NONFINITE = 6             #: NaN/Inf in a law, residual or solution
    BAD_INPUT = 7             #: settings out of range
    LINEAR_SOLVER = 8         #: linear solver set-up failed (info: its SolverStatus)
    NO_MEMORY = 9             #: an allocation failed (info: time, bytes, 0, what)
    TAPE_FULL = 10            #: the adjoint's tape has no room for the sub-steps of cut steps
    INTERRUPTED = 11          #: the run's cancel flag was set (info: time reached)


class SolverStatus(IntEnum):
    """The linear solver's codes, LS_* of fortran/linear_solver.f90 (KLU's analysis too)."""
    OK = 0            #: success
    SINGULAR = 1      #: zero or negligible pivot
    NO_MEMORY = 2     #: allocation failed
    INVALID = 3       #: bad pattern or call order
    NONFINITE = 4     #: NaN or Inf among the values


# The core's BLAS works on small systems thousands of times per run: one thread
# (no pool latency); parallelism belongs to batch runs over designs.
_core.blas_single_thread()


class KluAnalysis:
    """KLU's symbolic analysis (fill-reducing ordering and block structure) of a model's
    sparsity pattern, made on first use and then borrowed by every simulation, adjoint
    pass and sensitivity run of the model (the core's `klu_analysis` argument): the model,
    its pattern and this analysis are built once per case, a design changes only the
    values. Owned here and released with this object. KLU only reads an analysis after
    making it, so simulations in parallel threads share one; a copy (pickle, deepcopy: a
    Problem sent to a worker process) makes its own on first use. `analyses` counts the
    analyses made (1 after the first use)."""

    def __init__(self, ap, ai):
        self._ap = np.ascontiguousarray(ap, np.int32)
        self._ai = np.ascontiguousarray(ai, np.int32)
        self._handle = 0
        self._lock = threading.Lock()
        self.analyses = 0

    def handle(self) -> int:
        """The core's address of the analysis (made now on first use)."""
        if self._handle == 0:
            with self._lock:
                if self._handle == 0:
                    handle, status = _core.klu_analyze(self._ap, self._ai)
                    if status == SolverStatus.NO_MEMORY or (status == SolverStatus.OK and handle == 0):
                        raise ResourceError(f"out of memory in KLU's symbolic analysis of the "
                                            f"{self._ap.size - 1} x {self._ap.size - 1} "
                                            f"iteration matrix ({self._ai.size} nonzeros)")
                    if status != SolverStatus.OK:
                        raise ModelError(f"KLU rejected the sparsity pattern of the iteration "
                                         f"matrix ({self._ap.size - 1} unknowns, "
                                         f"{self._ai.size} nonzeros; status {int(status)})")
                    weakref.finalize(self, _core.klu_analysis_free, handle)
                    self.analyses += 1
                    self._handle = int(handle)
        return self._handle

    def __reduce__(self):
        return (KluAnalysis, (self._ap, self._ai))


def klu_analysis(model: Model, storage) -> int:
    """The `klu_analysis` argument of the core's runs of `model` with matrix storage
    `storage`: the address of the model's KluAnalysis for 'klu' (made on first use and
    kept with the model's pattern), 0 for 'dense'."""
    if storage != "klu":
        return 0
    pat = model.pattern("klu")
    if "analysis" not in pat:
        pat["analysis"] = KluAnalysis(pat["ap"], pat["ai"])
    return pat["analysis"].handle()


class CoreModel:
    """A model as the core holds it (fortran/flexmbs_api.f90 model_create): the arrays of a
    compiled model and one matrix storage's value positions that do not depend on the design
    or the time grid, sent once and built into the core's model (with the element mass
    matrices per unit rhoA and rhoI and the reference strains). Every run of the model
    (`simulate`, `simulate_adjoint`, `system_matrices`) passes its address with what changes
    per call: the element properties of the design and the law tables of the time grid. Made
    on first use, owned here and released with this object (as KluAnalysis); the core only
    reads it during a run (a run copies it into its own model with the design), so runs in
    parallel threads share one; a copy (pickle, deepcopy) makes its own on first use.
    `builds` counts the models built (1 after the first use)."""

    def __init__(self, arrays: dict):
        self._arrays = dict(arrays)
        self.nlaw = int(self._arrays["nlaw"])
        self._handle = 0
        self._release = None
        self._lock = threading.Lock()
        self.builds = 0

    @classmethod
    def of(cls, cm, pat, nlaw):
        """The CoreModel of a compiled model `cm` (Model.compile) with the pattern `pat`
        (Model.pattern) and nlaw time laws."""
        return cls(dict(
            ndof=cm.ndof, nc=cm.nc, nel=cm.nel, nload=cm.nload, nlaw=nlaw, nnz=pat["nnz"],
            qref=cm.qref, lumped=cm.lumped, gacc=cm.gacc, el_nen=cm.el_nen, el_dofs=cm.el_dofs,
            el_len=cm.el_len, el_eta=cm.el_eta, ld_dof=cm.ld_dof, ld_law=cm.ld_law,
            ld_amp=cm.ld_amp, c_kind=cm.c_kind, c_dofs=cm.c_dofs, c_coef=cm.c_coef, c_c0=cm.c_c0,
            c_law=cm.c_law, c_lawcoef=cm.c_lawcoef, map_el=pat["map_el"],
            map_diag=pat["map_diag"], map_cq=pat["map_cq"], map_qc=pat["map_qc"],
            map_qq=pat["map_qq"], nsd=cm.nsd, sd_dofs=cm.sd_dofs, sd_prop=cm.sd_prop,
            map_sd=pat["map_sd"]))

    def handle(self) -> int:
        """The core's address of the model (built now on first use)."""
        if self._handle == 0:
            with self._lock:
                if self._handle == 0:
                    handle, status, nbytes = _core.model_create(**self._arrays)
                    if status != 0 or handle == 0:
                        raise ResourceError(f"out of memory in the core: could not allocate the "
                                            f"model arrays ({self._arrays['nel']} elements, "
                                            f"{self._arrays['ndof'] + self._arrays['nc']} unknowns"
                                            f"; {format_bytes(nbytes) if nbytes > 0 else 'size unknown'})",
                                            required=float(nbytes) if nbytes > 0 else None)
                    self._release = weakref.finalize(self, _core.model_destroy, handle)
                    self.builds += 1
                    self._handle = int(handle)
        return self._handle

    def counts(self) -> dict:
        """The counts the core's model holds (fortran/flexmbs_api.f90 model_counts)."""
        names = ("ndof", "nc", "nel", "nload", "nlaw", "nnz", "nsd", "n")
        return dict(zip(names, (int(v) for v in _core.model_counts(self.handle()))))

    def __reduce__(self):
        return (CoreModel, (self._arrays,))


def core_model(model: Model, storage) -> CoreModel:
    """The CoreModel of `model` with matrix storage `storage` ('dense' or 'klu'), made on first
    use and kept with the model's pattern (a change of the model's structure makes a new one)."""
    pat = model.pattern(storage)
    nlaw = len(model.laws())
    key = ("core_model", nlaw)
    found = pat.get(key)
    if found is None:
        # setdefault: threads racing here keep one (a replaced one could be freed mid-run)
        found = pat.setdefault(key, CoreModel.of(model.compile(), pat, nlaw))
    return found


def core_model_args(model: Model, storage, t, props=None):
    """Keyword arguments of a run of `model` in the Fortran core (flexmbs_api.f90): its
    CoreModel (`model`: the compiled calls below pass its address and hold the object until
    the core returns, so the model cannot be freed under a run), its extents, the design and
    the law tables.

    storage: 'dense' or 'klu' (matrix layout); t: the time grid on which the
    laws are tabulated (uniform); props: (5, nel) element properties (default:
    the model's current sections).
    """
    cm = model.compile()
    if props is None:
        props = model.element_properties()
    props = np.asarray(props, float)
    if props.shape != (5, cm.el_dofs.shape[1]) or not np.all(np.isfinite(props)):
        raise ModelError(f"props must be a finite (5, {cm.el_dofs.shape[1]}) array of element "
                         f"properties [EA, kGA, EI, rhoA, rhoI], got shape {props.shape}")
    t = np.atleast_1d(np.asarray(t, float))
    if t.size < 2:
        t = np.array([0.0, 1.0])
    law_h = float(t[1] - t[0])
    laws = model.laws()
    if laws:
        # the laws do not depend on the design: tabulate once per model and time grid
        key = (tuple(id(law) for law in laws), t.size, float(t[0]), float(t[-1]))
        cache = model.__dict__.setdefault("_law_tables", {})
        if key not in cache:
            if len(cache) > 8:
                cache.clear()
            tab = [law.tabulate(t) for law in laws]
            cache[key] = (np.asfortranarray(np.array([v for v, _, _ in tab])),
                          np.asfortranarray(np.array([d for _, d, _ in tab])),
                          np.array([dd for _, _, dd in tab]))
        law_val, law_der, law_dd0 = cache[key]
    else:
        law_val = np.zeros((1, t.size), order="F")
        law_der = np.zeros((1, t.size), order="F")
        law_dd0 = np.zeros(1)
    return dict(model=core_model(model, storage), ndof=cm.ndof, nca=max(cm.nc, 1),
                el_prop=np.asfortranarray(props), law_h=law_h, law_val=law_val, law_der=law_der,
                law_dd0=law_dd0)


def system_matrices(model: Model, q, qdd=None, mu=None, t=0.0, *, cm=0.0, ck=1.0, kscale=0.0,
                    penalty=0.0, props=None, qd=None, cc=0.0):
    """Residual r (n,) of eq. (1) and dense iteration matrix S (n, n) of eq. (7) at a state.

    With the defaults (cm = 0, ck = 1, cc = 0, kscale = 0, penalty = 0, mu = 0, qd = 0) the
    leading ndof x ndof block of S is the tangent stiffness K_t(q) and r[:ndof] = f_int - f_ext.
    `qd` (default 0) are the velocities of the velocity-dependent forces (spring-dampers, the
    beams' Kelvin–Voigt damping) and `cc` the coefficient of their damping matrix C_t in S
    (gamma' in dynamics).
    The time laws are evaluated at t exactly.
    """
    c = model.compile()
    need, avail = 16.0 * c.n * c.n, _memory_limit(None)
    if need > avail or c.n > 46340:
        raise ResourceError(f"system_matrices returns the dense {c.n} x {c.n} iteration matrix: "
                            f"{format_bytes(need)}, more than {limit_source(None)} "
                            f"({format_bytes(avail)}) or beyond the core's 32-bit indexing "
                            "(46340 unknowns)", required=need, available=avail)
    q = np.asarray(q, float)
    qdd = np.zeros(c.ndof) if qdd is None else np.asarray(qdd, float)
    qd = np.zeros(c.ndof) if qd is None else np.asarray(qd, float)
    mu_arr = np.zeros(max(c.nc, 1))
    if mu is not None:
        mu_arr[:c.nc] = mu
    # the core tabulates laws on a grid from 0; t itself is a grid point
    grid = np.array([0.0, float(t)]) if t > 0 else np.array([0.0, 1e-6])
    margs = core_model_args(model, "dense", grid, props)
    owner, margs = _with_handle(margs)     # `owner` keeps the model alive through the call
    r, vals, _phimax, status = _core.system_matrices(**margs, nc=c.nc, nnz=c.n * c.n, q=q, qdd=qdd,
                                                     mu=mu_arr, t=float(t), cm=float(cm),
                                                     ck=float(ck), kscale=float(kscale),
                                                     pen=float(penalty), qd=qd, cc=float(cc))
    del owner
    if status == Status.NO_MEMORY:
        raise ResourceError(f"out of memory in the core: could not allocate the model arrays "
                            f"({c.nel} elements, {c.n} unknowns)")
    if status != 0:
        raise ModelError(f"system_matrices: the core rejected the model's arrays (status "
                         f"{int(status)}: extents of another model)")
    return r, vals.reshape(c.n, c.n, order="F")


# ----------------------------------------------------------------------------- compiled runs
class RunOutput(NamedTuple):
    """The outputs of the compiled generalized-alpha run (fortran/flexmbs_api.f90 `simulate`),
    by name; arrays in the core's layout (coordinates first, time last)."""
    q: np.ndarray            #: (nout, nsteps + 1) stored coordinates
    qd: np.ndarray           #: (nout, nsteps + 1) their velocities
    qdd: np.ndarray          #: (nout, nsteps + 1) their accelerations
    mu: np.ndarray           #: (max(nc, 1), nsteps + 1) multipliers
    stats: np.ndarray        #: (8,) counters (see the Fortran interface)
    status: int              #: a Status code
    info: np.ndarray         #: (4,) time, increment or residual, iterations, extra
    dq: np.ndarray           #: (nsens, nva, nsteps + 1) dq/dp
    dmu: np.ndarray          #: (ndmu, nva, nsteps + 1) dmu/dp
    tape_q: np.ndarray       #: (ndof, ntape) the adjoint's tape: coordinates of every sub-step
    tape_qd: np.ndarray      #: (ndof, ntape) velocities
    tape_qdd: np.ndarray     #: (ndof, ntape) accelerations
    tape_mu: np.ndarray      #: (max(nc, 1), ntape) multipliers
    tape_h: np.ndarray       #: (ntape,) step leading to a column
    tape_grid: np.ndarray    #: (nsteps + 1,) column of every grid point
    ntape_used: int          #: tape columns used
    checkpoints: np.ndarray  #: (nckr, nck) states at the checkpoints

    def tape(self, nc):
        """The columns of the tape the run used, as Result.tape: q, qd, qdd, mu (nc rows), h
        and grid."""
        n = int(self.ntape_used)
        return dict(q=self.tape_q[:, :n], qd=self.tape_qd[:, :n], qdd=self.tape_qdd[:, :n],
                    mu=self.tape_mu[:nc, :n], h=self.tape_h[:n], grid=np.asarray(self.tape_grid))


class AdjointOutput(NamedTuple):
    """The outputs of the compiled backward pass (fortran/flexmbs_api.f90 `simulate_adjoint`)."""
    grad: np.ndarray         #: (nv, nf) gradients through the core's dprop
    gprop: np.ndarray        #: (5, nela, nf) dG_f/d[EA, kGA, EI, rhoA, rhoI] per element
    status: int              #: a Status code
    info: np.ndarray         #: (4,) as RunOutput.info
    adj_out: np.ndarray      #: (ndof, nf, 4) the adjoint state at the segment's start


def _with_handle(kwargs):
    """(owner, kwargs with `model` as the core's address): the CoreModel given as `model` is
    returned as `owner`, which the caller holds until the compiled call returns (the address
    alone would not keep the model alive: a model edited meanwhile drops its CoreModel)."""
    owner = kwargs.get("model")
    if isinstance(owner, CoreModel):
        kwargs = dict(kwargs, model=owner.handle())
    return owner, kwargs


def cancel_flag():
    """A new cancel flag of one compiled run: a one-element C int array, 0; the run
    (`simulate_arrays`, `simulate_adjoint_arrays`: its `cancel`) reads it by reference once
    per step and ends with Interrupted when another thread sets it to 1."""
    return np.zeros(1, np.intc)


def _interrupted(out, what):
    if out.status == Status.INTERRUPTED:
        raise Interrupted(f"{what} interrupted at t = {out.info[0]:.6g} s", time=float(out.info[0]))
    return out


def simulate_arrays(*, cancel=None, **kwargs) -> RunOutput:
    """The compiled generalized-alpha run (fortran/flexmbs_api.f90 `simulate`) of a model's
    handle with its design and law tables (`core_model_args`) and the run's settings; its
    outputs by name. `cancel`: the run's cancel flag (`cancel_flag`; default: a flag of its
    own that nobody sets); Interrupted when it is set during the run."""
    owner, kwargs = _with_handle(kwargs)
    out = RunOutput(*_core.simulate(**kwargs, cancel=cancel_flag() if cancel is None else cancel))
    del owner
    return _interrupted(out, "simulation")


def simulate_adjoint_arrays(*, cancel=None, **kwargs) -> AdjointOutput:
    """The compiled forward run with the discrete adjoint's backward pass
    (fortran/flexmbs_api.f90 `simulate_adjoint`); its outputs by name. `cancel` as
    `simulate_arrays`'."""
    owner, kwargs = _with_handle(kwargs)
    out = AdjointOutput(*_core.simulate_adjoint(
        **kwargs, cancel=cancel_flag() if cancel is None else cancel))
    del owner
    return _interrupted(out, "adjoint backward pass")


#: How often (s) the main thread, waiting on a compiled run in its helper thread, wakes to run
#: Python's signal handlers (a signal delivered to the helper thread does not wake it).
WAIT_POLL_S = 0.05


def run_interruptible(fn, stack_bytes=0, **kwargs):
    """fn(**kwargs, cancel=flag): a compiled run (`simulate_arrays`, `simulate_adjoint_arrays`)
    with a cancel flag of its own (`cancel_flag`), that Ctrl-C ends within a step.

    Called from the main thread, the run goes to a helper thread (with a stack of at least
    stack_bytes + 16 MB when the default is smaller) while the main thread waits in short
    timed waits, so that its signal handlers run (a wait without timeout would last the whole
    run). A KeyboardInterrupt (Ctrl-C, or the command line's SIGTERM) or any other
    exception raised in the main thread while it waits sets the flag; the core returns at its
    next step, the helper thread ends, and the exception is raised again. Called from another
    thread (which receives no signals), the run goes to a helper thread only when the stack
    demands it; its flag is its own, so runs in parallel threads never stop each other."""
    flag = cancel_flag()
    main = threading.current_thread() is threading.main_thread()
    if not main and stack_bytes <= 0.5 * stack_limit():
        return fn(**kwargs, cancel=flag)
    big = stack_bytes > 0.5 * thread_stack()
    out = {}
    done = threading.Event()

    def run():
        try:
            out["value"] = fn(**kwargs, cancel=flag)
        except BaseException as exc:        # re-raised in the caller
            out["error"] = exc
        finally:
            done.set()

    # daemon: an interpreter ended by a second Ctrl-C does not wait for it
    th = threading.Thread(target=run, name="flexmbs-core", daemon=True)
    old = threading.stack_size()
    try:
        try:
            if big:
                threading.stack_size(int(math.ceil((stack_bytes + 16 * 2**20) / 65536) * 65536))
            th.start()
        finally:
            threading.stack_size(old)
        # an Event, not Thread.join: CPython 3.11's join, interrupted by a signal while the
        # thread runs, may mark the thread stopped (threading.py, _wait_for_tstate_lock)
        while not done.wait(WAIT_POLL_S):
            pass
    except BaseException:
        flag[0] = 1         # a run that starts now returns at its first step
        while th.is_alive() and not done.wait(WAIT_POLL_S):
            pass
        raise
    if "error" in out:
        raise out["error"]
    return out["value"]


def beam_element(length, stiffness, qref, q, eta, qd):
    """One geometrically exact beam element (fortran/beam2d.f90): (internal forces, tangent
    stiffness, damping matrix) at coordinates q and rates qd; for derivative checks."""
    return _core.beam_element(length, stiffness, qref, q, eta, qd)
