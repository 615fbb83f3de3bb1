"""Strain kinematics of the beam elements, shared by the stress response and the validity checks.

The element (fortran/beam2d.f90) interpolates x, y and phi of its 2 or 3 nodes with Lagrange
shape functions on xi in [-1, 1] (arc length s = (xi + 1) L / 2) and measures, with
c = cos(phi), s = sin(phi) of the interpolated rotation and x' = dx/ds,

    e1 = c x' + s y',    e2 = -s x' + c y',    kappa = phi',

from their values in the reference configuration: Gamma_1 = e1 - e1_ref (axial),
Gamma_2 = e2 - e2_ref (shear), kappa - kappa_ref (curvature). The stress resultants
N = EA Gamma_1, Q = kGA Gamma_2, M = EI kappa are evaluated at the reduced-integration Gauss
points (1 for 2 nodes, 2 for 3 nodes): those are the element's own stations.
This module is the one Python copy of these formulas (flexmbs.analysis.validity imports it).
"""
from __future__ import annotations

import math

import numpy as np

from flexmbs.model.sections import Circle, Rectangle, Tube

__all__ = ["shape", "raw_strains", "raw_strains_t", "raw_curvature_t", "raw_strain_derivatives",
           "gauss_points", "element_groups", "columns", "half_depth"]


def half_depth(section):
    """Distance c of the extreme fibre from the neutral axis: d/2 of a Circle or Tube, h/2 of a
    Rectangle; None for a section without a depth (GivenSection)."""
    if isinstance(section, (Circle, Tube)):
        return 0.5 * section.d
    if isinstance(section, Rectangle):
        return 0.5 * section.h
    return None


def shape(nen, xi):
    """Shape functions N (nen, npt) and dN/dxi (nen, npt) of a 2- or 3-node element at xi."""
    xi = np.asarray(xi, float)
    if nen == 2:
        return np.stack([0.5 * (1 - xi), 0.5 * (1 + xi)]), np.stack([-0.5 + 0 * xi, 0.5 + 0 * xi])
    return (np.stack([0.5 * xi * (xi - 1), 1 - xi * xi, 0.5 * xi * (xi + 1)]),
            np.stack([xi - 0.5, -2 * xi, xi + 0.5]))


def gauss_points(nen):
    """The stations xi where the element evaluates its strains (reduced Gauss integration)."""
    return np.array([0.0]) if nen == 2 else np.array([-1.0, 1.0]) / math.sqrt(3.0)


def _time_last(qe):
    """(nel, 3 nen, T) contiguous copy of qe (..., nel, 3 nen), the leading axes flattened into
    T and put last: the sums over an element's nodes then run over rows of T values. With the
    leading axes first, numpy's innermost loop had npt (1 or 2) values: raw_strains took
    1.6 ms for the robot's 4 elements x 1301 time points, a simulation's validity check 4.4 ms
    of its 18 (2-core reference machine)."""
    nel, m = qe.shape[-2:]
    return np.ascontiguousarray(np.moveaxis(qe.reshape((-1, nel, m)), 0, -1))


def _leading_first(v, lead):
    """(nel, npt, T) -> (..., nel, npt) with the leading shape `lead` (a view)."""
    return np.moveaxis(v, -1, 0).reshape(tuple(lead) + v.shape[:2])


def _along(q, comp, w):
    """sum_a w[:, a, :] q[:, 3 a + comp, :] over an element's nodes a: (nel, npt, T)."""
    return sum(q[:, 3 * a + comp, None, :] * w[:, a, :, None] for a in range(w.shape[1]))


def raw_strains_t(q, n, dn, jac):
    """raw_strains on time-last arrays: q (nel, 3 nen, T) -> (e1, e2, kappa) each (nel, npt, T)."""
    dns = dn[None, :, :] / jac[:, None, None]                # (nel, nen, npt)
    dx, dy = _along(q, 0, dns), _along(q, 1, dns)
    phi = _along(q, 2, np.broadcast_to(n[None], (q.shape[0],) + n.shape))
    c, s = np.cos(phi), np.sin(phi)
    return c * dx + s * dy, -s * dx + c * dy, raw_curvature_t(q, dn, jac)


