"""Derivative checkers shipped with the solver (after MINPACK's ``chkder``).

``check_tangent`` compares the exact tangent stiffness of one beam element
(``beam2d.f90``) with central finite differences of its internal forces at
random deformed states; ``check_iteration_matrix`` compares the whole
iteration matrix of eq. (7) of a model with central finite differences of the
residual of eq. (1). Both return a :class:`DerivativeCheck`. ``taylor_test``
checks any claimed derivative of any response (design sensitivities of a
simulation, static responses, aggregated constraints) by the order of its
Taylor remainder, without a finite-difference tolerance; it returns a
:class:`TaylorCheck`.

Relative errors are measured row by row: the largest entry of the difference
in a row divided by the largest entry of the analytic row (rows whose analytic
entries all vanish are measured against the largest entry of the matrix).
Rows of a beam element or of a mechanism mix axial, shear and bending
stiffness that differ by orders of magnitude; a single norm of the whole
matrix would hide an error in the small (bending) entries behind the large
(axial) ones.

Examples
--------
>>> from flexmbs.analysis.checks import check_tangent
>>> check_tangent(nen=3).max_relative_error < 1e-6
True
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexmbs.analysis.simulate import system_matrices
from flexmbs.core import beam_element
from flexmbs.errors import ModelError

__all__ = ["DerivativeCheck", "check_tangent", "check_iteration_matrix", "TaylorCheck",
           "taylor_test", "generalized_alpha_beta_prime"]


@dataclass
class DerivativeCheck:
    """The outcome of a derivative check.

    Attributes
    ----------
    max_relative_error : float
        Largest row-wise relative error over all checked states (see the module docstring).
    errors : (nstates,) array
        The row-wise relative error of each checked state (or stiffness part).
    worst_entry : (int, int)
        Row and column of the largest relative error in the worst state.
    analytic, finite_difference : 2-d arrays
        The two matrices of the worst state.
    step : float
        The finite-difference step used.
    """
    max_relative_error: float
    errors: np.ndarray
    worst_entry: tuple
    analytic: np.ndarray
    finite_difference: np.ndarray
    step: float

    def __float__(self):
        return float(self.max_relative_error)

    def __repr__(self):
        return (f"DerivativeCheck(max_relative_error={self.max_relative_error:.3e}, "
                f"states={self.errors.size}, worst_entry={self.worst_entry}, step={self.step:g})")


def _rowwise_error(a, b):
    """Largest row-wise relative difference of b against a, and its (row, column)."""
    diff = np.abs(a - b)
    scale = np.max(np.abs(a), axis=1)
    floor = max(np.max(np.abs(a)), np.finfo(float).tiny)
    scale = np.where(scale > 1e-12 * floor, scale, floor)
    rel = diff / scale[:, None]
    i, j = np.unravel_index(np.argmax(rel), rel.shape)
    return float(rel[i, j]), (int(i), int(j))


def _central_jacobian(fun, x0, steps):
    """Central-difference Jacobian of fun at x0 with per-coordinate steps."""
    f0 = fun(x0)
    jac = np.empty((f0.size, x0.size))
    for j in range(x0.size):
        e = np.zeros_like(x0)
        e[j] = steps[j]
        jac[:, j] = (fun(x0 + e) - fun(x0 - e)) / (2 * steps[j])
    return jac


def check_tangent(nen=3, *, states=5, length=0.5, stiffness=None, rotation=np.pi,
                  strain=0.2, step=1e-6, seed=0, damping_time=0.0):
    """Check the beam element tangent ``ke`` against central differences of ``fe``.

    At each random state the element (reference straight, of the given length,
    at a random orientation) is given a random rigid rotation of up to
    ``rotation`` rad, a random displacement of its nodes of up to
    ``strain * length`` and random nodal rotations of up to ``strain`` rad, so
    that axial, shear and bending strains and the geometric stiffness are all
    present. Every stiffness part (EA alone, kGA alone, EI alone) and the
    combined stiffness are checked separately, so an error in a small part is
    not hidden behind a large one.

    Parameters
    ----------
    nen : {2, 3}, default 3
        Nodes of the element (2: linear, 3: quadratic).
    states : int, default 5
        Random deformed states checked.
    length : float, default 0.5
        Reference element length (m).
    stiffness : (EA, kGA, EI) or None, default None
        Combined stiffness checked besides the unit parts; None: random values
        of order one scaled so that the three parts contribute alike.
    rotation : float, default pi
        Largest rigid rotation of the deformed state (rad).
    strain : float, default 0.2
        Size of the deformation relative to the element length.
    step : float, default 1e-6
        Central-difference step relative to max(1, length) on every coordinate.
    seed : int, default 0
        Seed of the random states.
    damping_time : float, default 0.0
        Kelvin–Voigt time eta (s) of the material: with eta > 0 every state also has
        random velocities (a rigid rotation rate and a deformation rate of order
        strain / eta), the forces include the viscous part, and besides ``ke`` = dfe/dq
        at fixed velocities the damping matrix ``ce`` = dfe/dqd is checked (one more
        entry per part in ``errors``).

    Returns
    -------
    DerivativeCheck
        ``max_relative_error`` over all states and parts (``errors`` has one
        entry per state and part).
    """
    if nen not in (2, 3):
        raise ModelError(f"check_tangent: nen must be 2 or 3, got {nen!r}")
    if not (length > 0 and step > 0 and states >= 1):
        raise ModelError("check_tangent: length, step and states must be positive")
    rng = np.random.default_rng(seed)
    errors = []
    worst = (-1.0, (0, 0), None, None)
    h = step * max(1.0, length)
    for _ in range(states):
        theta0 = rng.uniform(-np.pi, np.pi)
        origin = rng.uniform(-1, 1, 2)
        s = np.linspace(0.0, length, nen)
        qref = np.column_stack([origin[0] + s * np.cos(theta0), origin[1] + s * np.sin(theta0),
                                np.full(nen, theta0)]).ravel()
        alpha = rng.uniform(-rotation, rotation)
        c, sn = np.cos(alpha), np.sin(alpha)
        xy = np.column_stack([qref[0::3] - origin[0], qref[1::3] - origin[1]])
        xy = xy @ np.array([[c, sn], [-sn, c]]) + origin + rng.uniform(-1, 1, 2)
        xy += strain * length * rng.uniform(-1, 1, (nen, 2))
        phi = qref[2::3] + alpha + strain * rng.uniform(-1, 1, nen)
        qe = np.column_stack([xy, phi]).ravel()
        if stiffness is None:
            ea = rng.uniform(0.5, 2.0)
            comb = np.array([ea, rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0) * length ** 2])
        else:
            comb = np.asarray(stiffness, float)
        eta = float(damping_time)
        qde = np.zeros(qe.size)
        if eta > 0:
            # a rigid rotation rate (no strain rate) plus a deformation rate
            omega = rng.uniform(-1, 1) / eta
            qde[0::3] = -omega * (qe[1::3] - qe[1])
            qde[1::3] = omega * (qe[0::3] - qe[0])
            qde[2::3] = omega
            qde += strain / eta * rng.uniform(-1, 1, qe.size) * np.tile([length, length, 1.0], nen)
        for stiff in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), comb):
            _, ke, ce = beam_element(length, stiff, qref, qe, eta, qde)
            pairs = [(ke, lambda q, stiff=stiff: beam_element(length, stiff, qref, q, eta,
                                                                     qde)[0], qe)]
            if eta > 0:
                pairs.append((ce, lambda v, stiff=stiff: beam_element(length, stiff, qref, qe,
                                                                            eta, v)[0], qde))
            for analytic, fe, x0 in pairs:
                kfd = _central_jacobian(fe, x0, np.full(x0.size, h * max(1.0, np.max(np.abs(x0)))))
                err, ij = _rowwise_error(analytic, kfd)
                errors.append(err)
                if err > worst[0]:
                    worst = (err, ij, analytic.copy(), kfd)
    errors = np.array(errors)
    return DerivativeCheck(float(errors.max()), errors, worst[1], worst[2], worst[3], h)


def generalized_alpha_beta_prime(h, rho_inf):
    """beta' = (1 - alpha_m) / (beta h^2 (1 - alpha_f)) of eq. (7) for step h and rho_inf."""
    if not (h > 0 and 0 <= rho_inf <= 1):
        raise ModelError(f"need h > 0 and rho_inf in [0, 1], got h={h!r}, rho_inf={rho_inf!r}")
    alpha_m = (2 * rho_inf - 1) / (rho_inf + 1)
    alpha_f = rho_inf / (rho_inf + 1)
    gamma = 0.5 - alpha_m + alpha_f
    beta = 0.25 * (gamma + 0.5) ** 2
    return (1 - alpha_m) / (beta * h * h * (1 - alpha_f))


