"""Design gradients by the discrete adjoint of the generalized-alpha scheme.

For functionals of the whole discrete solution,

    G_f = sum_j ( gq[j, :, f] . q_j + gmu[j, :, f] . mu_j ),

that is, the per-step partials of a response aggregated over time (KS, p-norm, max, final
value, a weighted sum), `adjoint_gradient` returns dG_f/dp for every design variable p with
one backward pass over the stored converged states (Fortran, fortran/adjoint.f90): one
factorization and one transposed solve of the step's iteration matrix per step, for all nf
functionals at once, whatever the number of design variables. The derivation is in
docs/adjoint.md; the result is the transpose of the direct differentiation that
`simulate(design_derivatives=...)` carries forward, so both agree to the Newton tolerance.

>>> import numpy as np
>>> from flexmbs.adjoint import adjoint_gradient, simulate_for_adjoint
>>> from flexmbs.problem import Problem
>>> mech = Problem("robot_2dof").mechanism
>>> model = mech.set_design(mech.start)
>>> r = simulate_for_adjoint(model, 0.05, 5e-4, start="static")   # the tape of every state
>>> gq = np.zeros((r.t.size, model.ndof))
>>> gq[-1, 0] = 1.0                                           # G = q_0(t_end)
>>> adjoint_gradient(model, r, mech.element_property_derivatives(mech.start), gq).shape
(4, 1)
"""
from __future__ import annotations

import numpy as np

from flexmbs import _core
from flexmbs.core import core_model_args
from flexmbs.errors import ModelError, ResourceError, SimulationError
from flexmbs.model import Model
from flexmbs.resources import format_bytes, limit_source
from flexmbs.resources import memory_limit as _memory_limit
from flexmbs.simulate import Result, simulate

__all__ = ["adjoint_gradient", "simulate_for_adjoint", "adjoint_memory", "check_adjoint_memory"]

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


def simulate_for_adjoint(model, t_end, h=5e-4, **kwargs):
    """`simulate` keeping the tape of every converged (sub-)step (tape=True) with the states
    converged as full Newton's (polish=True: modified Newton's states, 1e-11 m off, made the
    adjoint's gradients 2e-8 to 7e-7 off on the robot): the states the backward pass needs.
    kwargs as `simulate` (not tape, polish, design_derivatives)."""
    for key in ("tape", "polish", "design_derivatives", "sensitivity_dofs",
                "constraint_force_derivatives"):
        if key in kwargs:
            raise ModelError(f"simulate_for_adjoint: {key}= is not allowed (the adjoint keeps "
                             "every state, converges every step and needs no forward "
                             "derivatives)")
    return simulate(model, t_end, h, tape=True, polish=True, **kwargs)


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
        simulate(..., tape=True, polish=True)).
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
    if tape is None or "q0" not in st or tape["q"].shape[0] != cm.ndof:
        raise ModelError("adjoint_gradient: result has no tape of its states: simulate with "
                         "simulate_for_adjoint (or simulate(..., tape=True, polish=True))")
    if st.get("newton", "full") != "full" and not st.get("polish", False) and result.dq is None:
        raise ModelError(f"adjoint_gradient: result was simulated with newton={st['newton']!r} "
                         "without polish=True: its states are modified Newton's, not converged "
                         "enough for the adjoint (use simulate_for_adjoint, or polish=True)")
    nt = result.t.size
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
    solver = st["solver"]
    pat = model.pattern(solver)
    margs = core_model_args(model, solver, result.t, model.element_properties())
    nel = cm.el_dofs.shape[1]
    dprop_f = np.zeros((5, nel, max(nv, 1)), order="F")
    dprop_f[:, :cm.nel, :nv] = dprop
    ncol = tape["h"].size
    mut = np.zeros((nca, ncol), order="F")
    mut[:cm.nc] = tape["mu"]
    grad, gprop, status, info = _core.simulate_adjoint(
        **margs, nsteps=nt - 1, q0=np.asarray(st["q0"], float), qd0=np.asarray(st["qd0"], float),
        ap=pat["ap"], ai=pat["ai"], h=float(st["h"]), rho_inf=float(st["rho_inf"]),
        tol=float(st["tol"]), max_iter=int(st["max_iter"]), max_cuts=int(st["max_cuts"]),
        solver=_SOLVERS[solver], static_start=int(st["start"] == "static"),
        kscale=float(st["kscale"]), penalty=float(st["penalty"]),
        ncol=ncol, qt=np.asfortranarray(tape["q"]), qdt=np.asfortranarray(tape["qd"]),
        qddt=np.asfortranarray(tape["qdd"]), mut=mut, th=np.asarray(tape["h"], float),
        grid=np.asarray(tape["grid"], np.int32), nf=nf, gq=gq_f, gmu=gmu_f,
        nv=max(nv, 1), dprop=dprop_f)
    if status == 9:
        raise ResourceError(f"adjoint_gradient: an allocation failed in the core "
                            f"({format_bytes(info[1]) if info[1] > 0 else 'size unknown'})",
                            required=float(info[1]) if info[1] > 0 else None)
    if status != 0:
        raise SimulationError(f"adjoint_gradient: the backward pass failed at t = {info[0]:.6g} s "
                              f"(core status {int(status)}, code {int(info[3])}): a singular "
                              "transposed iteration matrix", time=float(info[0]),
                              code=int(status))
    grad = np.array(grad[:nv])
    if return_properties:
        return grad, np.array(gprop[:, :cm.nel])
    return grad
