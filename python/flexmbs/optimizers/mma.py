"""The method of moving asymptotes (MMA) of Svanberg and its globally convergent form GCMMA.

A documented implementation of K. Svanberg, "The method of moving asymptotes - a new
method for structural optimization", Int. J. Numer. Meth. Engng 24 (1987) 359-373, in the
form given in K. Svanberg, "MMA and GCMMA - two methods for nonlinear optimization"
(KTH, 2007): approximations and asymptote update (sections 2-3), the conservative inner
iterations of GCMMA (section 4) and the primal-dual interior-point solution of the
subproblem (section 5). Written for the small numbers of design variables and the many
constraints (one per time step) of the fully coupled method: the Newton systems of the
subproblem are reduced to (n + 1) x (n + 1).

The problem solved is

    minimize f0(x)  subject to  fi(x) <= 0 (i = 1..m),  xmin <= x <= xmax,

and each iteration replaces every function by a convex, separable approximation with poles
at the moving asymptotes L_j < x_j < U_j,

    f~i(x) = r_i + sum_j p_ij / (U_j - x_j) + q_ij / (x_j - L_j),

whose curvature grows as the asymptotes close in on x: a reciprocal-variable
approximation, well suited to responses that fall like p^-3 to p^-4 as the deviations of
the paper's mechanisms do. The subproblem has elastic variables y_i >= 0 with a large linear
cost c (Svanberg's standard a0 = 1, a_i = 0, c_i = c, d_i = 1), so it always has a solution
and an infeasible start is pulled back towards feasibility.

Public names: `MMA` (the state of a run) and `solve_subproblem` (the interior-point
subproblem solver).
"""
from __future__ import annotations

import numpy as np

__all__ = ["MMA", "solve_subproblem"]