def check_iteration_matrix(model, q, qdd=None, mu=None, t=0.0, *, beta_prime=None, kscale=None,
                           penalty=None, step=1e-6, qd=None, gamma_prime=None):
    """Check the iteration matrix of eq. (7) against finite differences of the residual.

    The unknowns of a Newton correction are (dq, dlambda) with the physical
    multipliers mu = k lambda (see fortran/assembly.f90), and the accelerations
    follow the positions as dqdd = beta' dq, the velocities as dqd = gamma' dq
    (eqs. 3-5). Column j of the iteration matrix is therefore compared with the
    central difference of

        r(q + e dq_j, qd + gamma' e dq_j, qdd + beta' e dq_j, mu)   for a coordinate j,
        r(q, qd, qdd, mu + k e)                                      for a multiplier,

    where r is the dynamic residual of eq. (1) (mass term with factor 1),
    computed by :func:`flexmbs.analysis.simulate.system_matrices`.

    Parameters
    ----------
    model : flexmbs.Model
    q : (ndof,) array
        Coordinates of the state (need not satisfy the constraints).
    qdd : (ndof,) array or None, default None (zero)
        Accelerations of the state.
    mu : (nc,) array or None, default None (zero)
        Physical multipliers of the state.
    t : float, default 0.0
        Time at which the drive laws are evaluated.
    beta_prime : float or None, default None
        Coefficient of M in the iteration matrix; None: the generalized-alpha
        value for h = 5e-4 s and rho_inf = 0.5 (the paper's settings).
    qd : (ndof,) array or None, default None (zero)
        Velocities of the state (they matter for spring-dampers only).
    gamma_prime : float or None, default None
        Coefficient of the damping matrix C_t; None: the generalized-alpha value
        gamma / (beta h) for h = 5e-4 s and rho_inf = 0.5.
    kscale, penalty : float or None, default None
        k and p of eq. (1); None: k = the mean absolute diagonal of
        beta' M + K_t (the core's automatic choice), p = k.
    step : float, default 1e-6
        Central-difference step on the coordinates, relative to max(1, max|q|).

    Returns
    -------
    DerivativeCheck
        ``analytic`` is the iteration matrix, ``finite_difference`` its
        difference approximation, both (ndof + nc, ndof + nc).
    """

    cm_ = model.compile()
    ndof, nc = cm_.ndof, cm_.nc
    q = np.asarray(q, float)
    qdd = np.zeros(ndof) if qdd is None else np.asarray(qdd, float)
    mu = np.zeros(nc) if mu is None else np.asarray(mu, float)
    if q.shape != (ndof,) or qdd.shape != (ndof,) or mu.shape != (nc,):
        raise ModelError(f"check_iteration_matrix: q and qdd need {ndof} entries, mu {nc}")
    qd = np.zeros(ndof) if qd is None else np.asarray(qd, float)
    if qd.shape != (ndof,):
        raise ModelError(f"check_iteration_matrix: qd needs {ndof} entries, got shape {qd.shape}")
    if beta_prime is None:
        beta_prime = generalized_alpha_beta_prime(5e-4, 0.5)
    if gamma_prime is None:
        rho, h_ = 0.5, 5e-4
        alpha_m, alpha_f = (2 * rho - 1) / (rho + 1), rho / (rho + 1)
        gamma = 0.5 - alpha_m + alpha_f
        gamma_prime = gamma / (0.25 * (gamma + 0.5) ** 2 * h_)
    if kscale is None:
        _, s0 = system_matrices(model, q, qdd, mu, t, cm=beta_prime, ck=1.0, qd=qd,
                                cc=gamma_prime)
        kscale = float(np.mean(np.abs(np.diag(s0)[:ndof]))) or 1.0
    if penalty is None:
        penalty = kscale

    def res(qq, aa, mm, vv=qd):
        return system_matrices(model, qq, aa, mm, t, cm=1.0, ck=1.0, kscale=kscale,
                               penalty=penalty, qd=vv)[0]

    _, s = system_matrices(model, q, qdd, mu, t, cm=beta_prime, ck=1.0, kscale=kscale,
                           penalty=penalty, qd=qd, cc=gamma_prime)
    h = step * max(1.0, float(np.max(np.abs(q))))
    n = ndof + nc
    sfd = np.empty((n, n))
    for j in range(n):
        if j < ndof:
            e = np.zeros(ndof)
            e[j] = h
            sfd[:, j] = (res(q + e, qdd + beta_prime * e, mu, qd + gamma_prime * e)
                         - res(q - e, qdd - beta_prime * e, mu, qd - gamma_prime * e)) / (2 * h)
        else:
            e = np.zeros(nc)
            e[j - ndof] = kscale
            # the residual is linear in mu: a unit step in lambda is exact
            sfd[:, j] = (res(q, qdd, mu + e) - res(q, qdd, mu - e)) / 2.0
    err, ij = _rowwise_error(s, sfd)
    return DerivativeCheck(err, np.array([err]), ij, s, sfd, h)


