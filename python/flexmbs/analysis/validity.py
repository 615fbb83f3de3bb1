"""Validity of a result, and the diagnosis of a failed simulation.

A converged Newton iteration only says that the discrete equations are solved; it does not say
that the answer lies where the model means anything. `check_result` (run by `simulate` after
every run, `validity=` setting) measures, vectorised over the stored states:

- **strain**: the largest axial strain Gamma_1 and the largest bending strain |kappa| c
  (curvature times the half-depth c of the section: d/2 of a circle or tube, h/2 of a
  rectangle) of every beam element, measured from the reference configuration. Gamma_1 is
  taken where the element computes its axial force (the reduced-integration Gauss points;
  extrapolated to the nodes it carries the interpolation error of cos(phi) x'), the curvature
  phi' at the element's two ends (it is constant along a 2-node element and linear along a
  3-node one, so the ends are its extremes; the quadratic element represents the curvature
  P (L - s) / EI of a tip-loaded cantilever exactly). The
  material law N = EA Gamma_1, M = EI kappa is linear elastic; its range is limited by the
  material and by the strain measure itself: the Biot strain used here and the Green-Lagrange
  strain differ by Gamma^2 / 2, i.e. the stress of "the" linear law is ambiguous by Gamma / 2
  (0.5 % at 1 % strain, 5 % at 10 %), and every structural metal has yielded long before 1 %
  (yield strains 0.1-0.5 %). Defaults: a ValidityWarning above 1 %, InvalidResultError above
  10 % (ValidityLimits.strain_warn / strain_fail). Beams with a GivenSection (no material,
  no depth) are not checked, and the check says so.
- **constraint drift**: the largest |Phi(q, t)| of every constraint row over the stored states,
  against max(drift_warn, 1000 tol) qscale (warning) and drift_fail qscale (error), qscale =
  max(1, max|q_ref|, longest element) as in the core's convergence test.
- **energy** of free systems (no drive or prescribed motion, no time-varying load: every force
  is conservative and the joints do no work): T + U + V must not grow; generalized-alpha only
  dissipates (Chung & Hulbert 1993), so a growth above energy_warn (energy_fail) of the largest
  T + U is a warning (an error). Dampers and the beams' material damping (Kelvin–Voigt,
  flexmbs.Material) only remove energy, so the check holds, unchanged, for damped models
  (tests/test_damping.py).

Each check needs the coordinates it reads: with `store=` a subset, what is not stored is not
checked and the check's note says so.

`diagnose_failure` explains a failed run: redundant constraints (rank of the constraint Jacobian
Phi_q, by SVD), a direction that is neither held nor stiff (null space of the stiffness, or of
stiffness plus mass, on the null space of Phi_q), or an input so large that the residual
overflows.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from flexmbs.core import Status, system_matrices
from flexmbs.errors import InvalidResultError, ModelError, ValidityWarning
from flexmbs.model.constraints import constraint_jacobian, constraint_values_t, row_table
from flexmbs.resources import CHUNK_VALUES
from flexmbs.responses.strain import columns as _columns
from flexmbs.responses.strain import (element_groups, gauss_points, half_depth,
                                      raw_curvature_t, raw_strains, raw_strains_t, shape)

__all__ = ["ValidityLimits", "Check", "Validity", "check_result", "apply_validity",
           "redundant_constraints", "free_directions", "overflowing_inputs", "diagnose_failure",
           "OVERFLOW_LIMIT"]

#: Inputs at or above this magnitude overflow the residual: sqrt of the largest double
#: (1.8e308), so the product of two such quantities (force x displacement, stiffness x strain x
#: rotation in the element forces) is not representable.
OVERFLOW_LIMIT = math.sqrt(np.finfo(float).max)

_MODES = ("warn", "error", "off")


@dataclass(frozen=True)
class ValidityLimits:
    """Settings of the validity checks (SimulationSettings.validity; a case's [solver]
    validity keys).

    mode : 'warn' (default: ValidityWarning above the warning limits, InvalidResultError above
        the failure limits), 'error' (InvalidResultError above the warning limits too) or 'off'.
    strain_warn, strain_fail : strains (-), default 1 % and 10 %.
    drift_warn, drift_fail : constraint violation relative to qscale, default 1e-6 and 1e-3.
    energy_warn, energy_fail : energy growth of a free system relative to its largest
        kinetic plus strain energy, default 1 % and 10 %.
    """
    mode: str = "warn"
    strain_warn: float = 0.01
    strain_fail: float = 0.10
    drift_warn: float = 1e-6
    drift_fail: float = 1e-3
    energy_warn: float = 0.01
    energy_fail: float = 0.10

    def __post_init__(self):
        if self.mode not in _MODES:
            raise ModelError(f"validity mode must be one of {_MODES}, got {self.mode!r}")
        for a, b in (("strain_warn", "strain_fail"), ("drift_warn", "drift_fail"),
                     ("energy_warn", "energy_fail")):
            va, vb = getattr(self, a), getattr(self, b)
            for name, v in ((a, va), (b, vb)):
                if not (isinstance(v, (int, float, np.floating)) and not isinstance(v, bool)
                        and math.isfinite(v) and v > 0):
                    raise ModelError(f"ValidityLimits.{name} must be a positive finite number, "
                                     f"got {v!r}")
            if va > vb:
                raise ModelError(f"ValidityLimits.{a} = {va!r} is above {b} = {vb!r}")

    @classmethod
    def coerce(cls, value):
        """ValidityLimits from simulate's `validity` argument (a mode string or an instance)."""
        if isinstance(value, cls):
            return value
        if isinstance(value, str) and value in _MODES:
            return cls(mode=value)
        raise ModelError(f"validity must be 'warn', 'error', 'off' or a ValidityLimits, "
                         f"got {value!r}")