def solve_subproblem(p0, q0, P, Q, b, low, upp, alpha, beta, c, d, a0=1.0, a=None,
                     eps_min=1e-9, max_newton=200):
    """Solve the MMA subproblem by a primal-dual interior-point method (Svanberg 2007, sec. 5).

    minimize   sum_j (p0_j/(U_j-x_j) + q0_j/(x_j-L_j)) + a0 z + sum_i (c_i y_i + d_i y_i^2 / 2)
    subject to sum_j (P_ij/(U_j-x_j) + Q_ij/(x_j-L_j)) - a_i z - y_i <= b_i,
               alpha <= x <= beta,  y >= 0,  z >= 0.

    Parameters
    ----------
    p0, q0 : (n,) objective coefficients (>= 0).
    P, Q : (m, n) constraint coefficients (>= 0).
    b : (m,) right-hand sides.
    low, upp : (n,) asymptotes; alpha, beta : (n,) move bounds, low < alpha < beta < upp.
    c, d : (m,) costs of the elastic variables y (c > 0, d > 0).
    a0 : float, default 1; a : (m,), default zeros.
    eps_min : float, default 1e-9
        Final value of the barrier parameter (the relaxation of the complementarity).
    max_newton : int, default 200
        Newton iterations per barrier value.

    Returns
    -------
    x : (n,) solution; y : (m,) elastic variables; lam : (m,) constraint multipliers.
    """
    n, m = p0.size, b.size
    a = np.zeros(m) if a is None else np.asarray(a, float)
    x = 0.5 * (alpha + beta)
    y = np.ones(m)
    z = 1.0
    lam = np.ones(m)
    xsi = np.maximum(1.0 / (x - alpha), 1.0)
    eta = np.maximum(1.0 / (beta - x), 1.0)
    mu = np.maximum(1.0, 0.5 * c)
    zet = 1.0
    s = np.ones(m)
    epsi = 1.0

    def residual(x, y, z, lam, xsi, eta, mu, zet, s, epsi):
        ux1, xl1 = upp - x, x - low
        plam = p0 + P.T @ lam
        qlam = q0 + Q.T @ lam
        gvec = P @ (1.0 / ux1) + Q @ (1.0 / xl1)
        rex = plam / ux1 ** 2 - qlam / xl1 ** 2 - xsi + eta
        rey = c + d * y - mu - lam
        rez = a0 - zet - a @ lam
        relam = gvec - a * z - y + s - b
        rexsi = xsi * (x - alpha) - epsi
        reeta = eta * (beta - x) - epsi
        remu = mu * y - epsi
        rezet = zet * z - epsi
        res = lam * s - epsi
        return np.concatenate([rex, rey, [rez], relam, rexsi, reeta, remu, [rezet], res])

    while epsi > eps_min:
        r = residual(x, y, z, lam, xsi, eta, mu, zet, s, epsi)
        rnorm, rmax = np.linalg.norm(r), np.max(np.abs(r))
        it = 0
        while rmax > 0.9 * epsi and it < max_newton:
            it += 1
            ux1, xl1 = upp - x, x - low
            plam = p0 + P.T @ lam
            qlam = q0 + Q.T @ lam
            gvec = P @ (1.0 / ux1) + Q @ (1.0 / xl1)
            GG = P / ux1 ** 2 - Q / xl1 ** 2                     # (m, n) d g_i / d x_j
            delx = plam / ux1 ** 2 - qlam / xl1 ** 2 - epsi / (x - alpha) + epsi / (beta - x)
            dely = c + d * y - lam - epsi / y
            delz = a0 - a @ lam - epsi / z
            dellam = gvec - a * z - y - b + epsi / lam
            diagx = 2.0 * (plam / ux1 ** 3 + qlam / xl1 ** 3) + xsi / (x - alpha) + eta / (beta - x)
            diagy = d + mu / y
            diaglamyi = s / lam + 1.0 / diagy
            dellamyi = dellam + dely / diagy
            # reduced (n + 1) system in (dx, dz)
            w = 1.0 / diaglamyi
            Axx = np.diag(diagx) + GG.T @ (GG * w[:, None])
            azz = zet / z + a @ (a * w)
            axz = -GG.T @ (a * w)
            bx = delx + GG.T @ (dellamyi * w)
            bz = delz - a @ (dellamyi * w)
            AA = np.zeros((n + 1, n + 1))
            AA[:n, :n] = Axx
            AA[:n, n] = axz
            AA[n, :n] = axz
            AA[n, n] = azz
            sol = np.linalg.solve(AA, -np.concatenate([bx, [bz]]))
            dx, dz = sol[:n], sol[n]
            dlam = (GG @ dx) * w - dz * (a * w) + dellamyi * w
            dy = -dely / diagy + dlam / diagy
            dxsi = -xsi + epsi / (x - alpha) - xsi * dx / (x - alpha)
            deta = -eta + epsi / (beta - x) + eta * dx / (beta - x)
            dmu = -mu + epsi / y - mu * dy / y
            dzet = -zet + epsi / z - zet * dz / z
            ds = -s + epsi / lam - s * dlam / lam
            # step length keeping every variable strictly inside its bounds
            xx = np.concatenate([y, [z], lam, xsi, eta, mu, [zet], s])
            dxx = np.concatenate([dy, [dz], dlam, dxsi, deta, dmu, [dzet], ds])
            stm = max(np.max(-1.01 * dxx / xx), np.max(-1.01 * dx / (x - alpha)),
                      np.max(1.01 * dx / (beta - x)), 1.0)
            step = 1.0 / stm
            old = (x, y, z, lam, xsi, eta, mu, zet, s)
            for _ in range(50):
                x = old[0] + step * dx
                y = old[1] + step * dy
                z = old[2] + step * dz
                lam = old[3] + step * dlam
                xsi = old[4] + step * dxsi
                eta = old[5] + step * deta
                mu = old[6] + step * dmu
                zet = old[7] + step * dzet
                s = old[8] + step * ds
                r = residual(x, y, z, lam, xsi, eta, mu, zet, s, epsi)
                new = np.linalg.norm(r)
                if new <= rnorm:
                    break
                step *= 0.5
            rnorm, rmax = new, np.max(np.abs(r))
        epsi *= 0.1
    return x, y, lam