# ============================================================================ Taylor test
@dataclass
class TaylorCheck:
    """The outcome of a Taylor test of a gradient (see :func:`taylor_test`).

    Attributes
    ----------
    steps : (k,) array
        The steps s (each half the previous one).
    remainders : (k,) array
        e(s) = max over the response's components of |r(x + s d) - r(x) - s J d|.
    increments : (k,) array
        max |r(x + s d) - r(x)| (first order in s whatever the gradient).
    orders : (k - 1,) array
        Observed order of each halving, log(e(s) / e(s/2)) / log 2.
    order : float
        The median of `orders` (2 for a right gradient, 1 for a wrong one).
    slope : float
        Least-squares slope of log e against log s (a second estimate of the order).
    min_order : float
        The order the check asks for.
    floor : float
        The smallest remainder the check accepts (noise and rounding of the response).
    direction : (nv,) array
        The direction d.
    """
    steps: np.ndarray
    remainders: np.ndarray
    increments: np.ndarray
    orders: np.ndarray
    order: float
    slope: float
    min_order: float
    floor: float
    direction: np.ndarray

    @property
    def above_floor(self):
        """True if every remainder lies above the noise/rounding floor."""
        return bool(np.all(self.remainders > self.floor))

    @property
    def ok(self):
        """The gradient passes: observed order > min_order, remainders above the floor."""
        return bool(self.order > self.min_order and self.above_floor)

    def __bool__(self):
        return self.ok

    def table(self):
        """The step study as text."""
        lines = ["        step s    |r(x+sd)-r(x)|    remainder e(s)    order"]
        for k, (s, inc, e) in enumerate(zip(self.steps, self.increments, self.remainders)):
            o = f"{self.orders[k - 1]:8.3f}" if k else "        "
            lines.append(f"  {s:12.4e}    {inc:14.4e}    {e:14.4e}  {o}")
        lines.append(f"  order (median) {self.order:.3f}, least-squares slope {self.slope:.3f}, "
                     f"required > {self.min_order:g}; floor {self.floor:.2e}"
                     + ("" if self.above_floor else " (REACHED)"))
        return "\n".join(lines)

    def __repr__(self):
        return (f"TaylorCheck(order={self.order:.3f}, slope={self.slope:.3f}, ok={self.ok}, "
                f"remainders={self.remainders[0]:.2e}..{self.remainders[-1]:.2e})")


