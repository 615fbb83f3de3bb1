"""Vibration modes of a mechanism at a configuration, and the modes a time step cannot resolve.

**Modes.** At a state (q, qd, qdd, mu, t) of a motion the residual of eq. (1) is linearized:
M = dr/dqdd, C = dr/dqd (the beams' Kelvin–Voigt damping, spring-dampers) and K = dr/dq (elastic
and geometric stiffness, the multipliers' mu Phi_qq: a pendulum's restoring stiffness under
gravity), all from the core's iteration matrix (`flexmbs.core.system_matrices`). The
constraints are eliminated through an orthonormal basis Z of the null space of Phi_q
(scipy.linalg.null_space): the motions the joints allow, dq = Z y. The reduced quadratic
eigenproblem

    (lambda^2 Z^T M Z + lambda Z^T C Z + Z^T K Z) y = 0

is solved with scipy.linalg.eigh (K y = omega^2 M y) when it is undamped and symmetric, else
in its first-order form with scipy.linalg.eig. A mode's natural frequency is
|lambda| / (2 pi), its damping ratio -Re(lambda) / |lambda| (0: undamped), its shape Z y as a
nodal displacement field (dx, dy, dtheta per node), scaled to a largest translation of 1. A
mechanism's free motion (a crank turning) is a mode at 0 Hz.

**Modes the step cannot resolve.** Generalized-alpha (eqs. 3-6) integrates an undamped mode of
angular frequency omega with step h with a relative period error and a numerical damping
ratio that grow with Omega = omega h (`scheme_errors`, from the scheme's amplification
matrix). `resolved_limit(rho_inf)` is the Omega where either reaches SCHEME_TOL (1 %); a mode
with omega h beyond it is integrated with an error that depends on the scheme, not on the
mechanism. It matters when the mechanism does not damp it itself: a mode is *unresolved* at
step h when omega h > resolved_limit(rho_inf) and its damping ratio is below
max(LIGHT_DAMPING, the scheme's numerical damping at omega h): the decay the answer sees
is then mostly the integrator's.

A response *sees* a mode when the mode vibrates with at least SEEN_FRACTION (1 %) of the
deformation at the nodes the response reads: the deformation rate u' = qd - qd_rigid (the
motion less the rigid reference motion) is projected on the mode, eta' = phi^T M u' /
phi^T M phi, and the vibration amplitude |eta'| / omega times the mode's largest translation
at those nodes is compared with the largest deformation |q - q_rigid| there over the motion
(`vibration_shares`, at each time point with the modes of the nearest configuration checked).
A response that reads no node (a motor torque, a joint reaction) is judged on every node. A
mode vibrating below that share changes the response by about its share however badly the
step integrates it; a mode's quasi-static share (its part in the deformation itself, however
large) does not depend on the scheme. Without the rigid motion, a mode is seen when its shape
moves the response's nodes by SEEN_FRACTION of its largest translation.

`ModalCheck` holds the modes at a few times of a motion (`modal_check`) and lists, for a step
h, the unresolved modes each response sees (`ModalCheck.unresolved`): per response the
MAX_CHECKED lowest elastic modes it sees. A Richardson estimate from the steps h, h/2, h/4
(flexmbs.analysis.accuracy) is judged at its finest step: a mode unresolved there is
unresolved on every level of the ladder, and their agreement says nothing about it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flexmbs.core import system_matrices
from flexmbs.errors import ModelError
from flexmbs.model.constraints import constraint_jacobian

__all__ = ["Modes", "UnresolvedMode", "ModalCheck", "modes", "modes_of_result", "modal_check",
           "vibration_shares", "moving_bodies", "amplification_matrix",
           "scheme_errors", "resolved_limit", "SCHEME_TOL", "LIGHT_DAMPING", "SEEN_FRACTION",
           "MAX_CHECKED", "MODES_COMPUTED", "ZERO_FREQUENCY"]

#: relative period error or numerical damping ratio up to which a mode counts as resolved
SCHEME_TOL = 0.01
#: a mode damped below this ratio (and below the scheme's numerical damping) is lightly damped
LIGHT_DAMPING = 0.05
#: a response sees a mode vibrating with this fraction of the largest deformation at its nodes
SEEN_FRACTION = 0.01
#: the lowest elastic modes a response sees that are checked, per response and time
MAX_CHECKED = 3
#: elastic modes computed per time by `modal_check` (the lowest)
MODES_COMPUTED = 12
#: |lambda| below this fraction of the largest counts as a 0 Hz (rigid or mechanism) mode
ZERO_FREQUENCY = 1e-7


# ----------------------------------------------------------------------------- the scheme
def _alphas(rho_inf):
    am = (2.0 * rho_inf - 1.0) / (rho_inf + 1.0)
    af = rho_inf / (rho_inf + 1.0)
    gamma = 0.5 - am + af
    beta = 0.25 * (gamma + 0.5) ** 2
    return am, af, gamma, beta


def amplification_matrix(omega_h, rho_inf):
    """The amplification matrix of one generalized-alpha step (Arnold & Brüls 2007, the form
    of fortran/generalized_alpha.f90) on x'' + omega^2 x = 0 with h = 1: the state (x, v, a)
    with a the pseudo-acceleration; qdd = -omega^2 x at every step."""
    am, af, gamma, beta = _alphas(rho_inf)
    w2 = omega_h ** 2
    # unknowns at n+1: x, v, a; qdd_{n+1} = -w2 x_{n+1}
    # (1 - am) a1 + am a0 = (1 - af) qdd1 + af qdd0
    # x1 = x0 + v0 + (0.5 - beta) a0 + beta a1;  v1 = v0 + (1 - gamma) a0 + gamma a1
    a1 = np.array([[1.0, 0.0, -beta],
                   [0.0, 1.0, -gamma],
                   [(1.0 - af) * w2, 0.0, 1.0 - am]])
    a0 = np.array([[1.0, 1.0, 0.5 - beta],
                   [0.0, 1.0, 1.0 - gamma],
                   [-af * w2, 0.0, -am]])
    return np.linalg.solve(a1, a0)


def scheme_errors(omega_h, rho_inf):
    """(numerical damping ratio, relative period error) of generalized-alpha with spectral
    radius rho_inf on an undamped mode with omega h = omega_h (> 0): from the principal
    eigenvalues exp(Omega_bar (-xi +- i)) of the step's amplification matrix, xi = -ln|l| /
    arg(l) and the period error omega h / arg(l) - 1. Beyond Omega h where the principal pair
    turns real (arg 0) the mode is not integrated as an oscillation: (inf, inf)."""
    lam = np.linalg.eigvals(amplification_matrix(float(omega_h), float(rho_inf)))
    osc = lam[np.abs(lam.imag) > 1e-14]
    if osc.size == 0:
        return math.inf, math.inf
    lp = osc[np.argmax(np.abs(osc))]
    arg = abs(math.atan2(lp.imag, lp.real))
    return -math.log(abs(lp)) / arg, omega_h / arg - 1.0


def resolved_limit(rho_inf, tol=SCHEME_TOL):
    """The omega h up to which generalized-alpha with rho_inf integrates an undamped mode
    with a numerical damping ratio and a relative period error both below tol."""
    def worst(w):
        xi, per = scheme_errors(w, rho_inf)
        return max(xi, abs(per)) - tol
    from scipy.optimize import brentq     # here: a batch worker's start-up imports no scipy
    return brentq(worst, 1e-3, 3.0, xtol=1e-6)


# ----------------------------------------------------------------------------- modes
@dataclass
class Modes:
    """The vibration modes of a mechanism at one state (`modes`), lowest first.

    t : time of the state (s).
    frequency : (n,) natural frequencies |lambda| / (2 pi) (Hz); 0 for a rigid or mechanism
        motion.
    damping : (n,) damping ratios -Re(lambda) / |lambda| (0: undamped; 1 or more: no oscillation).
    eigenvalue : (n,) the eigenvalues lambda (1/s) with Im >= 0.
    shapes : (n, nnodes, 3) each mode's nodal displacements (dx, dy, dtheta), real, scaled
        to a largest translation of 1 (a mode moving no node: largest rotation 1).
    free : the number of motions the constraints allow (columns of the null-space basis).
    mass : (ndof, ndof) the mass matrix M of the state (not in JSON).
    """
    t: float
    frequency: np.ndarray
    damping: np.ndarray
    eigenvalue: np.ndarray = field(repr=False)
    shapes: np.ndarray = field(repr=False)
    free: int = 0
    mass: np.ndarray | None = field(default=None, repr=False)

    def __len__(self):
        return int(self.frequency.size)

    def to_json(self):
        return {"t": float(self.t), "frequency": [float(f) for f in self.frequency],
                "damping": [float(z) for z in self.damping], "free_motions": int(self.free)}


def _scaled_shape(v, ndof):
    v = np.asarray(v, complex)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > 0:
        v = v * (abs(v[k]) / v[k])           # the largest component real and positive
    s = v.real.reshape(ndof // 3, 3)
    trans = np.hypot(s[:, 0], s[:, 1]).max(initial=0.0)
    scale = trans if trans > 1e-12 * max(np.abs(s).max(initial=0.0), 1e-300) else \
        np.abs(s).max(initial=1.0)
    return s / (scale if scale > 0 else 1.0)


def modes(model, q=None, qd=None, qdd=None, mu=None, t=0.0, count=None):
    """The vibration modes of `model` linearized at the state (q, qd, qdd, mu, t) (defaults:
    the reference coordinates, at rest, zero multipliers, t = 0), lowest `count` (default
    all) first, as `Modes`. The multipliers mu of a loaded state (Result.mu) give the
    constraints' geometric stiffness (a pendulum under gravity); without them a hanging
    pendulum is a 0 Hz motion."""
    cm = model.compile()
    ndof, nc = cm.ndof, cm.nc
    q = cm.qref if q is None else np.asarray(q, float)
    if q.shape != (ndof,):
        raise ModelError(f"modes: q needs {ndof} entries (every coordinate), got shape {q.shape}")
    for name, v in (("qd", qd), ("qdd", qdd)):
        if v is not None and np.shape(v) != (ndof,):
            raise ModelError(f"modes: {name} needs {ndof} entries, got shape {np.shape(v)}")
    if mu is not None and np.shape(mu) != (nc,):
        raise ModelError(f"modes: mu needs {nc} entries (one per constraint row), got shape "
                         f"{np.shape(mu)}")
    if count is not None and (isinstance(count, bool) or not isinstance(count, (int, np.integer))
                              or count < 1):
        raise ModelError(f"modes: count must be a positive integer, got {count!r}")
    import scipy.linalg as sl             # here: a batch worker's start-up imports no scipy
    props = model.element_properties()
    mass = system_matrices(model, q, qdd, mu, t, cm=1.0, ck=0.0, qd=qd,
                           props=props)[1][:ndof, :ndof]
    stiff = system_matrices(model, q, qdd, mu, t, cm=0.0, ck=1.0, qd=qd,
                            props=props)[1][:ndof, :ndof]
    damp = system_matrices(model, q, qdd, mu, t, cm=0.0, ck=0.0, qd=qd, cc=1.0,
                           props=props)[1][:ndof, :ndof]
    z = sl.null_space(constraint_jacobian(cm, q)) if nc else np.eye(ndof)
    nf = z.shape[1]
    if nf == 0:
        empty = np.zeros(0)
        return Modes(float(t), empty, empty, empty.astype(complex), np.zeros((0, ndof // 3, 3)),
                     0, mass)
    mr, cr, kr = (z.T @ a @ z for a in (mass, damp, stiff))
    mr = 0.5 * (mr + mr.T)
    scale_k = max(np.abs(kr).max(initial=0.0), 1e-300)
    if np.abs(cr).max(initial=0.0) == 0.0 and np.abs(kr - kr.T).max() <= 1e-10 * scale_k:
        # undamped, symmetric: K y = omega^2 M y (scipy.linalg.eigh); lambda = i omega
        # every eigenvalue: the largest sets the rounding level of the 0 Hz ones
        w2, y = sl.eigh(0.5 * (kr + kr.T), mr)
        w2 = np.where(np.abs(w2) <= ZERO_FREQUENCY ** 2 * max(np.abs(w2).max(), 1e-300), 0.0, w2)
        lam = np.where(w2 >= 0, 1j * np.sqrt(np.abs(w2)), np.sqrt(np.abs(w2)) + 0j)
        vec = y
    else:
        # first-order form in the mass's Cholesky factor M = L L^T, u = L^T y:
        # [[0, I], [-L^-1 K L^-T, -L^-1 C L^-T]] (u, lambda u) = lambda (u, lambda u)
        low = sl.cholesky(mr, lower=True)
        kt = sl.solve_triangular(low, sl.solve_triangular(low, kr.T, lower=True).T, lower=True)
        ct = sl.solve_triangular(low, sl.solve_triangular(low, cr.T, lower=True).T, lower=True)
        eye, zero = np.eye(nf), np.zeros((nf, nf))
        lam, u = sl.eig(np.block([[zero, eye], [-kt, -ct]]))
        ok = np.isfinite(lam)
        lam, u = lam[ok], u[:, ok]
        big = max(np.abs(lam).max(initial=0.0), 1e-300)
        lam = np.where(np.abs(lam) <= ZERO_FREQUENCY * big, 0.0, lam)
        # one of each conjugate pair (Im >= 0); an overdamped pair (two real roots) is kept
        keep = lam.imag >= -1e-12 * big
        lam, u = lam[keep], u[:, keep]
        vec = sl.solve_triangular(low, u[:nf], lower=True, trans="T")
        # lambda = 0 is a double root of a 0 Hz motion: one per independent shape
        zero_idx = np.where(lam == 0)[0]
        if zero_idx.size > 1:
            y0 = vec[:, zero_idx]
            rank = np.linalg.matrix_rank(y0, tol=1e-8 * max(np.abs(y0).max(), 1e-300))
            drop = zero_idx[rank:]
            lam, vec = np.delete(lam, drop), np.delete(vec, drop, axis=1)
    order = np.lexsort((-lam.real, np.abs(lam)))
    lam, vec = lam[order], vec[:, order]
    if count is not None:
        lam, vec = lam[:count], vec[:, :count]
    absl = np.abs(lam)
    damping = np.where(absl > 0, -lam.real / np.where(absl > 0, absl, 1.0), 0.0)
    damping = np.where(np.abs(damping) < 1e-9, 0.0, damping)
    shapes = np.array([_scaled_shape(z @ vec[:, i], ndof) for i in range(lam.size)])
    return Modes(float(t), absl / (2.0 * np.pi), damping, lam,
                 shapes.reshape(lam.size, ndof // 3, 3), nf, mass)


def modes_of_result(model, result, times=None, count=None):
    """[Modes] of `model` at states of a simulated `result` that kept every coordinate
    (store='all'): at the grid points nearest `times` (default: the start)."""
    cm = model.compile()
    if result.q.shape[1] != cm.ndof or not np.array_equal(result.dofs, np.arange(cm.ndof)):
        raise ModelError("modes_of_result: the result must keep every coordinate "
                         "(simulate with store='all')")
    times = [float(result.t[0])] if times is None else [float(v) for v in np.atleast_1d(times)]
    out = []
    for tt in times:
        if not result.t[0] - 1e-12 <= tt <= result.t[-1] + 1e-12:
            raise ModelError(f"modes: time {tt:g} s is outside the motion [{result.t[0]:g}, "
                             f"{result.t[-1]:g}] s")
        j = int(np.argmin(np.abs(result.t - tt)))
        out.append(modes(model, result.q[j], result.qd[j], result.qdd[j],
                         result.mu[j] if cm.nc else None, float(result.t[j]), count))
    return out


# ----------------------------------------------------------------------------- the check
@dataclass
class UnresolvedMode:
    """A lightly damped mode a response sees that the step h does not resolve.

    response : the response's name; frequency (Hz) and damping (ratio) of the mode; t : the
    time of the configuration it was found at; h : the step judged; omega_h : 2 pi frequency
    h; h_resolved : the
    largest step that resolves it (resolved_limit / omega); bodies : the bodies that move most
    in it."""
    response: str
    frequency: float
    damping: float
    t: float
    h: float
    omega_h: float
    h_resolved: float
    bodies: tuple = ()

    def describe(self):
        """'mode at 671 Hz, undamped, in coupler_stress: ...'."""
        damp = "undamped" if self.damping < 1e-6 else f"damping ratio {self.damping:.2g}"
        where = f" (moving {', '.join(self.bodies)})" if self.bodies else ""
        return (f"mode at {self.frequency:.4g} Hz{where}, {damp}, in {self.response}: the "
                f"answer depends on the numerical damping (omega h = {self.omega_h:.2g} at h = "
                f"{self.h:.3g} s); add "
                f"material damping or use h <= {self.h_resolved:.2g} s")

    def to_json(self):
        return {"response": self.response, "frequency": self.frequency, "damping": self.damping,
                "t": self.t, "h": self.h, "omega_h": self.omega_h, "h_resolved": self.h_resolved,
                "bodies": list(self.bodies)}


@dataclass
class ModalCheck:
    """The lowest modes of a design at a few times of its motion (`modal_check`).

    modes : [Modes] at those times; seen : {response: (n_times, n_modes) bool}, which modes
    each response sees; bodies : per time, per mode, the bodies that move most."""
    modes: list
    seen: dict
    bodies: list

    def unresolved(self, h, rho_inf):
        """{response: [UnresolvedMode]} of the modes each response sees that step h with
        spectral radius rho_inf leaves unresolved (module docstring): per response one mode
        per frequency band (modes within 10 % of one listed, the same mode at another
        configuration, are left out), lowest first; responses with none are left out."""
        limit = resolved_limit(rho_inf)
        out = {}
        for name, seen in self.seen.items():
            found = []
            for k, md in enumerate(self.modes):
                for i in np.where(seen[k, :len(md)])[0][:MAX_CHECKED]:
                    f, zeta = float(md.frequency[i]), float(md.damping[i])
                    w = 2.0 * math.pi * f
                    if f <= 0 or not seen[k, i] or w * h <= limit:
                        continue
                    xi, _ = scheme_errors(w * h, rho_inf)
                    if zeta >= max(LIGHT_DAMPING, xi):
                        continue
                    if any(abs(u.frequency - f) <= 0.1 * f for u in found):
                        continue
                    found.append(UnresolvedMode(name, f, zeta, md.t, h, w * h, limit / w,
                                                tuple(self.bodies[k][i])))
            if found:
                out[name] = sorted(found, key=lambda u: u.frequency)
        return out


def moving_bodies(shape, owners):
    """The bodies whose largest translation in the shape is within half of the largest."""
    tr = np.hypot(shape[:, 0], shape[:, 1])
    top = tr.max(initial=0.0)
    if top <= 0:
        return ()
    best = {}
    for name, nodes in owners.items():
        best[name] = tr[nodes].max(initial=0.0)
    return tuple(n for n, v in sorted(best.items(), key=lambda kv: -kv[1]) if v >= 0.5 * top)


def vibration_shares(md, u_rate, umax, nodes):
    """Each mode's largest vibration amplitude, relative to the largest deformation umax at
    `nodes` (all when empty): max over the rows of u_rate (nt, ndof: deformation rates) of
    |eta'_i| / omega_i max|phi_i| / umax, eta'_i = phi_i^T M u' / phi_i^T M phi_i (the
    M-orthogonal projection on the mode)."""
    phi = md.shapes.reshape(len(md), -1)                       # (n, ndof)
    mphi = phi @ md.mass
    etad = (np.atleast_2d(u_rate) @ mphi.T) / np.maximum(np.einsum("ij,ij->i", mphi, phi),
                                                          1e-300)
    nn = md.shapes.shape[1]
    sel = np.asarray(list(nodes), int) if len(nodes) else np.arange(nn)
    pmax = np.hypot(md.shapes[:, sel, 0], md.shapes[:, sel, 1]).max(axis=1, initial=0.0)
    omega = 2.0 * np.pi * md.frequency
    if umax <= 0:
        return np.zeros(len(md))
    return np.abs(etad).max(axis=0, initial=0.0) / np.maximum(omega, 1e-300) * pmax / umax


def modal_check(model, result, response_nodes, times=None, count=MODES_COMPUTED, rigid=None):
    """ModalCheck of the elastic modes (the first `count` above 0 Hz) of `model` at the states
    of `result` (every coordinate kept) nearest `times` (default: the start, the middle and the end
    of the motion). response_nodes: {response: the nodes it reads (empty: every
    node)}. rigid: (q, qd), each (nt, ndof), the rigid reference motion's coordinates and
    velocities on result.t: a response sees a mode vibrating with SEEN_FRACTION of the
    largest deformation at its nodes (`vibration_shares`, each time point judged with the
    modes of the nearest time checked); without it, a mode whose shape moves its nodes by
    SEEN_FRACTION of its largest translation (module docstring)."""
    if times is None:
        t0, t1 = float(result.t[0]), float(result.t[-1])
        times = np.linspace(t0, t1, 3)
    if rigid is not None and (len(rigid) != 2 or any(np.shape(r) != np.shape(result.q)
                                                     for r in rigid)):
        raise ModelError(f"modal_check: rigid must be (q, qd) of the result's shape "
                         f"{result.q.shape}")
    times = np.asarray(times, float)
    if rigid is not None:
        u = (result.q - rigid[0]).reshape(result.t.size, -1, 3)
        u_rate = result.qd - rigid[1]
        # each time point goes with the configuration checked nearest to it
        window = np.argmin(np.abs(result.t[:, None] - times[None, :]), axis=1)
    owners = {b.name: np.asarray(b.nodes, int) for b in model.bodies.values()}
    found, bodies = [], []
    seen = {name: [] for name in response_nodes}
    # the 0 Hz motions come first: a few more than `count` hold `count` elastic modes
    for md in modes_of_result(model, result, times, count=count + 6):
        elastic = np.where(md.frequency > 0)[0][:count]
        md = Modes(md.t, md.frequency[elastic], md.damping[elastic], md.eigenvalue[elastic],
                   md.shapes[elastic], md.free, md.mass)
        found.append(md)
        bodies.append([moving_bodies(s, owners) for s in md.shapes])
        tr = np.hypot(md.shapes[:, :, 0], md.shapes[:, :, 1])     # (n, nnodes)
        top = tr.max(axis=1, initial=0.0)
        k = len(found) - 1
        for name, nodes in response_nodes.items():
            nodes = np.asarray(list(nodes), int)
            if rigid is not None:
                sel = nodes if nodes.size else np.arange(u.shape[1])
                umax = float(np.hypot(u[:, sel, 0], u[:, sel, 1]).max(initial=0.0))
                share = vibration_shares(md, u_rate[window == k], umax, nodes)
                seen[name].append(share >= SEEN_FRACTION)
            elif nodes.size == 0:
                seen[name].append(np.ones(len(md), bool))
            else:
                seen[name].append(tr[:, nodes].max(axis=1) >= SEEN_FRACTION * top)
    n = max((len(m) for m in found), default=0)
    seen_arr = {}
    for name, rows in seen.items():
        arr = np.zeros((len(found), n), bool)
        for k, r in enumerate(rows):
            arr[k, :r.size] = r
        seen_arr[name] = arr
    return ModalCheck(found, seen_arr, bodies)