class MMA:
    """State of an MMA / GCMMA run (Svanberg 2007, sections 2-4).

    Parameters
    ----------
    xmin, xmax : (n,) bounds of the (scaled) design variables.
    conservative : bool, default True
        True: GCMMA, the globally convergent version (section 4): after each subproblem the
        caller evaluates the functions at its solution and, while some approximation is not
        conservative (f~i(x) < fi(x)), the curvature parameters rho_i of the offending
        functions grow and the subproblem is solved again with the same asymptotes ("inner
        iterations", one analysis each). False: plain MMA, one analysis per iteration.
    move : float, default 0.5
        Move limit: a step changes x_j by at most move (xmax_j - xmin_j).
    asyinit : float, default 0.5
        Initial distance of the asymptotes from x, as a fraction of xmax - xmin.
    asyincr, asydecr : float, default 1.2 and 0.7
        Factors that widen the asymptotes when x_j moves monotonically and narrow them when
        it oscillates.
    albefa : float, default 0.1
        The subproblem keeps x_j at least albefa (x_j - L_j) away from an asymptote.
    c : float, default 1000
        Cost of the elastic variables (large: the subproblem satisfies the approximated
        constraints whenever it can).
    check_below : float, default -0.05
        GCMMA: constraints whose value at the trial point is below this are not checked for
        conservativeness (they are satisfied with a margin; Svanberg checks all of them, which
        with one constraint per time step spends inner iterations on irrelevant steps).

    Notes
    -----
    Use (GCMMA)::

        x_trial = mma.step(x, f0, df0, f, df)
        while not mma.conservative(f0(x_trial), f(x_trial)):
            x_trial = mma.tighten(f0(x_trial), f(x_trial))
    """

    def __init__(self, xmin, xmax, *, conservative=True, move=0.5, asyinit=0.5, asyincr=1.2,
                 asydecr=0.7, albefa=0.1, c=1000.0, check_below=-0.05):
        self.xmin = np.asarray(xmin, float)
        self.xmax = np.asarray(xmax, float)
        if self.xmin.shape != self.xmax.shape or np.any(self.xmax <= self.xmin):
            raise ValueError("MMA: xmax must exceed xmin elementwise")
        self.conservative_mode = bool(conservative)
        self.move, self.asyinit = float(move), float(asyinit)
        self.asyincr, self.asydecr = float(asyincr), float(asydecr)
        self.albefa, self.c = float(albefa), float(c)
        self.check_below = float(check_below)
        self.eps = 1e-7
        self.k = 0
        self.xold1 = self.xold2 = None
        self.low = self.upp = None
        self.last_multipliers = None
        self.last_elastic = None
        self.inner = 0

    @property
    def _range(self):
        return np.maximum(self.xmax - self.xmin, 1e-5)

    def _asymptotes(self, x):
        rng = self._range
        if self.k <= 2 or self.xold2 is None:
            low = x - self.asyinit * rng
            upp = x + self.asyinit * rng
        else:
            zzz = (x - self.xold1) * (self.xold1 - self.xold2)
            factor = np.ones_like(x)
            factor[zzz > 0] = self.asyincr
            factor[zzz < 0] = self.asydecr
            low = x - factor * (self.xold1 - self.low)
            upp = x + factor * (self.upp - self.xold1)
            low = np.clip(low, x - 10.0 * rng, x - 0.01 * rng)
            upp = np.clip(upp, x + 0.01 * rng, x + 10.0 * rng)
        return low, upp

    def _coefficients(self, grad, rho):
        """p, q of f~ = r + sum p/(U-x) + q/(x-L) for gradients (k, n) and curvatures (k,)."""
        ux2, xl2 = (self.upp - self.x) ** 2, (self.x - self.low) ** 2
        pos, neg = np.maximum(grad, 0.0), np.maximum(-grad, 0.0)
        reg = rho[:, None] / self._range[None, :]
        p = (1.001 * pos + 0.001 * neg + reg) * ux2[None, :]
        q = (0.001 * pos + 1.001 * neg + reg) * xl2[None, :]
        return p, q

    def _solve(self):
        p0, q0 = self._coefficients(self.df0[None, :], np.array([self.rho0]))
        P, Q = self._coefficients(self.df, self.rho)
        self._p0, self._q0, self._P, self._Q = p0[0], q0[0], P, Q
        ux, xl = self.upp - self.x, self.x - self.low
        self._r0 = self.f0 - (self._p0 / ux + self._q0 / xl).sum()
        self._r = self.f - (P / ux + Q / xl).sum(axis=1)
        m = self.f.size
        xt, y, lam = solve_subproblem(self._p0, self._q0, P, Q, -self._r, self.low, self.upp,
                                      self.alpha, self.beta, c=np.full(m, self.c), d=np.ones(m))
        self.last_multipliers, self.last_elastic = lam, y
        self.x_trial = np.clip(xt, self.xmin, self.xmax)
        return self.x_trial

    def step(self, x, f0, df0, f, df):
        """Start an iteration at x; return the solution of the subproblem.

        Parameters
        ----------
        x : (n,) current design (within the bounds).
        f0 : float, df0 : (n,) objective and its gradient.
        f : (m,) constraint values (feasible when <= 0); df : (m, n) their gradients.
        """
        self.x = np.asarray(x, float).copy()
        self.f0, self.df0 = float(f0), np.asarray(df0, float)
        self.f, self.df = np.asarray(f, float), np.asarray(df, float)
        self.k += 1
        self.inner = 0
        self.low, self.upp = self._asymptotes(self.x)
        rng = self._range
        self.alpha = np.maximum.reduce([self.low + self.albefa * (self.x - self.low),
                                        self.x - self.move * rng, self.xmin])
        self.beta = np.minimum.reduce([self.upp - self.albefa * (self.upp - self.x),
                                       self.x + self.move * rng, self.xmax])
        n = self.x.size
        if self.conservative_mode:       # Svanberg 2007, eq. (4.4): rho from the gradients
            self.rho0 = max(1e-6, 0.1 / n * float(np.abs(self.df0) @ rng))
            self.rho = np.maximum(1e-6, 0.1 / n * (np.abs(self.df) @ rng))
        else:
            self.rho0 = 1e-5
            self.rho = np.full(self.f.size, 1e-5)
        xt = self._solve()
        self.xold2, self.xold1 = self.xold1, self.x.copy()
        return xt

    def approximations(self, x):
        """Values of the current approximations f~0, f~ (m,) at x."""
        ux, xl = self.upp - x, x - self.low
        f0a = self._r0 + (self._p0 / ux + self._q0 / xl).sum()
        fa = self._r + (self._P / ux + self._Q / xl).sum(axis=1)
        return float(f0a), fa

    def _offending(self, f0_new, f_new):
        f0a, fa = self.approximations(self.x_trial)
        bad0 = f0_new > f0a + 0.5 * self.eps
        bad = (f_new > fa + 0.5 * self.eps) & (f_new > self.check_below)
        return bad0, bad, f0a, fa

    def conservative(self, f0_new, f_new):
        """True when the approximations at the trial point bound the true values (always True
        for plain MMA)."""
        if not self.conservative_mode:
            return True
        bad0, bad, _, _ = self._offending(f0_new, np.asarray(f_new, float))
        return not (bad0 or bad.any())

    def tighten(self, f0_new, f_new):
        """GCMMA inner iteration: raise rho of the non-conservative functions (Svanberg 2007,
        eq. 4.6) and solve the subproblem again; return the new trial point."""
        f_new = np.asarray(f_new, float)
        bad0, bad, f0a, fa = self._offending(f0_new, f_new)
        xt = self.x_trial
        d = ((xt - self.x) ** 2 * (self.upp - self.low)
             / ((self.upp - xt) * (xt - self.low) * self._range)).sum()
        d = max(d, 1e-12)
        if bad0:
            self.rho0 = min(1.1 * (self.rho0 + (f0_new - f0a) / d), 10.0 * self.rho0)
        grow = np.minimum(1.1 * (self.rho + (f_new - fa) / d), 10.0 * self.rho)
        self.rho = np.where(bad, grow, self.rho)
        self.inner += 1
        return self._solve()