@dataclass
class Check:
    """One validity check: status 'ok', 'warn', 'fail' or 'skipped'."""
    name: str
    status: str
    value: float | None = None
    warn_limit: float | None = None
    fail_limit: float | None = None
    where: str = ""
    note: str = ""

    def line(self):
        v = "-" if self.value is None else f"{self.value:.3g}"
        lim = "" if self.warn_limit is None else f" (warn > {self.warn_limit:.3g}, fail > {self.fail_limit:.3g})"
        extra = "; ".join(s for s in (self.where, self.note) if s)
        return f"{self.name}: {self.status}, {v}{lim}" + (f"; {extra}" if extra else "")


@dataclass
class Validity:
    """The validity checks of a Result (result.validity)."""
    checks: list = field(default_factory=list)
    mode: str = "warn"

    def __getitem__(self, name):
        for c in self.checks:
            if c.name == name:
                return c
        raise KeyError(f"no validity check {name!r}; checks are {[c.name for c in self.checks]}")

    @property
    def failures(self):
        return [c for c in self.checks if c.status == "fail"]

    @property
    def warnings(self):
        return [c for c in self.checks if c.status == "warn"]

    @property
    def ok(self):
        return not self.failures and not self.warnings

    def __str__(self):
        return "\n".join(c.line() for c in self.checks)


def _grade(value, warn, fail):
    if not math.isfinite(value) or value > fail:
        return "fail"
    return "warn" if value > warn else "ok"




