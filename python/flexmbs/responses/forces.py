"""Constraint forces: motor torques and joint reactions, from the multipliers of eq. (1).

The core solves M qdd + f_int(q) - f_ext(t) + Phi_q^T (mu + p Phi) = 0 (fortran/assembly.f90),
with mu = k lambda the physical multipliers (Result.mu, (nt, nc), rows in the model's order,
labels in model.row_label). At a converged state Phi = 0, so the generalized force that the
constraint rows exert on the coordinates is -Phi_q^T mu.

Sign convention of this module: the force of a row is F_r = -mu_r, the generalized force the
joint exerts on the row's first coordinate, the one with coefficient +1. For the rows of
flexmbs.model.arrays:

- pin / clamp (x_n - x0 = 0, ...): the force of the ground on node n (x, y) or its moment;
- hinge a-b (x_a - x_b = 0): the force on node a (node b receives -F);
- drive_rotation (phi_n - law = 0, or phi_n - phi_o - law = 0): the torque the motor applies
  to node n's body, positive counter-clockwise (node o's body receives -F): the motor torque;
- prescribe_position: the force that imposes the motion on node n.

Statics checks this (tests/test_responses.py): a pin holding a weight W under gravity -y has
F_y = +W (it pushes up), and a motor lifting an arm needs a positive torque
I_O alpha + m g (L/2) cos(theta).

Design gradients need d mu / dp (nt, nc, nv), which the caller passes as `dmu` (the core's
design derivatives of the multipliers); without it only the values are returned.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["find_rows", "constraint_force", "motor_torque", "joint_reaction", "Reaction"]


def _labels(model):
    return [model.row_label(r) for r in range(len(model._rows))]


def find_rows(model, label):
    """Row indices whose label is `label`, or `label` followed by ' x' / ' y' / ' phi' (the
    components of a pin, clamp or hinge), in the model's order."""
    labels = _labels(model)
    rows = [r for r, lab in enumerate(labels)
            if lab == label or lab in (f"{label} x", f"{label} y", f"{label} phi")]
    if not rows:
        raise ModelError(f"no constraint row labelled {label!r}; the model's rows are "
                         f"{labels}")
    return rows


def _row(model, row):
    nc = len(model._rows)
    if isinstance(row, str):
        rows = find_rows(model, row)
        if len(rows) != 1:
            raise ModelError(f"{row!r} names {len(rows)} rows ({[model.row_label(r) for r in rows]})"
                             "; name one row")
        return rows[0]
    if isinstance(row, (bool, np.bool_)) or not isinstance(row, (int, np.integer)) \
            or not 0 <= row < nc:
        raise ModelError(f"row must be a label or a row index in [0, {nc}), got {row!r}")
    return int(row)


def _check_shapes(model, result, dmu):
    nc = len(model._rows)
    mu = np.asarray(result.mu, float)
    if mu.ndim != 2 or mu.shape[1] != nc:
        raise ModelError(f"result.mu must have shape (nt, {nc}) for this model, got {mu.shape}")
    if dmu is not None:
        dmu = np.asarray(dmu, float)
        if dmu.ndim != 3 or dmu.shape[:2] != mu.shape:
            raise ModelError(f"dmu must have shape {mu.shape} + (nv,), got {dmu.shape}")
    return mu, dmu


def constraint_force(model, result, row, dmu=None):
    """Force F = -mu of one constraint row (label or index) over time, see the module docstring.

    Returns (F (nt,), dF (nt, nv) or None)."""
    r = _row(model, row)
    mu, dmu = _check_shapes(model, result, dmu)
    return -mu[:, r], (None if dmu is None else -dmu[:, r, :])


def motor_torque(model, result, drive, dmu=None):
    """Torque of a rotation drive over time, positive counter-clockwise on the driven node.

    drive: the driven node id (drive_rotation(node, ...), absolute or relative), a row label
    or a row index. Returns (torque (nt,), d torque (nt, nv) or None)."""
    if isinstance(drive, (int, np.integer)) and not isinstance(drive, (bool, np.bool_)):
        node = int(drive)
        rows = [r for r, lab in enumerate(_labels(model))
                if lab == f"motor node {node}" or lab.startswith(f"motor node {node} relative")]
        if len(rows) != 1:
            raise ModelError(f"motor_torque: node {node} has {len(rows)} rotation drives; give "
                             "the row label or index instead")
        drive = rows[0]
    return constraint_force(model, result, drive, dmu)


@dataclass
class Reaction:
    """Reaction force of a joint on its first node: components and magnitude over time.

    x, y, magnitude : (nt,); dx, dy, dmagnitude : (nt, nv) or None. The magnitude's
    gradient has a kink where the force vanishes (there it is taken as zero)."""
    x: np.ndarray
    y: np.ndarray
    magnitude: np.ndarray
    dx: np.ndarray | None = None
    dy: np.ndarray | None = None
    dmagnitude: np.ndarray | None = None


def joint_reaction(model, result, joint, dmu=None):
    """Reaction of a pin or hinge: the force the joint exerts on its first node.

    joint: a label ('pin node 0', 'hinge 3-4': its rows '<label> x' and '<label> y') or a
    pair of row indices (x row, y row). Returns a Reaction."""
    if isinstance(joint, str):
        rows = [r for r in find_rows(model, joint)
                if model.row_label(r) in (f"{joint} x", f"{joint} y")]
        if len(rows) != 2:
            raise ModelError(f"joint_reaction: {joint!r} does not name an x and a y row")
    else:
        try:
            rows = [_row(model, r) for r in joint]
        except TypeError:
            raise ModelError(f"joint must be a label or a pair of row indices, got {joint!r}") \
                from None
        if len(rows) != 2:
            raise ModelError(f"joint must be a pair of row indices (x, y), got {joint!r}")
    fx, dfx = constraint_force(model, result, rows[0], dmu)
    fy, dfy = constraint_force(model, result, rows[1], dmu)
    mag = np.hypot(fx, fy)
    out = Reaction(x=fx, y=fy, magnitude=mag)
    if dmu is not None:
        safe = np.where(mag > 0, mag, 1.0)[:, None]
        out.dx, out.dy = dfx, dfy
        out.dmagnitude = np.where(mag[:, None] > 0, (fx[:, None] * dfx + fy[:, None] * dfy) / safe,
                                  0.0)
    return out
