"""Design gradients by the discrete adjoint of the generalized-alpha scheme.

For functionals of the whole discrete solution,

    G_f = sum_j ( gq[j, :, f] . q_j + gmu[j, :, f] . mu_j ),

that is, the per-step partials of a response aggregated over time (KS, p-norm, max, final
value, a weighted sum), `adjoint_gradient` returns dG_f/dp for every design variable p with
one backward pass over the stored converged states (Fortran, fortran/adjoint.f90): one
factorization and one transposed solve of the step's iteration matrix per step, for all nf
functionals at once, whatever the number of design variables. The derivation is in
docs/adjoint.md; the result is the transpose of the direct differentiation that
`simulate(derivatives=...)` carries forward, so both agree to the Newton tolerance.

Checkpointing (docs/adjoint.md section 3b): `simulate_for_adjoint(..., checkpoints=K)` keeps
the full integration state at every K-th time point instead of the tape of every state;
`adjoint_gradient` then processes the run in segments of K steps from the last to the first,
re-running each forward from its checkpoint with the tape (about one more forward run in all)
and carrying the adjoint state from one segment to the previous one. Memory: the checkpoints
and one segment's tape (`checkpoint_memory`), ~sqrt(N) for N steps with K ~ sqrt(N)
(`checkpoint_interval`).

>>> import numpy as np
>>> from flexmbs.analysis.adjoint import adjoint_gradient, simulate_for_adjoint
>>> from flexmbs.analysis.settings import SimulationSettings
>>> from flexmbs.problem import Problem
>>> mech = Problem("robot_2dof").mechanism
>>> model = mech.set_design(mech.start)
>>> r = simulate_for_adjoint(model, 0.05, 5e-4, SimulationSettings(start="static"))  # the tape
>>> gq = np.zeros((r.t.size, model.ndof))
>>> gq[-1, 0] = 1.0                                           # G = q_0(t_end)
>>> adjoint_gradient(model, r, mech.element_property_derivatives(mech.start), gq).shape
(4, 1)
"""
from __future__ import annotations

import numpy as np

from flexmbs.analysis.simulate import (_arguments, _tape_bytes, checkpoint_bytes, checkpoint_rows,
                                       law_times, newton_mode, NEWTON_MODES, Result, simulate)
from flexmbs.core import (Status, core_model_args, klu_analysis, run_interruptible,
                          simulate_adjoint_arrays, simulate_arrays)
from flexmbs.errors import ModelError, ResourceError, SimulationError
from flexmbs.model.arrays import Model
from flexmbs.resources import STACK_BYTES_PER_UNKNOWN, format_bytes, limit_source
from flexmbs.resources import memory_limit as _memory_limit
from flexmbs.resources import time_steps

__all__ = ["adjoint_gradient", "simulate_for_adjoint", "adjoint_memory", "check_adjoint_memory",
           "checkpoint_memory", "checkpoint_interval"]

_SOLVERS = {"dense": 1, "klu": 2}


def adjoint_memory(ndof, nc, nt, nf, nel=0):
    """Bytes of a backward pass beyond its forward run: the per-step partials of nf
    functionals (ndof + nc per step and functional) and the per-element result (5 nel nf).
    The forward run's stored states (3 ndof + nc per step) are counted by `simulate`."""
    return 8.0 * (nt * nf * (ndof + max(nc, 1)) + 5 * max(nel, 1) * nf + 12 * ndof * nf)


def check_adjoint_memory(ndof, nc, nt, nf, nel=0, memory_limit=None):
    """ResourceError when a backward pass (`adjoint_memory`) does not fit in the memory limit
    (as `simulate`'s memory_limit)."""
    need = adjoint_memory(ndof, nc, nt, nf, nel)
    avail = _memory_limit(memory_limit)
    if need > avail:
        raise ResourceError(f"adjoint_gradient: the per-step partials of {nf} functionals over "
                            f"{nt} time points need {format_bytes(need)}, more than "
                            f"{limit_source(memory_limit)} ({format_bytes(avail)}): fewer "
                            "functionals, a coarser step or direct differentiation",
                            required=need, available=avail)