def _chunks(nt, width):
    """Slices of the time points such that a (chunk, width) array holds <= CHUNK_VALUES values."""
    step = max(1, int(CHUNK_VALUES // max(width, 1)))
    for j0 in range(0, nt, step):
        yield slice(j0, min(nt, j0 + step))


def _element_info(model):
    """Per element: (body name, local index, half-depth or None, material or None)."""
    info = {}
    for b in model.bodies.values():
        if b.kind != "beam":
            continue
        for k, (e, sec) in enumerate(zip(b.elements, model.element_sections(b))):
            info[e] = (b.name, k, half_depth(sec) if b.material is not None else None)
    return info


def _strain_checks(model, cm, result, lim):
    einfo = _element_info(model)
    axial = (0.0, None)      # value, (element, time index)
    bend = (0.0, None)
    skipped_store, skipped_given = [], []
    for nen, (ids, edofs) in element_groups(cm).items():
        cols = _columns(result.dofs, edofs)
        stored = np.all(cols >= 0, axis=1)
        depth = np.array([np.nan if einfo.get(e, (None, None, None))[2] is None
                          else einfo[e][2] for e in ids])
        checked = stored & np.isfinite(depth)
        skipped_store += [int(e) for e in ids[~stored]]
        skipped_given += [int(e) for e in ids[stored & ~np.isfinite(depth)]]
        if not checked.any():
            continue
        ids, cols, depth = ids[checked], cols[checked], depth[checked]
        jac = 0.5 * cm.el_len[ids]
        # axial strain where the element computes N (its reduced-integration Gauss points);
        # curvature, linear along a 3-node element, at the element's ends (its extremes).
        # Time last (the element's coordinates of a chunk as rows of time points): numpy's
        # inner loops then run over the time points, not over 1-2 stations (measured on the
        # 2-core reference machine with the drift check: 6.9 -> 2.9 ms for a 1301-step run of the
        # 4-element robot, 68.7 -> 17.4 ms with 64 elements)
        xg = gauss_points(nen)
        ng, dng = shape(nen, xg)
        _, dnn = shape(nen, np.array([-1.0, 1.0]))
        qref = cm.qref[edofs[checked]][:, :, None]              # (nel, 3 nen, 1)
        r1 = raw_strains_t(qref, ng, dng, jac)[0]
        rk = raw_curvature_t(qref, dnn, jac)
        for sl in _chunks(len(result.t), result.q.shape[1] + 2 * cols.size):
            qe = np.ascontiguousarray(result.q[sl].T)[cols]     # (nel, 3 nen, chunk)
            e1 = raw_strains_t(qe, ng, dng, jac)[0]
            a = np.abs(e1 - r1).max(axis=1)                     # (nel, chunk)
            b = np.abs(raw_curvature_t(qe, dnn, jac) - rk).max(axis=1) * depth[:, None]
            for arr, which in ((a, "axial"), (b, "bend")):
                arr = np.where(np.isfinite(arr), arr, np.inf)
                k, j = np.unravel_index(np.argmax(arr), arr.shape)
                v = float(arr[k, j])
                cur = axial if which == "axial" else bend
                if v > cur[0] or (cur[1] is None and v >= cur[0]):
                    cur = (v, (int(ids[k]), sl.start + int(j)))
                if which == "axial":
                    axial = cur
                else:
                    bend = cur
    notes = []
    if skipped_store:
        notes.append(f"{len(skipped_store)} element(s) not checked: their coordinates were not "
                     "stored (store=)")
    if skipped_given:
        notes.append(f"{len(skipped_given)} element(s) not checked: GivenSection beams have no "
                     "material and no section depth")
    note = "; ".join(notes)
    checks = []
    for name, (v, loc) in (("axial strain", axial), ("bending strain", bend)):
        if loc is None:
            checks.append(Check(name, "skipped", note=note or "no beam elements"))
            continue
        e, j = loc
        body, k, _ = einfo[e]
        where = f"element {e} (element {k} of beam '{body}') at t = {result.t[j]:.6g} s"
        checks.append(Check(name, _grade(v, lim.strain_warn, lim.strain_fail), v,
                            lim.strain_warn, lim.strain_fail, where, note))
    return checks


def _qscale(cm):
    s = max(1.0, float(np.abs(cm.qref).max()) if cm.qref.size else 1.0)
    if cm.nel:
        s = max(s, float(cm.el_len[:cm.nel].max()))
    return s


def _drift_check(model, cm, result, lim, law_val, tol):
    if cm.nc == 0:
        return Check("constraint drift", "skipped", note="the model has no constraints")
    used = cm.c_dofs[:, :cm.nc].astype(np.int64) - 1
    cols = _columns(result.dofs, np.where(used >= 0, used, 0))
    rows = np.where(np.all((cols >= 0) | (used < 0), axis=0))[0]
    if rows.size == 0:
        return Check("constraint drift", "skipped",
                     note="no constraint has all its coordinates stored (store=)")
    lv = np.asarray(law_val)[:, :len(result.t)] if law_val is not None else None
    worst, j, k = -1.0, 0, 0
    table = row_table(cm)
    for sl in _chunks(len(result.t), 2 * cm.ndof + 6 * cm.nc):
        qfull = np.zeros((cm.ndof, sl.stop - sl.start))            # time last (constraints.py)
        qfull[result.dofs] = result.q[sl].T
        phi = np.abs(constraint_values_t(table, qfull, None if lv is None else lv[:, sl]))[rows]
        phi = np.where(np.isfinite(phi), phi, np.inf)
        jj, kk = np.unravel_index(np.argmax(phi.T), phi.T.shape)   # earliest time first
        if phi[kk, jj] > worst:
            worst, j, k = float(phi[kk, jj]), sl.start + int(jj), int(kk)
    qs = _qscale(cm)
    warn = max(lim.drift_warn, 1e3 * tol) * qs
    fail = max(lim.drift_fail * qs, warn)
    note = "" if rows.size == cm.nc else f"{cm.nc - rows.size} row(s) not stored, not checked"
    return Check("constraint drift", _grade(worst, warn, fail), worst, warn,
                 fail, f"constraint '{model.row_label(int(rows[k]))}' at t = {result.t[j]:.6g} s",
                 note)


def _mass_blocks(nen, elen):
    """Consistent element mass pattern int N_a N_b ds (nel, nen, nen), exact (3-point Gauss)."""
    xg = np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)])
    wg = np.array([5 / 9, 8 / 9, 5 / 9])
    n, _ = shape(nen, xg)
    base = np.einsum("ak,bk,k->ab", n, n, wg)
    return 0.5 * elen[:, None, None] * base[None]


