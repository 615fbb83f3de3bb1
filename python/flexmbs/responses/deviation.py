"""Deviation of a flexible mechanism from its rigid reference, with design gradients.

A deviation response (`flexmbs.model.description.Deviation`) is sqrt(sum c_k^2) over scalar terms
c_k. A term is a component of the difference between a point's flexible position and its
position in the rigid reference (or of that difference for the vector from another point to
it), expressed in the ground frame or in the rigid reference's frame of a body, whose x axis
turns with the rotation of the body's first node (a beam's axis; a rigid body's centre, at
angle 0 at t = 0). Component 'angle' is the node's rotation minus its rigid rotation.

The paper's measures are three settings of this (Tromme et al., eqs. 28, 30, 33):
(28) terms = [A y, (tip relative to A) y]; (30) [tip norm]; (33) [A norm].

The rigid reference does not depend on the sizing design, so the gradient comes from the
flexible positions alone: d c_k/dx = e_k . R(theta_r)^T d(position)/dx.
"""
from __future__ import annotations

import numpy as np

__all__ = ["deviation_terms", "deviation"]


def _cols(dofs, wanted):
    idx = np.searchsorted(dofs, wanted)
    if np.any(idx >= len(dofs)) or np.any(dofs[np.minimum(idx, len(dofs) - 1)] != wanted):
        return None
    return idx


def _history(result, dofs, derivatives):
    """q[:, dofs] and dq[:, dofs, :] (None when not asked)."""
    c = _cols(result.dofs, np.asarray(dofs))
    if c is None:
        raise ValueError(f"coordinates {list(dofs)} were not stored")
    q = result.q[:, c]
    if not derivatives:
        return q, None
    s = _cols(result.sens_dofs, np.asarray(dofs))
    if s is None:
        raise ValueError(f"coordinates {list(dofs)} have no design derivatives")
    return q, result.dq[:, s, :]


def _reference(reference, dofs):
    """(nt, len(dofs)) rigid-reference history of some coordinates: from a RigidMotion (only
    those coordinates are computed) or an (nt, ndof) array."""
    if hasattr(reference, "coordinates"):
        return reference.coordinates(dofs)
    return np.asarray(reference)[:, dofs]


def _weights(point):
    """(node ids, weights) of a point: a node id, or a station along a beam
    (flexmbs.responses.station.StationPoint: its element's nodes and shape values)."""
    if hasattr(point, "nodes"):
        return [int(n) for n in point.nodes], [float(w) for w in point.n]
    return [int(point)], [1.0]


def _relative(point, reference_q, result, comps, derivatives):
    """(flexible - rigid reference) of coordinates `comps` (0: x, 1: y, 2: angle) of a point,
    (nt, len(comps)), and its design derivatives (nt, len(comps), nv) or None."""
    d = dq = 0.0
    for n, w in zip(*_weights(point)):
        sl = [3 * n + c for c in comps]
        q, dqn = _history(result, sl, derivatives)
        d = d + w * (q - _reference(reference_q, sl))
        if derivatives:
            dq = dq + w * dqn
    return d, (dq if derivatives else None)


def deviation_terms(node, reference_q, result, term, frame_node=None, relative_node=None,
                    derivatives=False):
    """Scalar terms (ncomp, nt) of one Term and their gradients (ncomp, nt, nv) or None.

    node, relative_node, frame_node: node ids of the point, of the point it is measured from
    (or None) and of the frame body's first node (None: ground); the point and the one it is
    measured from may also be stations along beams (flexmbs.responses.station.locate: their
    element's nodes interpolated by its shape functions); reference_q: the rigid reference, a
    flexmbs.model.kinematics.RigidMotion or its (nt, ndof) coordinates."""
    comps = [2] if term.component == "angle" else [0, 1]
    d, dq = _relative(node, reference_q, result, comps, derivatives)
    if relative_node is not None:
        dr, dqr = _relative(relative_node, reference_q, result, comps, derivatives)
        d = d - dr
        if derivatives:
            dq = dq - dqr
    if term.component == "angle":
        return d.T, (np.moveaxis(dq, 1, 0) if derivatives else None)
    if frame_node is not None:
        th = _reference(reference_q, [3 * frame_node + 2])[:, 0]
        c, s = np.cos(th), np.sin(th)
        d = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        if derivatives:
            dq = np.stack([c[:, None] * dq[:, 0] + s[:, None] * dq[:, 1],
                           -s[:, None] * dq[:, 0] + c[:, None] * dq[:, 1]], axis=1)
    pick = {"x": [0], "y": [1], "norm": [0, 1]}[term.component]
    return d[:, pick].T, (np.moveaxis(dq[:, pick, :], 1, 0) if derivatives else None)


def deviation(parts, derivatives=False):
    """sqrt(sum c^2) over the terms' components and its gradient ((nt,), (nt, nv) or None).

    parts: list of (values (ncomp, nt), gradients (ncomp, nt, nv) or None) from
    deviation_terms. Where the deviation is exactly 0 (t = 0 of a rest start) its gradient,
    which does not exist there, is given as 0."""
    c = np.concatenate([p[0] for p in parts])
    value = np.sqrt(np.sum(c * c, axis=0))
    if not derivatives:
        return value, None
    dc = np.concatenate([p[1] for p in parts])
    num = np.einsum("kt,ktv->tv", c, dc)
    with np.errstate(invalid="ignore", divide="ignore"):
        grad = np.where(value[:, None] > 0, num / np.where(value > 0, value, 1.0)[:, None], 0.0)
    return value, grad