def _taylor_one(values, r0, jd, steps, min_order, noise, direction):
    r0 = np.asarray(r0, float)
    rem = np.array([np.max(np.abs(np.asarray(v, float) - r0 - s * jd)) for s, v in zip(steps, values)])
    inc = np.array([np.max(np.abs(np.asarray(v, float) - r0)) for v in values])
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.log2(np.where(rem > 0, rem, np.nan))
        orders = (logs[:-1] - logs[1:]) / np.log2(steps[:-1] / steps[1:])
        slope = float(np.polyfit(np.log2(steps), logs, 1)[0]) if np.all(np.isfinite(logs)) \
            else float("nan")
    orders = np.where(np.isfinite(orders), orders, -np.inf)
    # rounding of the response itself: a remainder must stay well above eps * |r|
    floor = max(float(noise), 1e3 * np.finfo(float).eps * float(np.max(np.abs(r0), initial=0.0)))
    return TaylorCheck(steps=np.asarray(steps, float), remainders=rem, increments=inc,
                       orders=orders, order=float(np.median(orders)), slope=slope,
                       min_order=float(min_order), floor=floor, direction=direction)


def taylor_test(fun, x, jacobian, direction=None, *, step, halvings=6, value=None,
                min_order=1.8, noise=0.0, seed=0):
    """Taylor test of the derivative ``jacobian`` of a response ``fun`` at ``x``.

    Along a direction d the remainder

        e(s) = max_k | r_k(x + s d) - r_k(x) - s (J d)_k |

    is O(s^2) if J is the derivative of r, but only O(s) if J is wrong, whatever the
    size of the error: halving s divides e by 4 for a right derivative, by 2 for a wrong
    one (once s is small enough that the error's first-order term dominates). The test
    evaluates r at s = step, step/2, ..., step/2**halvings and asks for an observed order
    (median over the halvings) above ``min_order``. Unlike a finite-difference comparison
    at one step and one tolerance, nothing here depends on the size of the truncation or
    of the rounding error, as long as the remainders stay well above the response's noise
    (for a simulation, the Newton tolerance): choose ``step`` so that the remainder at the
    smallest step is several decades above it, and give that noise as ``noise``.

    Parameters
    ----------
    fun : callable
        x -> response: an array of any shape (a history: the max norm over its entries
        is used), or a dict name -> array to test several responses with one evaluation.
    x : (nv,) array
        The point.
    jacobian : array of shape r.shape + (nv,), or a dict of them (same keys as fun's)
        The claimed derivative of the response.
    direction : (nv,) array, optional
        Direction d (used as given: its length sets the scale of s). Default: a random
        unit vector from ``seed``.
    step : float
        The largest step s (in units of d).
    halvings : int, default 6
        Number of halvings of s (halvings + 1 evaluations of fun besides r(x)).
    value : array or dict, optional
        r(x), if already known (saves one evaluation).
    min_order : float, default 1.8
        Required observed order (2 expected, 1 for a wrong derivative).
    noise : float or dict name -> float, default 0
        Absolute noise level of the response (e.g. the effect of the solver tolerance;
        give a conservative estimate, a few times the level where the remainders of a
        step study stop falling): the check fails if a remainder is not above it (the
        order would then measure the noise). A floor of 1e3 eps max|r(x)| (rounding) is
        always applied.

    Returns
    -------
    TaylorCheck, or a dict name -> TaylorCheck if fun returns a dict.
    """
    x = np.asarray(x, float)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ModelError(f"taylor_test: x must be a finite 1-d array, got {x!r}")
    if not (isinstance(halvings, (int, np.integer)) and halvings >= 2):
        raise ModelError(f"taylor_test: halvings must be an integer >= 2, got {halvings!r}")
    if not (np.isfinite(step) and step > 0):
        raise ModelError(f"taylor_test: step must be a positive finite number, got {step!r}")
    if direction is None:
        d = np.random.default_rng(seed).standard_normal(x.size)
        d /= np.linalg.norm(d)
    else:
        d = np.asarray(direction, float)
        if d.shape != x.shape or not np.any(d):
            raise ModelError(f"taylor_test: direction must be a nonzero array of shape "
                             f"{x.shape}, got {direction!r}")
    r0 = fun(x) if value is None else value
    as_dict = isinstance(r0, dict)
    r0d = dict(r0) if as_dict else {None: r0}
    jac = dict(jacobian) if as_dict else {None: jacobian}
    if set(jac) != set(r0d):
        raise ModelError(f"taylor_test: jacobian keys {sorted(map(str, jac))} differ from the "
                         f"response keys {sorted(map(str, r0d))}")
    jd = {}
    for k, v in r0d.items():
        J = np.asarray(jac[k], float)
        v = np.asarray(v, float)
        if J.shape != v.shape + (x.size,):
            raise ModelError(f"taylor_test: jacobian{'' if k is None else f'[{k!r}]'} must have "
                             f"shape {v.shape + (x.size,)}, got {J.shape}")
        jd[k] = J @ d
    steps = step * 0.5 ** np.arange(halvings + 1)
    values = {k: [] for k in r0d}
    for s in steps:
        r = fun(x + s * d)
        r = r if as_dict else {None: r}
        for k in r0d:
            values[k].append(r[k])
    noise = dict(noise) if isinstance(noise, dict) else {k: noise for k in r0d}
    if set(noise) != set(r0d):
        raise ModelError(f"taylor_test: noise keys {sorted(map(str, noise))} differ from the "
                         f"response keys {sorted(map(str, r0d))}")
    out = {k: _taylor_one(values[k], r0d[k], jd[k], steps, min_order, noise[k], d) for k in r0d}
    return out if as_dict else out[None]
