"""Position analysis of a model with every flexible body rigid: assembly and rigid reference.

The rigid mechanism of a Model moves its **rigid groups** (`rigid_groups`: each beam's nodes,
each rigid body's nodes, every other node alone; bodies sharing a node form one group) as rigid
bodies in their reference shape. A group's pose z_g = (cx, cy, theta) places its reference
centroid at (cx, cy) and turns it by theta; node n of the group is at

    (x_n, y_n) = (cx, cy) + R(theta) r_n,     phi_n = phi_n0 + theta,

r_n its reference offset from the centroid. The constraint rows of the model
(`flexmbs.model.constraints`) become equations Phi(q(z), t) = 0 on the 3 ngroups poses, with
Jacobian J = Phi_q dq/dz. Rows inside a group (the rigid links of a rigid body) hold
identically.

- `assemble` closes the loops at one time from approximate positions: the group poses are
  fitted to the given nodes (least squares), then moved to the nearest pose that satisfies
  every row, nearest in the node positions (Gauss-Newton steps of minimum norm in the metric
  n_g |dc|^2 + sum_n |r_n|^2 dtheta^2, which is the nodes' squared displacement to second
  order; lstsq, so consistent redundant rows do no harm).
- `rigid_reference` is the position, velocity and acceleration analysis on a time grid, by
  continuation on the assembly branch of the first time: from each solved posture, with its
  velocities J zd = -Phi_t and accelerations J zdd = gamma - Phi_q q_zz[zd, zd], the Taylor
  predictor z + tau zd + tau^2/2 zdd, Newton on several times at once (batched LU on the
  square rows, batched SVD otherwise), and each interval tested as a step of the continuation
  (a short predicted move, a corrector's move small against it, the loop determinant's sign
  kept); an interval that fails is subdivided. It stops only at a singular posture (the
  Jacobian's rank deficiency is in the error) or at a drive law that jumps. It works on the
  poses and on the coordinates of the nodes the constraint rows use only, so its cost does
  not grow with the number of elements; the other nodes follow from the poses by rigid
  transforms when asked (`RigidMotion.coordinates`, or every node: `RigidMotion.q`).
- `drive_velocities` is the rigid-body velocity field the drives impose at one state (for a
  start from rest of a moving mechanism).

Examples
--------
>>> import numpy as np
>>> from flexmbs import Model, Material, Circle, TimeLaw
>>> from flexmbs.model.kinematics import rigid_reference, drive_velocities
>>> mat, sec = Material(7e10, 0.3, 2700), Circle(0.02)
>>> m = Model()
>>> crank = m.add_beam("crank", (0, 0), (0.1, 0), 2, material=mat, section=sec)
>>> rod = m.add_beam("rod", (0.1, 0), (0.4, 0), 2, material=mat, section=sec)
>>> m.pin(crank.first); m.hinge(crank.last, rod.first); m.prescribe_position(rod.last, y=0.0)
>>> m.drive_rotation(crank.first, TimeLaw(lambda t: 10 * t, lambda t: 10 + 0 * t, lambda t: 0 * t))
>>> ref = rigid_reference(m, np.linspace(0.0, 0.1, 11))
>>> round(float(ref.q[-1, 3 * rod.last]), 6)        # 0.1 cos 1 + sqrt(0.3^2 - 0.1^2 sin^2 1)
0.341987
>>> qd0 = drive_velocities(m, m.reference_coordinates())   # InitialConditions(qd0=qd0)
>>> round(float(qd0[3 * crank.last + 1]), 6)                # 10 rad/s x 0.1 m
1.0
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.model.constraints import (acceleration_rhs, constraint_rate, constraint_values,
                                 jacobian_entries, law_tables, row_table)

__all__ = ["rigid_groups", "assemble", "Assembly", "rigid_reference", "RigidMotion",
           "drive_velocities", "free_degrees_of_freedom"]

#: relative singular value below which J is taken as rank-deficient
RANK_RTOL = 1e-9
#: a residual at the rounding level of the coordinates is converged: ROUNDING machine epsilons
#: of the largest coordinate or law value (a link after 10^4 turns, at 6.3e4 rad: 9e-10)
ROUNDING = 64


def rigid_groups(model):
    """Node groups (lists of node ids, ascending) that move as one rigid body in the rigid
    mechanism: each beam's nodes, each rigid body's nodes (bodies sharing a node merge), and
    every other node alone. Ordered by their smallest node."""
    parent = list(range(model.nnodes))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for b in model.bodies.values():
        if b.kind not in ("beam", "rigid"):
            continue
        root = find(b.nodes[0])
        for n in b.nodes[1:]:
            rn = find(n)
            if rn != root:
                parent[rn] = root
    groups = {}
    for n in range(model.nnodes):
        groups.setdefault(find(n), []).append(n)
    return sorted(groups.values(), key=lambda g: g[0])


class _Poses:
    """The map z (ngroups poses) -> q (node coordinates) of a model's rigid groups."""

    def __init__(self, model):
        cm = model.compile()
        self.cm = cm
        self.groups = rigid_groups(model)
        ng = len(self.groups)
        self.ng = ng
        nn = model.nnodes
        ref = cm.qref.reshape(nn, 3)
        self.group_of = np.empty(nn, np.int64)
        self.r = np.zeros((nn, 2))
        self.phi0 = ref[:, 2].copy()
        self.c0 = np.zeros((ng, 2))
        self.count = np.zeros(ng)
        self.spread = np.zeros(ng)           # sum |r_n|^2
        for g, nodes in enumerate(self.groups):
            pts = ref[nodes, :2]
            c = pts.mean(axis=0)
            self.group_of[nodes] = g
            self.r[nodes] = pts - c
            self.c0[g] = c
            self.count[g] = len(nodes)
            with np.errstate(over="ignore", invalid="ignore"):   # checked just below
                self.spread[g] = float(np.sum((pts - c) ** 2))
        with np.errstate(over="ignore", invalid="ignore"):
            extent = np.abs(ref[:, :2] - ref[:, :2].mean(axis=0)).max() if nn else 0.0
        if not np.isfinite(extent) or extent > 1e100:
            raise ModelError(f"the mechanism's points span {float(extent):g} m: node coordinates "
                             "must be finite and within 1e100 m of each other")
        self.length = max(float(extent), 1e-3)
        # metric of the node displacements in pose coordinates (rotation of a lone node: as if
        # it carried an arm of 10 % of the model's size)
        wt = np.where(self.spread > 1e-12 * self.length ** 2 * self.count, self.spread,
                      self.count * (0.1 * self.length) ** 2)
        self.weight = np.stack([self.count, self.count, wt], axis=1).ravel()
        self.scale = max(1.0, float(np.abs(ref[:, :2]).max()) if nn else 1.0)
        # the nodes the constraint rows act on ("active"): the position analysis works on their
        # coordinates alone, so that its cost does not grow with the number of elements; rows
        # holds the constraint rows on the active coordinates (3 per active node, in order)
        full = row_table(cm)
        used = full.dofs[full.dofs >= 0]
        self.active = np.unique(used // 3)
        where = np.full(nn, -1, np.int64)
        where[self.active] = np.arange(self.active.size)
        d = np.where(full.dofs >= 0, full.dofs, 0)
        self.rows = replace(full, dofs=np.where(full.dofs >= 0, 3 * where[d // 3] + d % 3, -1),
                            ndof=3 * self.active.size)
        self.active_dofs = (3 * self.active[:, None] + np.arange(3)).ravel()
        # Jacobian pattern: each entry of Phi_q on coordinate (node n, component k) feeds the
        # pose columns of n's group (translation for x, y; rotation for all three); node is
        # the index among the active nodes
        r_idx, cols, _ = jacobian_entries(self.rows, cm.qref[self.active_dofs])
        node, comp = cols // 3, cols % 3
        g = self.group_of[self.active[node]]
        self._entries = (r_idx, node, comp, g)
        ncol = 3 * ng
        tr = np.flatnonzero(comp < 2)
        # contributions (translations, then rotations) -> entries of J, summed in their order;
        # numpy alone (scipy.sparse costs a batch worker ~0.15 s of imports)
        flat = np.concatenate([r_idx[tr] * ncol + 3 * g[tr] + comp[tr], r_idx * ncol + 3 * g + 2])
        order = np.argsort(flat, kind="stable")
        target, first = np.unique(flat[order], return_index=True)
        self._scatter = (order, first, target, self.rows.nc * ncol)

    # ---------------------------------------------------------------- maps
    # nodes: None (every node) or an array of node ids; outputs follow its order
    def q(self, z, nodes=None):
        """Node coordinates (..., 3 nnodes) of poses z (..., ng, 3), of every node or `nodes`."""
        sel = slice(None) if nodes is None else nodes
        z = np.asarray(z, float)
        zn = z[..., self.group_of[sel], :]                              # (..., nn, 3)
        c, s = np.cos(zn[..., 2]), np.sin(zn[..., 2])
        rx, ry = self.r[sel, 0], self.r[sel, 1]
        out = np.stack([zn[..., 0] + c * rx - s * ry, zn[..., 1] + s * rx + c * ry,
                        self.phi0[sel] + zn[..., 2]], axis=-1)
        return out.reshape(z.shape[:-2] + (-1,))

    def qa(self, z):
        """Coordinates (..., 3 nactive) of the active nodes (those the constraint rows use)."""
        return self.q(z, self.active)

    def rotated(self, z, nodes=None):
        """R(theta) r_n of every node (or of `nodes`), (..., nn, 2)."""
        sel = slice(None) if nodes is None else nodes
        th = np.asarray(z, float)[..., self.group_of[sel], 2]
        c, s = np.cos(th), np.sin(th)
        rx, ry = self.r[sel, 0], self.r[sel, 1]
        return np.stack([c * rx - s * ry, s * rx + c * ry], axis=-1)

    def qd(self, z, zd, nodes=None):
        """Node velocities (..., 3 nn) of pose rates zd at poses z (every node or `nodes`)."""
        sel = slice(None) if nodes is None else nodes
        rr = self.rotated(z, nodes)
        zn = np.asarray(zd, float)[..., self.group_of[sel], :]
        w = zn[..., 2]
        out = np.stack([zn[..., 0] - w * rr[..., 1], zn[..., 1] + w * rr[..., 0], w], axis=-1)
        return out.reshape(out.shape[:-2] + (-1,))

    def centripetal(self, z, zd, nodes=None):
        """q_zz[zd, zd] (..., 3 nn): the node accelerations of pose rates zd with zdd = 0."""
        sel = slice(None) if nodes is None else nodes
        rr = self.rotated(z, nodes)
        w = np.asarray(zd, float)[..., self.group_of[sel], 2]
        out = np.stack([-w * w * rr[..., 0], -w * w * rr[..., 1], 0.0 * w], axis=-1)
        return out.reshape(out.shape[:-2] + (-1,))

    def move(self, dz):
        """The displacement (m) of pose changes dz (..., ng, 3), (...,): the largest over the
        groups of the root-mean-square displacement of a group's nodes (in the metric of
        `weight`; a lone node turns as if it carried an arm of 10 % of the model)."""
        dz = np.asarray(dz, float)
        if not self.ng:
            return np.zeros(dz.shape[:-2])
        arm2 = self.weight[2::3] / self.count
        return np.sqrt(np.max(dz[..., 0] ** 2 + dz[..., 1] ** 2 + arm2 * dz[..., 2] ** 2,
                              axis=-1))

    def jacobian(self, z, qa=None, rra=None):
        """J = Phi_q dq/dz, (..., nc, 3 ng), at poses z (..., ng, 3); qa, rra: the active
        nodes' coordinates and R(theta) r_n when already known."""
        z = np.asarray(z, float)
        qa = self.qa(z) if qa is None else qa
        rra = self.rotated(z, self.active) if rra is None else rra
        _, _, vals = jacobian_entries(self.rows, qa)                    # (..., nent)
        r_idx, node, comp = self._entries[:3]
        tr = comp < 2
        arm = np.where(comp == 0, -rra[..., node, 1], np.where(comp == 1, rra[..., node, 0], 1.0))
        contrib = np.concatenate([vals[..., tr], vals * arm], axis=-1)
        lead = contrib.shape[:-1]
        order, first, target, size = self._scatter
        src = contrib.reshape(-1, contrib.shape[-1])[:, order]
        flat = np.zeros((src.shape[0], size))
        if target.size:
            flat[:, target] = np.add.reduceat(src, first, axis=1)
        return flat.reshape(lead + (self.rows.nc, 3 * self.ng))

    # ---------------------------------------------------------------- fitting
    def fit(self, q):
        """Poses (ng, 3) of the rigid copies of the reference groups nearest to q (ndof,)."""
        q = np.asarray(q, float).reshape(-1, 3)
        z = np.zeros((self.ng, 3))
        for g, nodes in enumerate(self.groups):
            pts = q[nodes, :2]
            c = pts.mean(axis=0)
            dphi = float(np.mean(q[nodes, 2] - self.phi0[nodes]))
            r = self.r[nodes]
            if self.spread[g] > 1e-24 * self.length ** 2:
                p = pts - c
                th = math.atan2(float(np.sum(r[:, 0] * p[:, 1] - r[:, 1] * p[:, 0])),
                                float(np.sum(r[:, 0] * p[:, 0] + r[:, 1] * p[:, 1])))
                th += 2 * math.pi * round((dphi - th) / (2 * math.pi))
            else:
                th = dphi
            z[g] = (c[0], c[1], th)
        return z

    def describe_group(self, g, model):
        owners = [b.name for b in model.bodies.values() if set(b.nodes) & set(self.groups[g])]
        if owners:
            return f"body {'/'.join(repr(o) for o in owners)}"
        return f"node {self.groups[g][0]}"


def _poses(model):
    """The pose map of a model, cached on the model until its structure changes."""
    cm = model.compile()
    cache = model.__dict__.get("_kinematics_poses")
    if cache is not None and cache[0] is cm:
        return cache[1]
    p = _Poses(model)
    model.__dict__["_kinematics_poses"] = (cm, p)
    return p


def _lstsq(a, b):
    """Minimum-norm least-squares solution of a x = b (2-D a)."""
    if a.size == 0:
        return np.zeros(a.shape[1])
    return np.linalg.lstsq(a, b, rcond=None)[0]


def _accepted(P, qa, law_val, tol):
    """Residual (K,) accepted at the active coordinates qa (K, 3 nactive) and law values
    law_val (nlaw, K): tol times the model's scale, or the rounding level of the largest
    coordinate or law value (angles grow without bound under a turning crank)."""
    mag = np.max(np.abs(qa), axis=-1, initial=0.0)
    if law_val.size:
        mag = np.maximum(mag, np.max(np.abs(law_val), axis=0))
    return np.maximum(tol * P.scale, ROUNDING * np.finfo(float).eps * mag)


def _worst_rows(model, phi, k=3):
    order = np.argsort(-np.abs(phi))[:k]
    return "; ".join(f"'{model.row_label(int(r))}' ({phi[r]:+.3g})" for r in order
                     if abs(phi[r]) > 0)


def _law_at(model, t):
    val, rate, acc = law_tables(model, [t])
    return val[:, 0], rate[:, 0], acc[:, 0]


@dataclass
class Assembly:
    """An assembled configuration (see `assemble`).

    q : (ndof,) coordinates satisfying every constraint row at t.
    z : (ngroups, 3) group poses (centroid x, y and rotation from the reference).
    correction : (nnodes,) distance (m) each node moved from the given positions.
    iterations : Newton (Gauss-Newton) iterations.
    residual : max |Phi| at q.
    t : float
    """
    q: np.ndarray
    z: np.ndarray
    correction: np.ndarray
    iterations: int
    residual: float
    t: float


def _nearest_assembly(P, z, qg, zg, law_val, tol, max_iter):
    """Gauss-Newton for min sum_n |p_n(z) - p_n given|^2 (+ the rotation of lone nodes from
    their given one, weighted as an arm of 10 % of the model) subject to Phi(q(z)) = 0, from
    poses z; each step solves the linearized problem's KKT system by least squares (minimum
    norm, so consistent redundant rows do no harm). Returns (z, iterations, residual, Phi)."""
    lone = P.weight[2::3] != P.spread                 # groups whose rotation moves no distance
    reg = np.where(lone, P.weight[2::3], 0.0)
    nn, ng = P.r.shape[0], P.ng
    gi = P.group_of
    pg = qg.reshape(-1, 3)[:, :2]
    nz = 3 * ng
    it = 0
    while True:
        qa = P.qa(z)
        phi = constraint_values(P.rows, qa, law_val)
        res = float(np.max(np.abs(phi))) if phi.size else 0.0
        accept = float(_accepted(P, qa[None], law_val[:, None], tol)[0])
        rr = P.rotated(z)
        pos = z[gi, :2] + rr
        # objective residual and its Jacobian on the poses
        A = np.zeros((2 * nn + ng, nz))
        A[2 * np.arange(nn), 3 * gi] = 1.0
        A[2 * np.arange(nn), 3 * gi + 2] = -rr[:, 1]
        A[2 * np.arange(nn) + 1, 3 * gi + 1] = 1.0
        A[2 * np.arange(nn) + 1, 3 * gi + 2] = rr[:, 0]
        A[2 * nn + np.arange(ng), 3 * np.arange(ng) + 2] = np.sqrt(reg)
        b = np.concatenate([(pg - pos).ravel(), np.sqrt(reg) * (zg[:, 2] - z[:, 2])])
        J = P.jacobian(z)
        nc = J.shape[0]
        kkt = np.block([[A.T @ A, J.T], [J, np.zeros((nc, nc))]])
        sol = _lstsq(kkt, np.concatenate([A.T @ b, -phi]))
        step = sol[:nz]
        move = float(np.max(np.abs(A[:2 * nn] @ step))) if nn else 0.0
        if (res <= accept and move <= accept) or it >= max_iter:
            return z, it, res, phi
        # damping: halve a step that makes the constraint residual grow a lot
        lam = 1.0
        for _ in range(30):
            znew = z + lam * step.reshape(-1, 3)
            rn = float(np.max(np.abs(constraint_values(P.rows, P.qa(znew), law_val)))) if nc else 0.0
            if rn <= max(2 * res, accept) or lam < 1e-6:
                break
            lam *= 0.5
        it += 1
        if lam * move <= 1e-15 * P.scale and res > accept:
            return znew, it, rn, constraint_values(P.rows, P.qa(znew), law_val)  # stalled
        z = znew


def assemble(model, t=0.0, q=None, *, tol=1e-12, max_iter=50):
    """Close the loops: the configuration nearest to q that satisfies every constraint row at t.

    Each rigid group (`rigid_groups`) keeps its reference shape: its pose is first fitted to
    the given nodes (q, default the model's reference coordinates), then moved to satisfy the
    rows with the smallest displacement of the nodes (minimum-norm Gauss-Newton). Consistent
    redundant rows are allowed; free degrees of freedom keep their given values as nearly as
    the rows allow.

    Parameters
    ----------
    model : Model
    t : float
        Time at which the drives' laws are evaluated.
    q : (ndof,) array, optional
        Approximate coordinates (default: the reference).
    tol : float
        Convergence: max |Phi| <= tol * max(1, largest |x|, |y| of the reference), or at the
        rounding level of the coordinates (ROUNDING machine epsilons of the largest coordinate
        or law value: an angle of many turns).
    max_iter : int

    Returns
    -------
    Assembly

    Raises
    ------
    ModelError
        If no configuration satisfies the rows (the message names the rows with the largest
        residual at the closest configuration found, and the time), or bad arguments.
    """
    P = _poses(model)
    t = float(t)
    if not math.isfinite(t):
        raise ModelError(f"assemble: t must be finite, got {t}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ModelError(f"assemble: max_iter must be a non-negative integer, got {max_iter!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise ModelError(f"assemble: tol must be a positive number, got {tol!r}")
    qg = P.cm.qref.copy() if q is None else np.asarray(q, float)
    if qg.shape != (P.cm.ndof,) or not np.all(np.isfinite(qg)):
        raise ModelError(f"assemble: q must be a finite array of shape ({P.cm.ndof},), "
                         f"got shape {np.shape(q)}")
    val, _, _ = _law_at(model, t)
    z0 = P.fit(qg)
    z, it, res, phi = _nearest_assembly(P, z0.copy(), qg, z0, val, tol, max_iter)
    if not res <= _accepted(P, P.qa(z)[None], val[:, None], tol)[0]:
        raise ModelError(f"assemble: the constraints cannot be satisfied at t = {t:.6g} s with "
                         f"rigid bodies (max |Phi| = {res:.3g} after {it} iterations); largest "
                         f"residuals: {_worst_rows(model, phi)}")
    qa = P.q(z)
    corr = np.hypot(*(qa.reshape(-1, 3)[:, :2] - qg.reshape(-1, 3)[:, :2]).T)
    return Assembly(q=qa, z=z, correction=corr, iterations=it, residual=res, t=t)


def _svd_solve(u, s, vt, b, rank_tol):
    """Minimum-norm solutions of stacks of systems from their SVD: (..., m) right-hand sides."""
    inv = np.where(s > rank_tol[..., None], 1.0 / np.where(s > 0, s, 1.0), 0.0)
    ub = np.einsum("...ij,...i->...j", u, b)
    return np.einsum("...ji,...j->...i", vt, inv * ub)


def free_degrees_of_freedom(model, q=None, t=0.0):
    """Free degrees of freedom of the rigid mechanism at q (default: reference): 3 ngroups minus
    the rank of the constraint Jacobian on the group poses, and a description of the groups the
    free motions move most (list of str)."""
    P = _poses(model)
    qq = P.cm.qref if q is None else np.asarray(q, float)
    z = P.fit(qq)
    J = P.jacobian(z) / np.sqrt(P.weight)
    nz = J.shape[1]
    if J.shape[0]:
        _, s, vt = np.linalg.svd(J)
        rank = int(np.sum(s > RANK_RTOL * max(s.max(), 1e-300)))
    else:
        rank, vt = 0, np.zeros((0, nz))
    null = np.eye(nz)[rank:] if J.shape[0] == 0 else vt[rank:]
    where = []
    for v in null:
        g = int(np.argmax(np.abs(v / np.sqrt(P.weight)).reshape(-1, 3).sum(axis=1)))
        d = P.describe_group(g, model)
        if d not in where:
            where.append(d)
    return nz - rank, where


@dataclass(eq=False)
class RigidMotion:
    """The rigid reference on a time grid (see `rigid_reference`).

    t : (nt,); z, zd, zdd : (nt, ngroups, 3) group poses and their rates; groups : the node
    groups; iterations : (nt,) Newton iterations spent on each time (the chunk that solved it,
    with the attempts and substeps since the previous time); residual : (nt,) max |Phi|;
    substeps : (nt,) intermediate postures the continuation solved between the previous time
    and this one.

    The node histories follow from the poses by rigid transforms: `coordinates(dofs, rate)`
    gives those of some coordinates (cost and memory nt x len(dofs); the last
    MEMO_ENTRIES asked of up to MEMO_VALUES values are kept, the reference being the same
    for every design of a case); q, qd, qdd (nt, ndof) hold every node's, computed on first use and kept (nt x
    ndof values each).
    """
    #: `coordinates` results kept (a response asks for the same few coordinates at every
    #: design: 4 calls and ~1.3 ms of a 17 ms evaluation of the paper's robot, measured on the
    #: 2-core reference machine)
    MEMO_ENTRIES = 32
    #: ... of at most this many values each (8 MB; larger ones are computed at every call)
    MEMO_VALUES = 1 << 20
    t: np.ndarray
    z: np.ndarray
    zd: np.ndarray
    zdd: np.ndarray
    groups: list
    iterations: np.ndarray
    residual: np.ndarray
    substeps: np.ndarray = None
    poses: object = field(default=None, repr=False)
    _memo: dict = field(default_factory=dict, init=False, repr=False)

    def _nodes_history(self, nodes, rate):
        P = self.poses
        if rate == 0:
            return P.q(self.z, nodes)
        if rate == 1:
            return P.qd(self.z, self.zd, nodes)
        return P.qd(self.z, self.zdd, nodes) + P.centripetal(self.z, self.zd, nodes)

    def coordinates(self, dofs, rate=0):
        """(nt, len(dofs)) history of the coordinates `dofs` (0-based indices of q; an int
        gives (nt,)): positions (rate=0), velocities (1) or accelerations (2)."""
        if isinstance(rate, bool) or rate not in (0, 1, 2):
            raise ModelError(f"RigidMotion.coordinates: rate must be 0, 1 or 2, got {rate!r}")
        ndof = self.poses.cm.ndof
        d = np.asarray(dofs)
        if d.ndim > 1 or (d.size and d.dtype.kind not in "iu") or \
                (d.size and (d.min() < 0 or d.max() >= ndof)):
            raise ModelError(f"RigidMotion.coordinates: dofs must be coordinate indices in "
                             f"[0, {ndof}), got {dofs!r}")
        flat = np.atleast_1d(d).astype(np.int64)
        key = (rate, flat.tobytes())
        out = self._memo.get(key)
        if out is None:
            nodes, inv = np.unique(flat // 3, return_inverse=True)
            h = self._nodes_history(nodes, rate).reshape(self.t.size, nodes.size, 3)
            out = h[:, inv.ravel(), flat % 3]
            if out.size > self.MEMO_VALUES:          # not kept: no copy of a large history
                return out[:, 0] if d.ndim == 0 else out
            if len(self._memo) >= self.MEMO_ENTRIES:
                self._memo.pop(next(iter(self._memo)))
            self._memo[key] = out
        out = out.copy()           # the caller's to change
        return out[:, 0] if d.ndim == 0 else out

    @cached_property
    def q(self):
        """(nt, ndof) node coordinates (every node; see `coordinates` for a few)."""
        return self._nodes_history(None, 0)

    @cached_property
    def qd(self):
        """(nt, ndof) node velocities."""
        return self._nodes_history(None, 1)

    @cached_property
    def qdd(self):
        """(nt, ndof) node accelerations."""
        return self._nodes_history(None, 2)


_CHUNK_ITER, _CHUNK_MAX = 6, 64

#: continuation of the rigid reference (`rigid_reference`), each step from a solved posture:
#: the Taylor predictor moves the mechanism by at most STEP_MAX times its size
#: (`_Poses.length`), and the corrector by at most CORRECTION_RATIO times the predicted move
#: plus CORRECTION_FLOOR times the size (the predictor's error falls 8-fold when its step is
#: halved, while a move to another assembly branch is the distance between the branches,
#: whatever the step)
STEP_MAX = 0.2
CORRECTION_RATIO, CORRECTION_FLOOR = 0.1, 1e-4
#: Newton solves at once the times of a chunk whose predictor from the last posture moves the
#: mechanism by at most CHUNK_REACH of its size (each interval is then tested as a step)
CHUNK_REACH = 2.0
#: an interval of the time grid is subdivided down to 2^-MAX_HALVINGS of its length
MAX_HALVINGS = 40
#: a posture where the continuation stops is singular if the constraint Jacobian's smallest
#: singular value is below SINGULAR_RTOL of its largest (2^-40 of a step from a dead centre,
#: where it vanishes like the square root of the distance, it is ~1e-6)
SINGULAR_RTOL = 1e-4


def _newton_batch(P, z, law_val, accept, max_iter, live=None):
    """Newton on the poses of several times at once, z (K, ng, 3), law_val (nlaw, K), accepted
    residuals accept (K,), until every residual is below 1 % of its accepted one or has stopped
    falling (at its rounding level when accepted; none near a solution when not). The steps
    solve J dz = -Phi on the rows `live` when they are square (LU), else by minimum norm from
    the batched SVD of J W^-1/2. Returns (z, iterations, residuals (K,), Phi (K, nc))."""
    sw = np.sqrt(P.weight)
    K = z.shape[0]
    phi = constraint_values(P.rows, P.qa(z), law_val)
    res = np.max(np.abs(phi), axis=-1) if phi.shape[-1] else np.zeros(K)
    it = 0
    target = 0.01 * accept
    while it < max_iter and np.any(res > target):
        it += 1
        J = P.jacobian(z)
        dz = _square_solve(J, live, -phi)
        if dz is None:
            u, s, vt = np.linalg.svd(J / sw, full_matrices=False)
            dz = _svd_solve(u, s, vt, -phi, RANK_RTOL * s.max(axis=-1)) / sw
        z = z + dz.reshape(z.shape)
        phi = constraint_values(P.rows, P.qa(z), law_val)
        new = np.max(np.abs(phi), axis=-1)
        floor = np.all(new <= accept) and np.all((new > 0.25 * res) | (new <= target))
        stalled = np.all((new <= target) | (new > 0.9 * res))    # no solution near: stop
        res = new
        if floor or stalled:
            break
    return z, it, res, phi


def _square_solve(J, live, b):
    """Solutions of J[:, live] x = b[:, live] (K systems) by LU when `live` is given and every
    system is regular, else None."""
    if live is None:
        return None
    try:
        x = np.linalg.solve(J[:, live, :], b[:, live, None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    return x if np.all(np.isfinite(x)) else None


def _rates(P, z, qa, J, rate, acc, live=None):
    """Pose rates zd and accelerations zdd (K, ng, 3) at poses z (K, ng, 3) (qa, J: their
    active coordinates and Jacobian) from the law rates and accelerations
    (nlaw, K): J zd = -Phi_t, J zdd = gamma - Phi_q q_zz[zd, zd]; and whether J has full column
    rank at each (K,). On the rows `live` when they are square (an inverse, its Frobenius
    condition number bounding the 2-norm one from above), else by minimum norm from the SVD."""
    sw = np.sqrt(P.weight)
    K, nz = z.shape[0], J.shape[-1]
    inv = None
    if live is not None:
        try:
            inv = np.linalg.inv(J[:, live, :])
        except np.linalg.LinAlgError:
            inv = None
    if inv is not None and np.all(np.isfinite(inv)):
        cond = np.linalg.norm(J[:, live, :] / sw, axis=(1, 2)) * \
            np.linalg.norm(inv * sw[:, None], axis=(1, 2))
        full = cond * RANK_RTOL < 1.0
        if not np.all(full):           # the bound is not sharp: the singular values decide
            s = np.linalg.svd(J[~full] / sw, compute_uv=False)
            full[~full] = s.min(axis=-1) > RANK_RTOL * s.max(axis=-1)

        def solve(b):
            return np.einsum("kij,kj->ki", inv, b[:, live])
    else:
        u, s, vt = np.linalg.svd(J / sw, full_matrices=False)
        smax = s.max(axis=-1, initial=0.0)
        full = np.sum(s > RANK_RTOL * smax[:, None], axis=-1) >= nz

        def solve(b):
            return _svd_solve(u, s, vt, b, RANK_RTOL * smax) / sw
    zd = solve(-constraint_rate(P.rows, rate)).reshape(z.shape)
    qda = P.qd(z, zd, P.active)
    gamma = acceleration_rhs(P.rows, qa, qda, acc)
    cen = P.centripetal(z, zd, P.active)
    _, _, pq = jacobian_entries(P.rows, qa)                         # Phi_q entries (K, nent)
    r_idx, node, comp, _ = P._entries
    pqc = np.zeros((K, P.rows.nc))
    np.add.at(pqc.T, r_idx, (pq * cen[:, 3 * node + comp]).T)
    zdd = solve(gamma - pqc).reshape(z.shape)
    return zd, zdd, full


@dataclass
class _Posture:
    """A solved posture of the continuation: time, poses and their rates, and the sign of the
    loop determinant (det of the Jacobian's non-vanishing rows; 0 when not square)."""
    t: float
    z: np.ndarray
    zd: np.ndarray
    zdd: np.ndarray
    sign: float


class _Step(NamedTuple):
    """What `_advance` solved: the leading m times that pass (poses and their rates, Newton
    iterations, residuals), why the next one did not ('' when all pass), and, when the first
    step alone is too long, its predicted move over the longest allowed (else 0)."""
    m: int
    z: np.ndarray
    zd: np.ndarray
    zdd: np.ndarray
    iterations: int
    residual: np.ndarray
    why: str
    over: float


def _leading(ok):
    """Number of leading True values of a 1-D boolean array."""
    bad = np.flatnonzero(~ok)
    return int(bad[0]) if bad.size else int(ok.size)


def _step_length(P, c):
    """The time step over which the Taylor predictor of the posture c moves the mechanism by
    0.7 STEP_MAX of its size (from the moves v, a of its velocities and accelerations:
    v tau + a tau^2 / 2 = S), or inf when it stands still."""
    v, a = float(P.move(c.zd)), float(P.move(c.zdd))
    goal = 0.7 * STEP_MAX * P.length
    root = v + math.sqrt(v * v + 2 * a * goal)
    return 2 * goal / root if root > 0 else math.inf


def _chunk_times(t, k, t0, hs, size):
    """Up to `size` times after t0: the grid times t[k], t[k+1], ..., each interval (from t0,
    then between grid times) divided into equal substeps of at most hs. Returns the times, the
    grid index each leads to (owner) and which are grid times."""
    out, owner, grid = [], [], []
    prev = t0
    for j in range(k, t.size):
        pieces = 1 if math.isinf(hs) else max(1, math.ceil((t[j] - prev) / hs - 1e-6))
        take = min(pieces, size - len(out))
        pts = prev + (t[j] - prev) * np.arange(1, take + 1) / pieces
        if take == pieces:
            pts[-1] = t[j]
        out.extend(pts)
        owner.extend([j] * take)
        grid.extend([False] * (pieces - 1) + [True] if take == pieces else [False] * take)
        prev = t[j]
        if len(out) >= size:
            break
    return np.array(out), np.array(owner, np.int64), np.array(grid, bool)


def _taylor(z, zd, zdd, tau):
    """The Taylor predictor z + tau zd + tau^2/2 zdd (poses (..., ng, 3), tau (...,))."""
    tau = np.asarray(tau, float)[..., None, None]
    return z + tau * zd + 0.5 * tau * tau * zdd


def _advance(P, c, times, val, rate, acc, tol, max_iter, orient):
    """Continue from the posture c to the ascending times (all after c.t), law tables
    (nlaw, K) on them. Newton solves every time at once from the Taylor predictor of c (the
    times whose predicted move from c exceeds CHUNK_REACH of the mechanism's size are left for
    later), then each interval between successive postures (c, the first time, the second...)
    is tested as one step of the continuation: the Taylor predictor of the interval's first
    posture moves at most STEP_MAX of the size, the residual is accepted, the corrector's move
    from that predictor is small against the predicted move, and the loop determinant keeps
    its sign, and J keeps its full rank. orient: the rows of the loop determinant (square), or
    None. Returns a _Step."""
    times = np.asarray(times, float)
    pred = _taylor(c.z, c.zd, c.zdd, times - c.t)
    reach = P.move(pred - c.z)
    if reach[0] > STEP_MAX * P.length:          # the first step is too long: no Newton
        return _Step(0, None, None, None, 0, None, _too_long(P, reach[0]),
                     reach[0] / (STEP_MAX * P.length))
    n = _leading(reach <= CHUNK_REACH * P.length)
    times, pred, val = times[:n], pred[:n], val[:, :n]
    accept = _accepted(P, P.qa(pred), val, tol)
    z, it, res, _ = _newton_batch(P, pred, val, accept, max_iter, orient)
    qa = P.qa(z)
    rra = P.rotated(z, P.active)
    J = P.jacobian(z, qa, rra)
    zd, zdd, full = _rates(P, z, qa, J, rate[:, :n], acc[:, :n], orient)
    # each interval as a step of the continuation, predicted from its first posture
    z0 = np.concatenate([c.z[None], z[:-1]])
    zd0 = np.concatenate([c.zd[None], zd[:-1]])
    zdd0 = np.concatenate([c.zdd[None], zdd[:-1]])
    p = _taylor(z0, zd0, zdd0, np.diff(np.concatenate([[c.t], times])))
    step, corr = P.move(p - z0), P.move(z - p)
    short = step <= STEP_MAX * P.length
    conv = res <= accept
    near = corr <= CORRECTION_RATIO * step + CORRECTION_FLOOR * P.length
    same = np.ones(n, bool) if orient is None else \
        np.linalg.slogdet(J[:, orient, :])[0] == c.sign
    m = _leading(short & conv & near & same & full)
    why = ""
    if m < n:
        why = (_too_long(P, step[m]) if not short[m] else
               f"Newton's residual {res[m]:.3g} above {accept[m]:.3g} after {it} iterations"
               if not conv[m] else
               f"a corrector's move of {corr[m]:.3g} m against a predicted move of "
               f"{step[m]:.3g} m (the solution jumps: another assembly branch?)"
               if not near[m] else
               "a change of sign of the loop determinant (another assembly branch)"
               if not same[m] else "a posture where the constraint Jacobian loses rank")
    if m == 0:
        return _Step(0, None, None, None, it, None, why, 0.0)
    return _Step(m, z[:m], zd[:m], zdd[:m], it, res[:m], why, 0.0)


def _too_long(P, step):
    return (f"a predicted move of {step:.3g} m (more than {STEP_MAX:g} of the mechanism's size "
            f"{P.length:.3g} m)")


def _singular_ratio(P, z):
    """Smallest over largest singular value of J W^-1/2 at poses z (ng, 3)."""
    J = P.jacobian(z) / np.sqrt(P.weight)
    s = np.linalg.svd(J, compute_uv=False) if J.size else np.zeros(1)
    return float(s.min() / s.max()) if s.max() > 0 else 0.0


#: Values (doubles) per time point of `rigid_reference` and of the laws of the drives that
#: follow it, fitted a little above the peak traced by tracemalloc over 30 001 time points
#: (robot_2dof 46.5 values per point, fourbar 35.3, slider_crank_press 38.7; the estimate is
#: 1.2 times these): per point (the grid, iterations, substeps, residual, chunk work), per
#: group (the poses z, zd, zdd: 9, and temporaries), per law (value, rate and acceleration
#: tables) and per drive that follows the reference (Mechanism's 'reference' law: its
#: coordinate histories and Hermite spline).
REFERENCE_VALUES_PER_POINT = 8
REFERENCE_VALUES_PER_GROUP = 10
REFERENCE_VALUES_PER_LAW = 4
REFERENCE_VALUES_PER_DRIVE = 10


def reference_memory(model, nt, following_drives=0):
    """Bytes (rough peak, an upper bound within a factor 2) of `rigid_reference(model, t)`
    on nt times and of the laws of `following_drives` drives that follow it: it grows like nt
    and is estimated before the reference is computed (Mechanism.reference)."""
    ng = _poses(model).ng
    nlaw = len(model.laws())
    per = (REFERENCE_VALUES_PER_POINT + REFERENCE_VALUES_PER_GROUP * ng
           + REFERENCE_VALUES_PER_LAW * nlaw + REFERENCE_VALUES_PER_DRIVE * following_drives)
    return 8.0 * float(nt) * per


def rigid_reference(model, t, q0=None, *, tol=1e-12, max_iter=20):
    """Position, velocity and acceleration analysis of the rigid mechanism on the times t.

    The first time is assembled from q0 (default: reference) with `assemble`; the next ones by
    continuation on that assembly branch: from the last posture solved, the Taylor predictor
    z + tau zd + tau^2/2 zdd (velocities from J zd = -Phi_t, accelerations from
    J zdd = gamma - Phi_q q_zz[zd, zd], `flexmbs.model.constraints.acceleration_rhs`), then Newton
    on several times at once. A time is accepted only as the continuation of the last posture:
    a predicted move of at most STEP_MAX of the mechanism's size, a residual below tol times
    the model's scale or at the rounding level of its coordinates, a corrector's move small
    against the predicted one (CORRECTION_RATIO, CORRECTION_FLOOR), the same sign of the loop
    determinant (when the constraint Jacobian's non-vanishing rows are square) and a Jacobian
    of full rank; otherwise the interval is subdivided and the intermediate postures solved
    first (substeps no longer than the predictor's reach, down to 2^-MAX_HALVINGS of a step).

    Returns
    -------
    RigidMotion

    Raises
    ------
    ModelError
        If the drives leave degrees of freedom free (the message says how many and which bodies
        they move); if the mechanism reaches a singular posture (a dead centre, the end of its
        reach: the message names the time and the constraint Jacobian's rank deficiency, its
        smallest singular value relative to its largest there), or cannot follow its drives
        there although the Jacobian has full rank (a drive law that jumps); or bad arguments.
    """
    P = _poses(model)
    t = np.atleast_1d(np.asarray(t, float))
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise ModelError(f"rigid_reference: t must be a non-empty 1-D array of finite times, "
                         f"got shape {np.shape(t)}")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ModelError("rigid_reference: t must be strictly increasing")
    first = assemble(model, t[0], q0, tol=tol)
    nz = 3 * P.ng
    sw = np.sqrt(P.weight)
    J0 = P.jacobian(first.z)
    s0 = np.linalg.svd(J0 / sw, compute_uv=False) if J0.shape[0] else np.zeros(0)
    smax0 = max(s0.max(initial=0.0), 1e-300)
    rank0 = int(np.sum(s0 > RANK_RTOL * smax0))
    if rank0 < nz:
        nfree, where = free_degrees_of_freedom(model, first.q, t[0])
        raise ModelError(f"rigid reference: {nz - rank0} free degree(s) of freedom remain at "
                         f"t = {t[0]:.6g} s (moving {', '.join(where)}); a rigid reference needs "
                         f"every degree of freedom driven (add a drive, a pin or a prescribed "
                         f"position)")
    # the loop determinant: on the rows that do not vanish (rigid links inside a group do,
    # at any poses: tested at the first and at turned and shifted ones) when they are as many
    # as the poses (no redundant row); Newton and the rates then solve these rows alone
    shake = first.z + np.array([0.1 * P.length, -0.07 * P.length, 0.3])
    size0 = np.maximum(np.abs(J0 / sw).max(axis=1, initial=0.0),
                       np.abs(P.jacobian(shake) / sw).max(axis=1, initial=0.0))
    live = np.flatnonzero(size0 > RANK_RTOL * smax0)
    orient = live if live.size == nz else None
    sign0 = float(np.linalg.slogdet(J0[live])[0]) if orient is not None else 0.0
    val, rate, acc = law_tables(model, t)
    nt = t.size
    z = np.zeros((nt, P.ng, 3))
    zd, zdd = np.zeros_like(z), np.zeros_like(z)
    its = np.zeros(nt, np.int64)
    subs = np.zeros(nt, np.int64)
    resid = np.zeros(nt)
    z[0], its[0], resid[0] = first.z, first.iterations, first.residual
    zd0, zdd0, _ = _rates(P, first.z[None], P.qa(first.z[None]), J0[None], rate[:, :1],
                          acc[:, :1], orient)
    zd[0], zdd[0] = zd0[0], zdd0[0]
    c = _Posture(t[0], z[0], zd[0], zdd[0], sign0)
    # chunks of up to `size` times solved together: the grid's, each interval divided into
    # substeps no longer than the predictor's reach (`_step_length`) and than hs, where steps
    # that long failed (a chunk that passes easily lets the next grow and hs double, one that
    # stops early sets the next's size; a first step that fails alone shrinks hs)
    dtmax = float(np.max(np.diff(t))) if nt > 1 else 0.0
    k, size, hs, pending = 1, 2, math.inf, 0
    while k < nt:
        times, owner, grid = _chunk_times(t, k, c.t, min(hs, _step_length(P, c)), size)
        if grid.all():
            lv, lr, la = val[:, owner], rate[:, owner], acc[:, owner]
        else:
            lv, lr, la = law_tables(model, times)
            for tab, on_grid in ((lv, val), (lr, rate), (la, acc)):
                tab[:, grid] = on_grid[:, owner[grid]]
        st = _advance(P, c, times, lv, lr, la, tol, max_iter if times.size == 1 else _CHUNK_ITER,
                      orient)
        pending += st.iterations
        if st.m:
            m = st.m
            c = _Posture(times[m - 1], st.z[-1], st.zd[-1], st.zdd[-1], sign0)
            np.add.at(subs, owner[:m][~grid[:m]], 1)
            done = owner[:m][grid[:m]]
            if done.size:
                z[done], zd[done], zdd[done] = (st.z[grid[:m]], st.zd[grid[:m]],
                                                st.zdd[grid[:m]])
                its[done], resid[done] = st.iterations, st.residual[grid[:m]]
                its[done[0]] += pending - st.iterations
                pending = 0
                k = int(done[-1]) + 1
            if m == times.size and st.iterations <= 3:
                size = min(2 * size, _CHUNK_MAX)
                hs = math.inf if 2 * hs > dtmax else 2 * hs
            elif m < times.size:
                size = m
            continue
        if times.size > 1:                      # a chunk's first time: alone, then substeps
            size = 1
            continue
        hs = (times[0] - c.t) / max(2.0, 2.0 * st.over)
        if hs < max((t[k] - t[k - 1]) * 2.0 ** -MAX_HALVINGS, 16 * np.finfo(float).eps * abs(t[k])):
            raise _stuck(P, c, t[k], st.why, hs)
    return RigidMotion(t=t, z=z, zd=zd, zdd=zdd, groups=P.groups, iterations=its,
                       residual=resid, substeps=subs, poses=P)


def _stuck(P, c, tk, why, hsub):
    """The error of a continuation that cannot go past the posture c (towards the time tk):
    a singular posture when the constraint Jacobian is nearly rank-deficient there."""
    ratio = _singular_ratio(P, c.z)
    if ratio < SINGULAR_RTOL:
        return ModelError(
            f"rigid reference: the mechanism reaches a singular posture at t = {c.t:.6g} s and "
            f"cannot pass it towards t = {tk:.6g} s: the constraint Jacobian is rank-deficient "
            f"there (its smallest singular value is {ratio:.2g} of its largest, below "
            f"{SINGULAR_RTOL:g}): a dead centre, a toggle or the end of the mechanism's reach, "
            f"where the drives do not determine the motion")
    return ModelError(
        f"rigid reference: the mechanism cannot follow its drives past t = {c.t:.6g} s towards "
        f"t = {tk:.6g} s, although the constraint Jacobian has full rank there (smallest "
        f"singular value {ratio:.2g} of its largest): {why} on a step of {hsub:.3g} s; a drive "
        f"law that jumps (not continuous in time)?")


def drive_velocities(model, q, t=0.0):
    """The rigid-body velocity field qd (ndof,) that the drives impose at state q and time t.

    Every rigid group (each beam, rigid body, lone node) moves rigidly about its centroid in q;
    the pose rates solve J zd = -Phi_t (minimum norm in the node metric: directions the drives
    leave free get no velocity). Use it to start a moving mechanism from rest without exciting
    its flexible bodies: ``simulate(model, t_end, h,
    initial=InitialConditions(q0=q0, qd0=drive_velocities(model, q0)))``
    (flexmbs.analysis.settings.InitialConditions).
    """
    P = _poses(model)
    q = np.asarray(q, float)
    if q.shape != (P.cm.ndof,) or not np.all(np.isfinite(q)):
        raise ModelError(f"drive_velocities: q must be a finite array of shape ({P.cm.ndof},), "
                         f"got shape {np.shape(q)}")
    _, rate, _ = _law_at(model, float(t))
    # poses about the actual centroids: the arms are the nodes' offsets in q
    qn = q.reshape(-1, 3)
    arms = np.zeros((qn.shape[0], 2))
    for nodes in P.groups:
        arms[nodes] = qn[nodes, :2] - qn[nodes, :2].mean(axis=0)
    J = P.jacobian(np.zeros((P.ng, 3)), q[P.active_dofs], arms[P.active])
    sw = np.sqrt(P.weight)
    zd = (_lstsq(J / sw, -constraint_rate(P.rows, rate)) / sw).reshape(P.ng, 3)
    w = zd[P.group_of]
    out = np.stack([w[:, 0] - w[:, 2] * arms[:, 1], w[:, 1] + w[:, 2] * arms[:, 0], w[:, 2]], axis=1)
    return out.ravel()