def checkpoint_memory(model, nsteps, every):
    """(checkpoints, one segment's tape) in bytes of a checkpointed adjoint over nsteps steps
    with a checkpoint every `every` time points:

        8 (nsteps // every + 1) (5 ndof + nc + 3)                  the checkpoints
        8 (K + 1 + max(8, K // 4)) (3 ndof + nc + 1.5),   K = min(every, nsteps)
                                                                  one segment's tape

    (a segment cutting more steps than its room is re-run once with room for every step cut
    max_cuts times, as `simulate`'s tape)."""
    every = int(every)
    return (checkpoint_bytes(model, nsteps, every),
            _tape_bytes(model, segment_columns(min(every, nsteps))))


def segment_columns(nseg):
    """Columns a segment's tape is first allocated with: its nseg + 1 time points and room for
    a quarter more sub-steps (at least 8); a segment cutting more is re-run once with room
    for every step cut max_cuts times."""
    return nseg + 1 + max(8, nseg // 4)


def checkpoint_interval(model, nsteps, available=None):
    """Time points between checkpoints: ceil(sqrt(nsteps)) (about the least memory,
    `checkpoint_memory`: both parts ~ sqrt(nsteps)) when `available` is None; else the largest
    interval (the fewest segments) whose checkpoints and segment tape fit in `available`
    bytes, or None when ceil(sqrt(nsteps)) does not."""
    k_sqrt = max(1, int(np.ceil(np.sqrt(nsteps))))
    if available is None:
        return k_sqrt
    if sum(checkpoint_memory(model, nsteps, k_sqrt)) > available:
        return None
    lo, hi = k_sqrt, max(k_sqrt, nsteps)       # the memory grows with K above sqrt(nsteps)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if sum(checkpoint_memory(model, nsteps, mid)) <= available:
            lo = mid
        else:
            hi = mid - 1
    return lo


def simulate_for_adjoint(model, t_end, h=5e-4, settings=None, *, checkpoints=None,
                         initial=None, steps=None, **deprecated):
    """`simulate` keeping the tape of every converged (sub-)step (tape=True) with the states
    converged as full Newton's (settings.polish set: 'auto''s states, 8e-12 m off, made the
    robot's KS gradient 2e-6 off): the states the backward pass needs.

    checkpoints : None, int or 'auto'
        None: the tape of every state. K (>= 1): only the full state at every K-th time
        point (simulate(checkpoints=K)); `adjoint_gradient` re-runs the segments between
        them with the tape (about one more forward run). 'auto': K = `checkpoint_interval`
        (ceil(sqrt(nsteps))).

    settings, initial, steps as `simulate`'s (no design derivatives, no tape=: the adjoint
    keeps every state and needs no forward derivatives)."""
    for key in ("tape", "polish", "design_derivatives", "sensitivity_dofs",
                "constraint_force_derivatives", "derivatives"):
        if key in deprecated:
            raise ModelError(f"simulate_for_adjoint: {key}= is not allowed (the adjoint keeps "
                             "every state, converges every step and needs no forward "
                             "derivatives)")
    settings, initial, _, reuse = _arguments("simulate_for_adjoint", settings, initial, None,
                                             deprecated)
    settings = settings.replace(polish=True)
    if reuse is not None:
        settings = settings.replace(newton=newton_mode(settings.newton, reuse))
    if isinstance(checkpoints, str):
        if checkpoints != "auto":
            raise ModelError(f"checkpoints must be None, 'auto' or an integer >= 1, got "
                             f"{checkpoints!r}")
        n = time_steps(t_end, h, np.inf) if steps is None else len(steps) - 1
        checkpoints = checkpoint_interval(model, n)
    return simulate(model, t_end, h, settings, initial=initial, tape=checkpoints is None,
                    checkpoints=checkpoints, steps=steps)


def _seed(name, value, nt, rows, nf=None):
    """(nt, rows, nf) float array from (nt, rows) or (nt, rows, nf), or a ModelError."""
    a = np.asarray(value, float) if not isinstance(value, (str, bytes)) else None
    if a is not None and a.ndim == 2:
        a = a[:, :, None]
    if a is None or a.ndim != 3 or a.shape[:2] != (nt, rows) or (nf is not None and a.shape[2] != nf):
        shape = None if a is None else a.shape
        want = f"({nt}, {rows}, nf)" if nf is None else f"({nt}, {rows}, {nf})"
        raise ModelError(f"{name} must have shape ({nt}, {rows}) or {want}, got {shape}")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} holds non-finite values")
    return a