def _energy_check(model, cm, result, lim, props):
    name = "energy"
    if np.any(cm.c_law[:cm.nc] > 0) or np.any(cm.ld_law[:cm.nload] > 0):
        return Check(name, "skipped", note="not a free system: drives, prescribed motion or "
                     "time-varying loads do work")
    if len(result.dofs) != cm.ndof:
        return Check(name, "skipped", note="not all coordinates stored (store=)")
    q, qd = result.q, result.qd
    nt = q.shape[0]
    kin = np.zeros(nt)
    for sl in _chunks(nt, cm.ndof):
        kin[sl] = 0.5 * (qd[sl] * qd[sl]) @ cm.lumped
    strain = np.zeros(nt)
    fg = cm.lumped * cm.gacc
    for nen, (ids, edofs) in element_groups(cm).items():
        elen = cm.el_len[ids]
        mb = _mass_blocks(nen, elen)                            # (nel, nen, nen)
        rho_a, rho_i = props[3, ids], props[4, ids]
        for comp, rho in ((0, rho_a), (1, rho_a), (2, rho_i)):
            dd = edofs[:, comp::3]                              # (nel, nen)
            mw = mb * rho[:, None, None]
            np.add.at(fg, dd, np.einsum("eab,eb->ea", mw, cm.gacc[dd]))
            for sl in _chunks(nt, dd.size):
                v = qd[sl][:, dd]
                kin[sl] += 0.5 * np.einsum("tea,eab,teb->t", v, mw, v)
        # strain energy with the core's reduced integration (U whose gradient is f_int)
        xg = gauss_points(nen)
        wg = np.full(xg.size, 2.0 / xg.size)
        n, dn = shape(nen, xg)
        jac = 0.5 * elen
        r1, r2, rk = raw_strains(cm.qref[edofs], n, dn, jac)
        stiff = props[:3, ids]
        for sl in _chunks(nt, edofs.size * len(xg)):
            e1, e2, kap = raw_strains(q[sl][:, edofs], n, dn, jac)
            dens = (stiff[0][None, :, None] * (e1 - r1) ** 2 + stiff[1][None, :, None] * (e2 - r2) ** 2
                    + stiff[2][None, :, None] * (kap - rk) ** 2)
            strain[sl] += 0.5 * np.einsum("tek,k,e->t", dens, wg, jac)
    # spring-dampers: strain energy k (l - l0)^2 / 2, potential f0 l of the preload (the
    # damper only dissipates)
    pot_sd = np.zeros(nt)
    for k in range(cm.nsd):
        sd = cm.sd_dofs[:, k] - 1
        ks, _, l0, f0 = cm.sd_prop[:, k]
        ln = np.hypot(q[:, sd[2]] - q[:, sd[0]], q[:, sd[3]] - q[:, sd[1]])
        strain += 0.5 * ks * (ln - l0) ** 2
        pot_sd += f0 * (ln - ln[0])
    fext = fg.copy()
    np.add.at(fext, cm.ld_dof[:cm.nload] - 1, cm.ld_amp[:cm.nload])
    pot = np.zeros(nt)
    for sl in _chunks(nt, cm.ndof):
        pot[sl] = -((q[sl] - q[0]) @ fext)
    pot += pot_sd
    energy = kin + strain + pot
    scale = float(np.max(kin + strain))
    if not np.all(np.isfinite(energy)):
        return Check(name, "fail", math.inf, lim.energy_warn, lim.energy_fail,
                     note="non-finite energy")
    if scale <= 0.0:
        return Check(name, "ok", 0.0, lim.energy_warn, lim.energy_fail,
                     note="no motion and no strain")
    growth = (energy - energy[0]) / scale
    j = int(np.argmax(growth))
    return Check(name, _grade(max(float(growth[j]), 0.0), lim.energy_warn, lim.energy_fail),
                 max(float(growth[j]), 0.0), lim.energy_warn, lim.energy_fail,
                 f"largest growth at t = {result.t[j]:.6g} s",
                 "T + U + V relative to max(T + U); generalized-alpha never adds energy")


