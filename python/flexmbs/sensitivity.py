"""Design sensitivities of a case's time responses: direct differentiation or finite differences.

The paper (section 5.2) uses forward finite differences, one extra simulation per
design variable. flexmbs differentiates the discrete generalized-alpha equations
directly in Fortran (fortran/generalized_alpha.f90, `sens_step`): after each
converged step, the factored iteration matrix is solved for the n_v right-hand
sides, so every time response gets its exact derivative for a fraction of a
simulation. The chain rule then carries dq/dp to the deviation measures
(28), (30), (33) of the case, and the beam mass has an analytic gradient.

Both methods share one interface, `case_gradients(case, design, method=...)`:
- 'direct'  : direct differentiation (default, exact to solver precision);
- 'forward' : forward differences with a relative step (the paper's method);
- 'central' : central differences (a check, twice the cost).
`check_sensitivity` compares 'direct' with central differences along a random
direction, over a range of steps, as users of a derivative code expect. A check that
does not depend on the accuracy of finite differences is the Taylor test,
`flexmbs.checks.taylor_test` (tests/test_sensitivity.py applies it to every response).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from flexmbs.errors import CaseError, ModelError
from flexmbs.sections import real_number
from flexmbs.simulate import simulate

__all__ = ["CaseGradients", "case_gradients", "check_sensitivity", "SensitivityCheck", "METHODS"]

METHODS = ("direct", "forward", "central")


@dataclass
class CaseGradients:
    """Responses of one design and their derivatives (design variables in mm).

    Attributes
    ----------
    design_mm : (nv,) design.
    t : (nt,) time grid.
    deviation : (nt,) deviation history (m).
    d_deviation : (nt, nv) its derivatives (m/mm).
    mass : beam mass (kg); d_mass : (nv,) its gradient (kg/mm).
    max_deviation, t_at_max, step_at_max : the maximum of the history (index 0-based).
    d_max_deviation : (nv,) derivative of the deviation at the step of the maximum (m/mm).
    method : 'direct', 'forward' or 'central'.
    simulations : simulations run (1 for direct).
    wall_time : seconds.
    """
    design_mm: np.ndarray
    t: np.ndarray
    deviation: np.ndarray
    d_deviation: np.ndarray
    mass: float
    d_mass: np.ndarray
    method: str
    simulations: int
    wall_time: float
    stats: dict = field(default_factory=dict)

    @property
    def step_at_max(self):
        return int(np.argmax(self.deviation))

    @property
    def max_deviation(self):
        return float(self.deviation[self.step_at_max])

    @property
    def t_at_max(self):
        return float(self.t[self.step_at_max])

    @property
    def d_max_deviation(self):
        return self.d_deviation[self.step_at_max].copy()


def _case_and_design(case, design_mm, what):
    """(Case, design array): a case name/path/dict is loaded; the design is a flat sequence of
    nv positive finite numbers (mm)."""
    from flexmbs.cases import as_case

    case = as_case(case, f"{what}: case")
    try:
        p = case._design(design_mm)
    except CaseError as exc:
        raise ModelError(f"{what}: design must have {len(case.design_names)} finite values "
                         f"({', '.join(case.design_names)}), got {design_mm!r}: {exc}") from None
    return case, p


def _case_settings(case, overrides):
    kw = dict(h=case.h, rho_inf=case.rho_inf, start=case.start_mode)
    kw.update(overrides)
    return kw


def _sensor_deviation(case, design, t_end, with_derivatives, sim_kw):
    """One simulation of `design`: deviation history (and its design derivatives)."""
    design = np.asarray(design, float)
    model = case.build_model(design)
    dofs = np.asarray(case.sensor_dofs, int)
    kw = dict(store=sorted({int(d) // 3 for d in dofs}))
    if with_derivatives:
        kw.update(design_derivatives=case.element_property_derivatives(design), sensitivity_dofs=dofs)
    r = simulate(model, t_end, **kw, **sim_kw)
    qs = r.coordinates(dofs)
    dev, jac = case.deviation_from_sensors(qs, t=r.t)
    ddev = None
    if with_derivatives:
        # r.dq columns follow sorted sensitivity dofs; reorder to case.sensor_dofs
        order = np.searchsorted(r.sens_dofs, dofs)
        ddev = np.einsum("ts,tsv->tv", jac, r.dq[:, order, :])
    return r, dev, ddev


def case_gradients(case, design_mm, method="direct", fd_step=1e-6, **simulate_kw):
    """Deviation history, beam mass and their design derivatives for one design.

    Parameters
    ----------
    case : flexmbs.cases.Case
    design_mm : sequence of float
        Design variables (mm).
    method : {'direct', 'forward', 'central'}, default 'direct'
        Direct differentiation, or finite differences (one / two extra simulations
        per variable).
    fd_step : float, default 1e-6
        Relative step of the finite differences (absolute step fd_step * |p_i| mm).
        CASES.md: the late time steps of the robot are vibration samples, and a
        1e-3 relative step is 2.5-13 % wrong there; 1e-6 is accurate.
    **simulate_kw
        Overrides of the case's simulation settings (h, rho_inf, start, solver, ...);
        `t_end` overrides the case's horizon.

    Returns
    -------
    CaseGradients
    """
    if not isinstance(method, str) or method not in METHODS:
        raise ModelError(f"method must be one of {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    case, p = _case_and_design(case, design_mm, "case_gradients")
    if method != "direct" and not (0 < real_number("fd_step", fd_step) < 1):
        raise ModelError(f"fd_step must lie in (0, 1), got {fd_step!r}")
    t_end = simulate_kw.pop("t_end", case.t_end)
    sim_kw = _case_settings(case, simulate_kw)
    nv = p.size
    if method == "direct":
        r, dev, ddev = _sensor_deviation(case, p, t_end, True, sim_kw)
        nsim = 1
    else:
        if not (0 < fd_step < 1):
            raise ModelError(f"fd_step must lie in (0, 1), got {fd_step!r}")
        r, dev, _ = _sensor_deviation(case, p, t_end, False, sim_kw)
        ddev = np.zeros((dev.size, nv))
        nsim = 1
        for i in range(nv):
            dp = fd_step * max(abs(p[i]), 1.0)
            e = np.zeros(nv)
            e[i] = dp
            _, dplus, _ = _sensor_deviation(case, p + e, t_end, False, sim_kw)
            nsim += 1
            if method == "forward":
                ddev[:, i] = (dplus - dev) / dp
            else:
                _, dminus, _ = _sensor_deviation(case, p - e, t_end, False, sim_kw)
                nsim += 1
                ddev[:, i] = (dplus - dminus) / (2 * dp)
    return CaseGradients(design_mm=p, t=r.t, deviation=dev, d_deviation=ddev,
                         mass=float(case.mass(p)), d_mass=np.asarray(case.mass_gradient(p), float),
                         method=method, simulations=nsim, wall_time=time.perf_counter() - t0,
                         stats=r.stats)


@dataclass
class SensitivityCheck:
    """Direct derivatives against central differences along one direction.

    rows: list of (step_mm, max relative error over the checked steps) for each FD step;
    direct: (nt,) directional derivative of the deviation history (direct differentiation);
    best_error: the smallest error over the step study; direction: unit vector used.
    """
    direction: np.ndarray
    direct: np.ndarray
    rows: list
    checked_steps: np.ndarray

    @property
    def best_error(self):
        return min(err for _, err in self.rows)

    def table(self):
        """The step study as text."""
        lines = ["  FD step (mm)   max rel. error (direct vs central)"]
        lines += [f"  {h:12.3e}   {e:10.3e}" for h, e in self.rows]
        return "\n".join(lines)


def check_sensitivity(case, design_mm, direction=None, steps=(1e-2, 1e-3, 1e-4, 1e-5, 1e-6),
                      seed=0, time_steps=None, **simulate_kw):
    """Check direct-differentiation derivatives against central differences.

    The deviation history's derivative along `direction` (default: a random unit
    vector from `seed`) by direct differentiation is compared with central
    differences of step s * direction (mm) for every s in `steps`; the error at
    each s is max over the checked time steps of |direct - FD| / max|FD|. A good
    derivative code shows the FD error first falling like s^2 (truncation), then
    rising like eps/s (round-off and solver tolerance), with the smallest error
    near 1e-6 or below.
    """
    case, p = _case_and_design(case, design_mm, "check_sensitivity")
    rng = np.random.default_rng(seed)
    if direction is None:
        d = rng.standard_normal(p.size)
    else:
        try:
            d = np.asarray(direction, float)
        except (TypeError, ValueError):
            d = None
        if d is None or d.shape != p.shape or not np.all(np.isfinite(d)) or not np.any(d):
            raise ModelError(f"check_sensitivity: direction must be {p.size} finite numbers, not "
                             f"all zero, got {direction!r}")
    d = d / np.linalg.norm(d)
    if isinstance(steps, (str, bytes)) or np.ndim(steps) != 1 or len(steps) == 0:
        raise ModelError(f"check_sensitivity: steps must be a list of positive numbers (mm), "
                         f"got {steps!r}")
    steps = [real_number("check_sensitivity: steps", s, positive=True) for s in steps]
    t_end = simulate_kw.pop("t_end", case.t_end)
    sim_kw = _case_settings(case, simulate_kw)
    _, _, ddev = _sensor_deviation(case, p, t_end, True, sim_kw)
    direct = ddev @ d
    if time_steps is None:
        idx = np.arange(direct.size)
    else:
        idx = np.asarray(time_steps)
        if idx.ndim != 1 or idx.size == 0 or idx.dtype.kind not in "iu" \
                or idx.min() < -direct.size or idx.max() >= direct.size:
            raise ModelError(f"check_sensitivity: time_steps must be step indices in "
                             f"[0, {direct.size}), got {time_steps!r}")
    rows = []
    for s in steps:
        _, dp, _ = _sensor_deviation(case, p + s * d, t_end, False, sim_kw)
        _, dm, _ = _sensor_deviation(case, p - s * d, t_end, False, sim_kw)
        fd = (dp - dm) / (2 * s)
        scale = max(np.max(np.abs(fd[idx])), 1e-300)
        rows.append((float(s), float(np.max(np.abs(direct[idx] - fd[idx])) / scale)))
    return SensitivityCheck(direction=d, direct=direct, rows=rows, checked_steps=idx)