def adjoint_gradient(model: Model, result: Result, design_derivatives, dG_dq, dG_dmu=None, *,
                     memory_limit=None, return_properties=False):
    """Design gradients of functionals of a simulation by the discrete adjoint.

    Parameters
    ----------
    model : Model
        The model simulated (same design).
    result : Result
        Its simulation with the tape of every (sub-)step (`simulate_for_adjoint`, or
        simulate(..., SimulationSettings(polish=True), tape=True)), or with checkpoints
        (simulate_for_adjoint(..., checkpoints=K)): then the backward pass runs over the
        segments between them from the last to the first, each re-run forward from its
        checkpoint with the tape first (one segment's tape in memory at a time).
    design_derivatives : array (5, nel, nv)
        d[EA, kGA, EI, rhoA, rhoI]/dp of every element (as `simulate`'s).
    dG_dq : array (nt, ndof) or (nt, ndof, nf)
        dG_f/dq_j: the partials of nf functionals with respect to the coordinates at every
        time point of result.t.
    dG_dmu : array (nt, nc) or (nt, nc, nf), optional
        dG_f/dmu_j with respect to the constraint forces (Result.mu).
    memory_limit : as `simulate`'s.
    return_properties : bool
        Also return dG_f/d[EA, kGA, EI, rhoA, rhoI]_e, (5, nel, nf).

    Returns
    -------
    (nv, nf) array dG_f/dp (nf = 1 for 2-D partials), and with return_properties the
    per-element array.

    Raises
    ------
    ModelError for inconsistent input (a run without its tape, or with modified Newton
    states not polished), SimulationError when a transposed system is singular,
    ResourceError when the partials do not fit in memory.
    """
    if not isinstance(model, Model):
        raise ModelError(f"adjoint_gradient expects a flexmbs Model, got {type(model).__name__}")
    if not isinstance(result, Result):
        raise ModelError(f"adjoint_gradient: result must be a simulate Result, got "
                         f"{type(result).__name__}")
    cm = model.compile()
    st = result.settings
    tape = result.tape
    ck = getattr(result, "checkpoints", None)
    if tape is not None and (tape["q"].shape[0] != cm.ndof):
        tape = None
    if ck is not None and ck["states"].shape[0] != checkpoint_rows(cm.ndof, cm.nc):
        ck = None
    if (tape is None and ck is None) or result.initial is None:
        raise ModelError("adjoint_gradient: result has no tape of its states: simulate with "
                         "simulate_for_adjoint (or simulate(..., SimulationSettings(polish=True), "
                         "tape=True))")
    if st.newton != "full" and not st.polish and result.dq is None:
        raise ModelError(f"adjoint_gradient: result was simulated with newton={st.newton!r} "
                         "without polish=True: its states are modified Newton's, not converged "
                         "enough for the adjoint (use simulate_for_adjoint, or polish=True)")
    nt = result.t.size
    stp = result.steps
    dprop = np.asarray(design_derivatives, float)
    if dprop.ndim != 3 or dprop.shape[:2] != (5, cm.nel) or not np.all(np.isfinite(dprop)):
        raise ModelError(f"design_derivatives must be a finite array of shape (5, {cm.nel}, nv), "
                         f"got shape {dprop.shape}")
    nv = dprop.shape[2]
    gq = _seed("dG_dq", dG_dq, nt, cm.ndof)
    nf = gq.shape[2]
    check_adjoint_memory(cm.ndof, cm.nc, nt, nf, cm.nel, memory_limit)
    nca = max(cm.nc, 1)
    gq_f = np.zeros((cm.ndof, nf, nt), order="F")
    gq_f[...] = np.transpose(gq, (1, 2, 0))
    gmu_f = np.zeros((nca, nf, nt), order="F")
    if dG_dmu is not None:
        gmu = _seed("dG_dmu", dG_dmu, nt, cm.nc, nf)
        gmu_f[:cm.nc] = np.transpose(gmu, (1, 2, 0))
    if stp is not None:
        # outputs interpolated from a non-uniform step grid (Result.steps): the seeds of
        # its points are the interpolation's transpose applied to those of the outputs
        wt = stp["matrix"].T.tocsr()
        nt = wt.shape[0]
        gq_f = np.asfortranarray(np.stack([(wt @ gq_f[:, f, :].T).T for f in range(nf)], 1))
        gmu_f = np.asfortranarray(np.stack([(wt @ gmu_f[:, f, :].T).T for f in range(nf)], 1))
    solver = st.solver
    pat = model.pattern(solver)
    law_t, _ = law_times(float(st.h), result.t.size - 1, _step_times(result))
    margs = core_model_args(model, solver, law_t, model.element_properties())
    nel = cm.el_dofs.shape[1]
    # the core accumulates dG/d[EA, kGA, EI, rhoA, rhoI] of every element (gprop); their
    # product with the design derivatives is taken here, not in the core: a copy of the
    # (5, nel, nv) derivatives, 84 MB at 2048 element-wise variables, is not made. The core
    # contracts only the properties that some variable moves: one column marks them
    dprop_f = np.zeros((5, nel, 1), order="F")
    if nv:
        dprop_f[:, :cm.nel, 0] = np.abs(dprop).max(axis=2)
    gprop = np.zeros((5, nel, nf), order="F")
    adj = np.zeros((cm.ndof, nf, 4), order="F")

    def backward(tp, j0, nseg, have_in, kscale, penalty):
        """The backward pass over the tape tp of the nseg steps from time point j0: the
        per-element property gradients (the core's own product with the marker column of
        dprop_f is not the gradient) and the adjoint state at j0."""
        ncol = tp["h"].size
        mut = np.zeros((nca, ncol), order="F")
        mut[:cm.nc] = tp["mu"]
        back = run_interruptible(
            simulate_adjoint_arrays, STACK_BYTES_PER_UNKNOWN * cm.n, **margs, nsteps=nseg,
            q0=np.asarray(result.initial.q0, float),
            qd0=np.asarray(result.initial.qd0, float), ap=pat["ap"], ai=pat["ai"],
            **_integrator_args(result), static_start=int(st.start == "static"),
            kscale=float(kscale), penalty=float(penalty),
            ncol=ncol, qt=np.asfortranarray(tp["q"]), qdt=np.asfortranarray(tp["qd"]),
            qddt=np.asfortranarray(tp["qdd"]), mut=mut, th=np.asarray(tp["h"], float),
            grid=np.asarray(tp["grid"], np.int32), nf=nf, gq=gq_f, gmu=gmu_f,
            nv=1, dprop=dprop_f, ntot=nt, j_start=j0, have_in=int(have_in),
            adj_in=adj, gprop_in=gprop, klu_analysis=klu_analysis(model, solver))
        if back.status != 0:
            _core_failure(back.status, back.info, "", f"the backward pass failed at t = "
                          f"{back.info[0]:.6g} s (core status {int(back.status)}, code "
                          f"{int(back.info[3])}): a singular transposed iteration matrix")
        return back.gprop, back.adj_out

    if tape is not None:
        gprop, _ = backward(tape, 0, nt - 1, False, st.kscale or 0.0, st.penalty or 0.0)
    else:
        every, states = int(ck["every"]), np.asarray(ck["states"], float)
        nsteps = nt - 1
        nseg = -(-nsteps // every)
        for k in range(nseg - 1, -1, -1):       # the segments from the last to the first
            j0 = k * every
            n_k = min(every, nsteps - j0)
            xs = np.ascontiguousarray(states[:, k])
            tp = _segment_tape(model, result, margs, pat, xs, j0, n_k)
            # the run's scalings k, p; the first segment recomputes them (and the static
            # start's, from the settings) as the first run did
            kp = (st.kscale or 0.0, st.penalty or 0.0) if j0 == 0 else (xs[-2], xs[-1])
            gprop, adj = backward(tp, j0, n_k, k < nseg - 1, *kp)
            adj = np.asfortranarray(adj)
            gprop = np.asfortranarray(gprop)
    grad = np.tensordot(dprop, gprop[:, :cm.nel], axes=([0, 1], [0, 1]))     # (nv, nf)
    if return_properties:
        return grad, np.array(gprop[:, :cm.nel])
    return grad


def _step_times(result):
    """The times of a run's non-uniform step grid (Result.steps), None on the uniform one."""
    return None if result.steps is None else result.steps["t"]


def _integrator_args(result):
    """The core's integrator settings of a run from its Result.settings: what the backward
    pass and a segment's re-run must share with the forward run."""
    st, tg = result.settings, _step_times(result)
    return dict(h=float(st.h), rho_inf=float(st.rho_inf), tol=float(st.tol),
                max_iter=int(st.max_iter), max_cuts=int(st.max_cuts),
                solver=_SOLVERS[st.solver], tg=np.zeros(1) if tg is None else tg)


def _core_failure(status, info, where, failure):
    """Raise for a core call that returned a non-zero status: ResourceError for a failed
    allocation (Status.NO_MEMORY; `where` says during what), else SimulationError('adjoint_gradient: '
    + failure) at the time info[0]."""
    if status == Status.NO_MEMORY:
        raise ResourceError(f"adjoint_gradient: an allocation failed in the core{where} "
                            f"({format_bytes(info[1]) if info[1] > 0 else 'size unknown'})",
                            required=float(info[1]) if info[1] > 0 else None)
    raise SimulationError(f"adjoint_gradient: {failure}", time=float(info[0]), code=int(status))


def _segment_tape(model, result, margs, pat, x_start, j0, nseg):
    """The tape of the nseg steps from time point j0 of a checkpointed run (result), re-run
    from its checkpoint x_start with the run's settings (a fresh iteration matrix at the
    segment's start: the states agree with the first run's to the Newton tolerance; bitwise
    with full Newton)."""
    cm = model.compile()
    st = result.settings
    nel = cm.el_dofs.shape[1]
    ncol = segment_columns(nseg)
    for attempt in range(2):
        out = run_interruptible(
            simulate_arrays, STACK_BYTES_PER_UNKNOWN * cm.n, **margs, nsteps=nseg,
            q0=np.asarray(result.initial.q0, float), qd0=np.asarray(result.initial.qd0, float),
            ap=pat["ap"], ai=pat["ai"], **_integrator_args(result),
            newton=NEWTON_MODES[st.newton], static_start=0,
            kscale=float(x_start[-2]), penalty=float(x_start[-1]),
            out_dofs=np.ones(1, np.int32), nv=0, dprop=np.zeros((5, nel, 1), order="F"),
            sens_dofs=np.ones(1, np.int32), want_dmu=0, ndmu=1,
            polish=int(st.polish), ntape=ncol, nckr=x_start.size, nck=1,
            ckpt_every=0, restart=1, x_start=x_start, j_start=int(j0),
            klu_analysis=klu_analysis(model, st.solver))
        status, info = int(out.status), out.info
        if status == Status.TAPE_FULL and attempt == 0:
            ncol = nseg * 2 ** int(st.max_cuts) + 1
            continue
        break
    if status != 0:
        _core_failure(status, info, f" while re-running the segment from t = "
                      f"{j0 * st.h:.6g} s", f"the re-run of the segment from its checkpoint "
                      f"at t = {j0 * st.h:.6g} s failed at t = {info[0]:.6g} s (core status "
                      f"{status}), although the first run converged")
    return out.tape(cm.nc)