def check_result(model, result, limits=None, *, law_val=None, tol=1e-10, props=None):
    """The validity checks of `result` (a Validity); see the module docstring."""
    lim = ValidityLimits.coerce(limits if limits is not None else "warn")
    out = Validity(mode=lim.mode)
    if lim.mode == "off":
        return out
    cm = model.compile()
    props = model.element_properties() if props is None else np.asarray(props, float)
    if law_val is None:
        laws = model.laws()
        law_val = (np.array([law.tabulate(result.t)[0] for law in laws]) if laws
                   else np.zeros((1, len(result.t))))
    out.checks += _strain_checks(model, cm, result, lim)
    out.checks.append(_drift_check(model, cm, result, lim, law_val, tol))
    out.checks.append(_energy_check(model, cm, result, lim, props))
    return out


def apply_validity(validity, result=None):
    """Warn (ValidityWarning) or raise InvalidResultError as the mode says."""
    if validity.mode == "off":
        return
    bad = validity.failures + (validity.warnings if validity.mode == "error" else [])
    if bad:
        msg = "the simulation converged but its result is not valid: " + "; ".join(
            f"{c.name} {c.value:.3g} in {c.where} exceeds the limit "
            f"{c.fail_limit if c.status == 'fail' else c.warn_limit:.3g}" for c in bad)
        if any(c.name.endswith("strain") for c in bad):
            msg += (" (linear-elastic range; the loads or the section are far outside what this "
                    "model represents)")
        err = InvalidResultError(msg + "; set SimulationSettings(validity=...) (a case: "
                                 "[solver] validity and its limits) to change the limits")
        err.validity = validity
        err.result = result
        raise err
    for c in validity.warnings:
        warnings.warn(f"{c.name} {c.value:.3g} in {c.where} is above {c.warn_limit:.3g}"
                      + (f" ({c.note})" if c.note else ""), ValidityWarning, stacklevel=3)