def raw_curvature_t(q, dn, jac):
    """kappa of raw_strains_t alone (no rotation to evaluate): (nel, npt, T)."""
    return _along(q, 2, dn[None, :, :] / jac[:, None, None])


def raw_strains(qe, n, dn, jac):
    """Raw strain measures (e1, e2, kappa) as in beam2d.f90, at points with shape values
    n, dn (nen, npt); qe (..., nel, 3 nen), jac (nel,) = L / 2 -> each (..., nel, npt)."""
    qe = np.asarray(qe, float)
    lead = qe.shape[:-2]
    return tuple(_leading_first(v, lead) for v in raw_strains_t(_time_last(qe), n, dn, jac))


def raw_strain_derivatives(qe, dqe, n, dn, jac):
    """Directional derivatives of (e1, e2, kappa) along dqe.

    qe (nt, nel, 3 nen) coordinates, dqe (nt, nel, 3 nen, nv) their derivatives (design
    derivatives dq/dp, say) -> each (nt, nel, npt, nv). From e1 = c x' + s y',
    e2 = -s x' + c y' with phi = N_a phi_a: de1 = c dx' + s dy' + e2 dphi,
    de2 = -s dx' + c dy' - e1 dphi, dkappa = dphi'.
    """
    nen = n.shape[0]
    x, y, p = qe[..., 0::3], qe[..., 1::3], qe[..., 2::3]
    dxq, dyq, dpq = dqe[..., 0::3, :], dqe[..., 1::3, :], dqe[..., 2::3, :]
    dns = dn[None, :, :] / jac[:, None, None]                # (nel, nen, npt)
    dx = sum(x[..., a, None] * dns[:, a, :] for a in range(nen))
    dy = sum(y[..., a, None] * dns[:, a, :] for a in range(nen))
    phi = sum(p[..., a, None] * n[a] for a in range(nen))
    c, s = np.cos(phi)[..., None], np.sin(phi)[..., None]
    e1 = c * dx[..., None] + s * dy[..., None]
    e2 = -s * dx[..., None] + c * dy[..., None]
    ddx = sum(dxq[..., a, None, :] * dns[:, a, :, None] for a in range(nen))
    ddy = sum(dyq[..., a, None, :] * dns[:, a, :, None] for a in range(nen))
    dkap = sum(dpq[..., a, None, :] * dns[:, a, :, None] for a in range(nen))
    dphi = sum(dpq[..., a, None, :] * n[a][:, None] for a in range(nen))
    return (c * ddx + s * ddy + e2 * dphi, -s * ddx + c * ddy - e1 * dphi, dkap)


def element_groups(cm, elements=None):
    """Elements grouped by node count: {nen: (element ids, dof array (nel, 3 nen), 0-based)}.

    cm: a CompiledModel; elements: the element ids to group (default: all), order kept."""
    ids_all = range(cm.nel) if elements is None else elements
    groups = {}
    for e in ids_all:
        groups.setdefault(int(cm.el_nen[e]), []).append(int(e))
    return {nen: (np.array(ids), (cm.el_dofs[:3 * nen, ids] - 1).T.astype(np.int64))
            for nen, ids in groups.items()}


def columns(dofs, wanted):
    """Columns of `wanted` coordinates among the sorted stored `dofs` (-1 where not stored)."""
    dofs = np.asarray(dofs)
    wanted = np.asarray(wanted)
    if dofs.size == 0:
        return np.full(wanted.shape, -1)
    idx = np.clip(np.searchsorted(dofs, wanted), 0, dofs.size - 1)
    return np.where(dofs[idx] == wanted, idx, -1)
