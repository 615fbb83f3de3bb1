"""Constraint rows of a compiled model: values, Jacobian, time derivatives, acceleration terms.

The one place where the rows of eq. (1) are evaluated in Python (the Fortran core has its own
copy in fortran/constraints.f90). A row r of `Model.compile()` is one of

kind 1, linear
    Phi = sum_k coef_k q_{d_k} - c0 - lawcoef law(t)
kind 2, rigid link x (node j held in the frame of node i, offset (a, b) = coef[0:2])
    Phi = x_j - x_i - (cos(phi_i) a - sin(phi_i) b) - c0 - lawcoef law(t)
kind 3, rigid link y
    Phi = y_j - y_i - (sin(phi_i) a + cos(phi_i) b) - c0 - lawcoef law(t)

kind 4, prismatic (the component of x_b - x_a along a vector fixed in node a's frame,
e0 = coef[0:2] at phi_a = 0)
    Phi = (R(phi_a) e0) . (x_b - x_a) - c0 - lawcoef law(t)

with dofs d = (x_i, x_j, phi_i) for kind 2, (y_i, y_j, phi_i) for kind 3 and
(x_a, y_a, x_b, y_b, phi_a) for kind 4. Every function
takes states with any leading shape (..., ndof) and returns (..., nc), so a whole time history
is evaluated at once. The acceleration right-hand side is

    gamma = -(Phi_q qd)_q qd - 2 Phi_qt qd - Phi_tt,   so that   Phi_q qdd = gamma

(Phi_qt = 0 here: laws enter additively): a linear row gives gamma = lawcoef law''(t); a rigid
link x row gives -(cos a - sin b) phid_i^2 + lawcoef law'', a y row -(sin a + cos b) phid_i^2
+ lawcoef law''; a prismatic row, with e = R(phi_a) e0, e' = R(pi/2) e, d = x_b - x_a,
-(-e.d phid_a^2 + 2 phid_a e'.(xd_b - xd_a)) + lawcoef law''.

Examples
--------
>>> import numpy as np
>>> from flexmbs import Model, Circle, Material
>>> from flexmbs.model.constraints import constraint_values, law_tables
>>> m = Model()
>>> b = m.add_beam("b", (0, 0), (1, 0), 1, material=Material(7e10, 0.3, 2700), section=Circle(0.01))
>>> m.pin(b.first)
>>> cm = m.compile()
>>> val, rate, acc = law_tables(m, [0.0])
>>> constraint_values(cm, cm.qref, val[:, 0]).tolist()
[0.0, 0.0]
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["RowTable", "row_table", "law_tables", "drive_terms", "constraint_values",
           "constraint_values_t", "jacobian_entries", "constraint_jacobian", "constraint_rate",
           "acceleration_rhs"]

KIND_LINEAR, KIND_RIGID_X, KIND_RIGID_Y, KIND_PRISMATIC = 1, 2, 3, 4
_KINDS = (KIND_LINEAR, KIND_RIGID_X, KIND_RIGID_Y, KIND_PRISMATIC)
#: coordinates per row at most (MAX_CDOF of fortran/constraints.f90)
MAX_CDOF = 5


@dataclass(frozen=True)
class RowTable:
    """The constraint rows of a compiled model as 0-based arrays.

    kind (nc,); dofs (nc, MAX_CDOF) 0-based, -1 where unused; coef (nc, MAX_CDOF); c0 (nc,);
    law (nc,) 0-based law index, -1 for none; lawcoef (nc,); ndof.
    """
    kind: np.ndarray
    dofs: np.ndarray
    coef: np.ndarray
    c0: np.ndarray
    law: np.ndarray
    lawcoef: np.ndarray
    ndof: int

    @property
    def nc(self):
        return self.kind.size


def row_table(cm):
    """RowTable of a CompiledModel (checks that every row kind is known)."""
    nc = cm.nc
    kind = np.asarray(cm.c_kind[:nc], np.int64)
    bad = ~np.isin(kind, _KINDS)
    if np.any(bad):
        r = int(np.flatnonzero(bad)[0])
        raise ModelError(f"constraint row {r} has kind {int(kind[r])}; known kinds are {_KINDS}")
    return RowTable(kind=kind,
                    dofs=np.asarray(cm.c_dofs[:, :nc], np.int64).T - 1,
                    coef=np.asarray(cm.c_coef[:, :nc], float).T.copy(),
                    c0=np.asarray(cm.c_c0[:nc], float).copy(),
                    law=np.asarray(cm.c_law[:nc], np.int64) - 1,
                    lawcoef=np.asarray(cm.c_lawcoef[:nc], float).copy(),
                    ndof=int(cm.ndof))


def _rows(cm_or_rows):
    return cm_or_rows if isinstance(cm_or_rows, RowTable) else row_table(cm_or_rows)


def law_tables(model, t):
    """(value, rate, accel) of every time law of `model` on the times t: each (nlaw, nt)."""
    t = np.atleast_1d(np.asarray(t, float))
    laws = model.laws()
    if not laws:
        z = np.zeros((0, t.size))
        return z, z.copy(), z.copy()
    tab = [law.evaluate(t) for law in laws]
    return tuple(np.array([x[k] for x in tab]) for k in range(3))


def drive_terms(cm, law_table):
    """lawcoef * law of every row, (..., nc) from a law table (nlaw, ...) (value, rate or
    acceleration); None or an empty table: no driven rows allowed."""
    rows = _rows(cm)
    has = rows.law >= 0
    if law_table is None or np.size(law_table) == 0:
        if np.any(has):
            raise ModelError("constraint rows are driven by time laws, but no law values were given")
        if law_table is None:
            return 0.0
        return np.zeros(np.shape(law_table)[1:] + (rows.nc,))      # no laws: (..., nc) zeros
    lt = np.asarray(law_table, float)
    vals = np.moveaxis(lt[np.where(has, rows.law, 0)], 0, -1)       # (..., nc)
    return np.where(has, rows.lawcoef, 0.0) * vals


def _angle_terms(rows, q):
    """cos(phi) a - sin(phi) b and sin(phi) a + cos(phi) b for every row, (..., nc), with phi
    the row's angle (phi_i of a rigid link, phi_a of a prismatic row) and (a, b) = coef[0:2]
    (zero on linear rows)."""
    rigid = rows.kind != KIND_LINEAR
    col = np.where(rows.kind == KIND_PRISMATIC, 4, 2)
    ph = q[..., np.where(rigid, rows.dofs[np.arange(rows.nc), col], 0)]
    c, s = np.cos(ph), np.sin(ph)
    a = np.where(rigid, rows.coef[:, 0], 0.0)
    b = np.where(rigid, rows.coef[:, 1], 0.0)
    return c * a - s * b, s * a + c * b


def constraint_values_t(cm, qt, law_val):
    """constraint_values on time-last arrays: qt (ndof, T) states as columns, law_val (nlaw, T)
    or None -> Phi (nc, T). The states last make numpy's inner loops run over them instead of
    over a row's 4 coordinates, and the rotations are evaluated only when a row turns (the
    drift check of a 1301-step robot run took 1.7 ms on the 2-core reference machine)."""
    rows = _rows(cm)
    used = rows.dofs >= 0
    qd = qt[np.where(used, rows.dofs, 0)]                             # (nc, 4, T)
    val = np.sum(np.where(used, rows.coef, 0.0)[:, :, None] * qd, axis=1)
    turning = rows.kind != KIND_LINEAR
    if np.any(turning):
        rx, ry = _angle_terms(rows, qt.T)
        rx, ry = rx.T, ry.T                                           # (nc, T)
        rigid = qd[:, 1] - qd[:, 0] - np.where((rows.kind == KIND_RIGID_X)[:, None], rx, ry)
        prism = rx * (qd[:, 2] - qd[:, 0]) + ry * (qd[:, 3] - qd[:, 1])
        val = np.where(turning[:, None], np.where((rows.kind == KIND_PRISMATIC)[:, None],
                                                  prism, rigid), val)
    return val - rows.c0[:, None] - np.asarray(drive_terms(rows, law_val)).T


def constraint_values(cm, q, law_val):
    """Phi (..., nc) of every row at states q (..., ndof); law_val (nlaw, ...): the law values
    at the same times (None when no row is driven)."""
    rows = _rows(cm)
    q = np.asarray(q, float)
    lead = q.shape[:-1]
    qt = np.ascontiguousarray(q.reshape(-1, q.shape[-1]).T)           # (ndof, T)
    if law_val is not None:
        law_val = np.asarray(law_val, float)
        law_val = law_val.reshape((law_val.shape[0], qt.shape[1]))
    return constraint_values_t(rows, qt, law_val).T.reshape(lead + (rows.nc,))


def jacobian_entries(cm, q):
    """Phi_q as triplets: rows (nnz,), cols (nnz,), vals (..., nnz) at states q (..., ndof).

    Entries repeat when a row names a coordinate twice (sum them)."""
    rows = _rows(cm)
    q = np.asarray(q, float)
    lin = rows.kind == KIND_LINEAR
    prism = rows.kind == KIND_PRISMATIC
    link = np.zeros(rows.dofs.shape[1])
    link[:2] = -1.0, 1.0
    base = np.where(lin[:, None], rows.coef, link)
    rx, ry = _angle_terms(rows, q)
    dphi = np.where(rows.kind == KIND_RIGID_X, ry, -rx)             # dPhi/dphi_i, (..., nc)
    vals = np.broadcast_to(base, q.shape[:-1] + base.shape).copy()
    vals[..., 2] = np.where(lin, vals[..., 2], dphi)
    if np.any(prism):
        # (-e, e, e'.d), e = (rx, ry), e' = (-ry, rx), d = x_b - x_a
        d = np.where(rows.dofs >= 0, rows.dofs, 0)
        qd = q[..., d]
        dx, dy = qd[..., 2] - qd[..., 0], qd[..., 3] - qd[..., 1]
        for k, v in enumerate((-rx, -ry, rx, ry, -ry * dx + rx * dy)):
            vals[..., k] = np.where(prism, v, vals[..., k])
    valid = rows.dofs >= 0
    r_idx, k_idx = np.nonzero(valid)
    return r_idx, rows.dofs[r_idx, k_idx], vals[..., r_idx, k_idx]


def constraint_jacobian(cm, q, sparse=False):
    """Phi_q (nc, ndof) at one state q (ndof,): a dense array, or a scipy CSR matrix."""
    rows = _rows(cm)
    q = np.asarray(q, float)
    if q.shape != (rows.ndof,):
        raise ModelError(f"q must have shape ({rows.ndof},), got {q.shape}")
    r, c, v = jacobian_entries(rows, q)
    if sparse:
        from scipy.sparse import csr_matrix
        return csr_matrix((v, (r, c)), shape=(rows.nc, rows.ndof))
    jac = np.zeros((rows.nc, rows.ndof))
    np.add.at(jac, (r, c), v)
    return jac


def constraint_rate(cm, law_rate):
    """Phi_t (..., nc) from the law rates (nlaw, ...)."""
    return -drive_terms(cm, law_rate)


def acceleration_rhs(cm, q, qd, law_acc):
    """gamma (..., nc) = -(Phi_q qd)_q qd - 2 Phi_qt qd - Phi_tt at states q, qd (..., ndof),
    law accelerations (nlaw, ...); Phi_q qdd = gamma on the acceleration level."""
    rows = _rows(cm)
    q = np.asarray(q, float)
    qd = np.asarray(qd, float)
    rigid = rows.kind != KIND_LINEAR
    prism = rows.kind == KIND_PRISMATIC
    rx, ry = _angle_terms(rows, q)
    col = np.where(prism, 4, 2)
    w = qd[..., np.where(rigid, rows.dofs[np.arange(rows.nc), col], 0)]
    quad = np.where(rows.kind == KIND_RIGID_X, rx, ry) * w * w
    if np.any(prism):
        # qd^T Phi_qq qd = -e.d w^2 + 2 w e'.(v_b - v_a)
        d = np.where(rows.dofs >= 0, rows.dofs, 0)
        qv, vv = q[..., d], qd[..., d]
        ed = rx * (qv[..., 2] - qv[..., 0]) + ry * (qv[..., 3] - qv[..., 1])
        epv = -ry * (vv[..., 2] - vv[..., 0]) + rx * (vv[..., 3] - vv[..., 1])
        quad = np.where(prism, -ed * w * w + 2.0 * w * epv, quad)
    return np.where(rigid, -quad, 0.0) + drive_terms(rows, law_acc)