# --------------------------------------------------------------------------- diagnosis
def redundant_constraints(model, q=None, rtol=1e-9):
    """Redundant constraint rows: [(row, [rows it repeats])], in model order.

    Rows are taken one by one; a row whose gradient lies (to rtol relative to its norm) in the
    span of the rows kept before it is redundant, and its combination names the rows it repeats
    (least squares on the kept rows, coefficients above rtol)."""
    cm = model.compile()
    if cm.nc == 0:
        return []
    q = cm.qref if q is None else np.asarray(q, float)
    jac = constraint_jacobian(cm, q)
    used = np.where(np.any(jac != 0.0, axis=0))[0]
    jac = jac[:, used]
    basis = np.zeros((0, jac.shape[1]))   # orthonormal rows
    kept = []
    out = []
    for r in range(cm.nc):
        g = jac[r]
        norm = np.linalg.norm(g)
        res = g - (basis @ g) @ basis if kept else g
        res = res - (basis @ res) @ basis if kept else res
        if norm == 0.0 or np.linalg.norm(res) <= rtol * norm:
            if kept:
                coef, *_ = np.linalg.lstsq(jac[kept].T, g, rcond=None)
                deps = [kept[i] for i in np.where(np.abs(coef) > 1e-6 * np.abs(coef).max())[0]]
            else:
                deps = []
            out.append((r, deps))
        else:
            basis = np.vstack([basis, res / np.linalg.norm(res)])
            kept.append(r)
    return out


_DIRS = ("x", "y", "rotation")


def free_directions(model, q=None, *, mass=False, rtol=1e-9, max_unknowns=3000):
    """Motions neither held by the constraints nor resisted by stiffness (nor by mass if
    `mass`): [(node, direction, body name)] of the largest component of each null vector of
    Z^T A Z, Z spanning the null space of Phi_q and A = K / |K| (+ M / |M|). None when the model
    is too large for this dense analysis (ndof > max_unknowns)."""
    cm = model.compile()
    if cm.ndof > max_unknowns:
        return None
    q = cm.qref if q is None else np.asarray(q, float)
    _, s = system_matrices(model, q)
    a = s[:cm.ndof, :cm.ndof]
    a = 0.5 * (a + a.T)
    a = a / max(np.abs(a).max(), 1e-300)
    if mass:
        _, sm = system_matrices(model, q, cm=1.0, ck=0.0)
        mm = sm[:cm.ndof, :cm.ndof]
        a = a + mm / max(np.abs(mm).max(), 1e-300)
    if cm.nc:
        jac = constraint_jacobian(cm, q)
        _, sv, vt = np.linalg.svd(jac)
        rank = int(np.sum(sv > rtol * max(sv.max(), 1e-300))) if sv.size else 0
        z = vt[rank:].T
    else:
        z = np.eye(cm.ndof)
    if z.shape[1] == 0:
        return []
    red = z.T @ a @ z
    w, v = np.linalg.eigh(0.5 * (red + red.T))
    scale = max(np.abs(w).max(), 1e-300)
    free = []
    owner = {n: b.name for b in model.bodies.values() for n in b.nodes}
    for i in np.where(np.abs(w) <= 1e-10 * scale)[0]:
        vec = z @ v[:, i]
        d = int(np.argmax(np.abs(vec)))
        free.append((d // 3, _DIRS[d % 3], owner.get(d // 3, "")))
    return free


def overflowing_inputs(model, law_val=None, props=None):
    """Inputs whose magnitude reaches OVERFLOW_LIMIT: [(description, value)]."""
    cm = model.compile()
    found = []
    for k in range(cm.nload):
        d = int(cm.ld_dof[k]) - 1
        amp = float(cm.ld_amp[k])
        scale = 1.0
        if cm.ld_law[k] > 0 and law_val is not None:
            scale = float(np.nanmax(np.abs(law_val[cm.ld_law[k] - 1])))
        what = ("moment" if d % 3 == 2 else "fx" if d % 3 == 0 else "fy")
        if not abs(amp * scale) < OVERFLOW_LIMIT:
            found.append((f"load {what} at node {d // 3}", amp * scale))
    for d in np.where(~(np.abs(cm.lumped) < OVERFLOW_LIMIT))[0]:
        found.append((f"point mass at node {d // 3}", float(cm.lumped[d])))
    g = np.asarray(model._gravity)
    if np.any(np.abs(g) > 0) and not (np.abs(g).max() * max(np.abs(cm.lumped).max(initial=0.0), 1.0)
                                      < OVERFLOW_LIMIT):
        found.append(("gravity", float(np.abs(g).max())))
    props = model.element_properties() if props is None else props
    names = ("EA", "kGA", "EI", "rhoA", "rhoI")
    for i, e in zip(*np.where(~(np.abs(props[:, :cm.nel]) < OVERFLOW_LIMIT))):
        found.append((f"{names[i]} of element {e}", float(props[i, e])))
    if law_val is not None:
        for i, law in enumerate(model.laws()):
            v = float(np.max(np.abs(law_val[i]))) if np.size(law_val[i]) else 0.0
            if not v < OVERFLOW_LIMIT:
                found.append((f"time law {getattr(law, 'name', '') or i + 1}", v))
    return found


def diagnose_failure(model, status, *, q=None, law_val=None, props=None):
    """A sentence explaining a failed run (status of the core), or '' if nothing is found:
    overflow of an input, redundant constraints, or a motion neither held nor stiff."""
    big = overflowing_inputs(model, law_val, props)
    if big:
        items = ", ".join(f"{w} = {v:.3g}" for w, v in big)
        return (f"overflow: {items} is so large that the residual overflows double precision "
                f"(inputs must stay below {OVERFLOW_LIMIT:.3g}, the square root of the largest "
                "double); check the units and the magnitude of that input")
    if status not in (2, 3, 4):
        return ""
    red = redundant_constraints(model, q)
    if red:
        parts = []
        for r, deps in red:
            dep = (" repeats " + ", ".join(f"row {d + 1} '{model.row_label(d)}'" for d in deps)
                   if deps else " has a zero gradient")
            parts.append(f"row {r + 1} '{model.row_label(r)}'{dep}")
        return ("over-constrained: redundant constraints (the constraint Jacobian has rank "
                f"{model.compile().nc - len(red)} for {model.compile().nc} rows): "
                + "; ".join(parts) + ". Remove the duplicate joint or constraint")
    free = free_directions(model, q, mass=(status != Status.STATIC_FAILED))
    if free:
        items = ", ".join(f"node {n} {d}" + (f" (body '{b}')" if b else "") for n, d, b in free[:6])
        more = f" and {len(free) - 6} more" if len(free) > 6 else ""
        what = "stiffness" if status == Status.STATIC_FAILED else "mass, stiffness"
        return (f"under-constrained: the mechanism is not held: {len(free)} free motion(s) "
                f"with no constraint and no {what}, largest at {items}{more}")
    if status == Status.STATIC_FAILED and free == []:
        cm = model.compile()
        loads = np.abs(cm.ld_amp[:cm.nload])
        big = (f" (largest load {loads.max():.3g} at node {(int(cm.ld_dof[np.argmax(loads)]) - 1) // 3})"
               if loads.size else "")
        return ("the constraints are independent and the structure is held (no free motion), "
                "so Newton's divergence points to loads beyond what the structure carries"
                f"{big}: check their magnitude")
    return ""
