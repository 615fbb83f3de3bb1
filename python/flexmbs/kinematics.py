"""Position analysis of a model with every flexible body rigid: assembly and rigid reference.

The rigid mechanism of a Model moves its **rigid groups** (`rigid_groups`: each beam's nodes,
each rigid body's nodes, every other node alone; bodies sharing a node form one group) as rigid
bodies in their reference shape. A group's pose z_g = (cx, cy, theta) places its reference
centroid at (cx, cy) and turns it by theta; node n of the group is at

    (x_n, y_n) = (cx, cy) + R(theta) r_n,     phi_n = phi_n0 + theta,

r_n its reference offset from the centroid. The constraint rows of the model
(`flexmbs.constraints`) become equations Phi(q(z), t) = 0 on the 3 ngroups poses, with
Jacobian J = Phi_q dq/dz. Rows inside a group (the rigid links of a rigid body) hold
identically.

- `assemble` closes the loops at one time from approximate positions: the group poses are
  fitted to the given nodes (least squares), then moved to the nearest pose that satisfies
  every row, nearest in the node positions (Gauss-Newton steps of minimum norm in the metric
  n_g |dc|^2 + sum_n |r_n|^2 dtheta^2, which is the nodes' squared displacement to second
  order; lstsq, so consistent redundant rows do no harm).
- `rigid_reference` is the position analysis on a time grid: Newton at each time from a
  quadratic extrapolation of the previous solutions, then velocities J zd = -Phi_t and
  accelerations J zdd = gamma - Phi_q q_zz[zd, zd] at every time at once (batched SVD). It
  works on the poses and on the coordinates of the nodes the constraint rows use only, so its
  cost does not grow with the number of elements; the other nodes follow from the poses by
  rigid transforms when asked (`RigidMotion.coordinates`, or every node: `RigidMotion.q`).
- `drive_velocities` is the rigid-body velocity field the drives impose at one state (for a
  start from rest of a moving mechanism).

Example
-------
>>> import numpy as np
>>> from flexmbs import Model, Material, Circle, TimeLaw
>>> from flexmbs.kinematics import rigid_reference, drive_velocities
>>> mat, sec = Material(7e10, 0.3, 2700), Circle(0.02)
>>> m = Model()
>>> crank = m.add_beam("crank", (0, 0), (0.1, 0), 2, material=mat, section=sec)
>>> rod = m.add_beam("rod", (0.1, 0), (0.4, 0), 2, material=mat, section=sec)
>>> m.pin(crank.first); m.hinge(crank.last, rod.first); m.prescribe_position(rod.last, y=0.0)
>>> m.drive_rotation(crank.first, TimeLaw(lambda t: 10 * t, lambda t: 10 + 0 * t, lambda t: 0 * t))
>>> ref = rigid_reference(m, np.linspace(0.0, 0.1, 11))
>>> round(float(ref.q[-1, 3 * rod.last]), 6)        # 0.1 cos 1 + sqrt(0.3^2 - 0.1^2 sin^2 1)
0.341987
>>> qd0 = drive_velocities(m, m.reference_coordinates())   # use as simulate(..., qd0=qd0)
>>> round(float(qd0[3 * crank.last + 1]), 6)                # 10 rad/s x 0.1 m
1.0
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from flexmbs.constraints import (acceleration_rhs, constraint_rate, constraint_values,
                                 jacobian_entries, law_tables, row_table)
from flexmbs.errors import ModelError

__all__ = ["rigid_groups", "assemble", "Assembly", "rigid_reference", "RigidMotion",
           "drive_velocities", "free_degrees_of_freedom"]

#: relative singular value below which J is taken as rank-deficient
RANK_RTOL = 1e-9


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
        phi = constraint_values(P.rows, P.qa(z), law_val)
        res = float(np.max(np.abs(phi))) if phi.size else 0.0
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
        if (res <= tol * P.scale and move <= tol * P.scale) or it >= max_iter:
            return z, it, res, phi
        # damping: halve a step that makes the constraint residual grow a lot
        lam = 1.0
        for _ in range(30):
            znew = z + lam * step.reshape(-1, 3)
            rn = float(np.max(np.abs(constraint_values(P.rows, P.qa(znew), law_val)))) if nc else 0.0
            if rn <= max(2 * res, tol * P.scale) or lam < 1e-6:
                break
            lam *= 0.5
        it += 1
        if lam * move <= 1e-15 * P.scale and res > tol * P.scale:
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
        Convergence: max |Phi| <= tol * max(1, largest |x|, |y| of the reference).
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
    if not res <= tol * P.scale:
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
    groups; iterations : (nt,) Newton iterations per time; residual : (nt,) max |Phi|.

    The node histories follow from the poses by rigid transforms: `coordinates(dofs, rate)`
    gives those of some coordinates (cost and memory nt x len(dofs); the last
    MEMO_ENTRIES asked of up to MEMO_VALUES values are kept, the reference being the same
    for every design of a case); q, qd, qdd (nt, ndof) hold every node's, computed on first use and kept (nt x
    ndof values each).
    """
    #: `coordinates` results kept (a response asks for the same few coordinates at every
    #: design: 4 calls and ~1.3 ms of a 17 ms evaluation of the paper's robot, session 7)
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


def _extrapolate(t, z, k, idx):
    """Guess of the poses at times t[idx] from the solutions z[:k] (quadratic extrapolation of
    the last three, linear from two, constant from one)."""
    tk = t[idx][:, None, None]
    if k >= 3:
        t0, t1, t2 = t[k - 3], t[k - 2], t[k - 1]
        l0 = (tk - t1) * (tk - t2) / ((t0 - t1) * (t0 - t2))
        l1 = (tk - t0) * (tk - t2) / ((t1 - t0) * (t1 - t2))
        l2 = (tk - t0) * (tk - t1) / ((t2 - t0) * (t2 - t1))
        return l0 * z[k - 3] + l1 * z[k - 2] + l2 * z[k - 1]
    if k == 2:
        return z[1] + (z[1] - z[0]) * (tk - t[1]) / (t[1] - t[0])
    return np.broadcast_to(z[0], (idx.size,) + z.shape[1:]).copy()


def _newton_batch(P, z, law_val, tol, max_iter):
    """Newton on the poses of several times at once, z (K, ng, 3), law_val (nlaw, K): minimum
    norm steps from the batched SVD of J W^-1/2. Returns (z, iterations, residuals (K,),
    Phi (K, nc))."""
    sw = np.sqrt(P.weight)
    K = z.shape[0]
    phi = constraint_values(P.rows, P.qa(z), law_val)
    res = np.max(np.abs(phi), axis=-1) if phi.shape[-1] else np.zeros(K)
    it = 0
    target = 0.01 * tol * P.scale
    while it < max_iter and np.any(res > target):
        it += 1
        u, s, vt = np.linalg.svd(P.jacobian(z) / sw, full_matrices=False)
        rtol = RANK_RTOL * s.max(axis=-1)
        z = z + (_svd_solve(u, s, vt, -phi, rtol) / sw).reshape(z.shape)
        phi = constraint_values(P.rows, P.qa(z), law_val)
        new = np.max(np.abs(phi), axis=-1)
        floor = np.all(new <= tol * P.scale) and np.all((new > 0.25 * res) | (new <= target))
        res = new
        if floor:
            break
    return z, it, res, phi


def rigid_reference(model, t, q0=None, *, tol=1e-12, max_iter=20):
    """Position, velocity and acceleration analysis of the rigid mechanism on the times t.

    The first time is assembled from q0 (default: reference) with `assemble`; each next one by
    Newton from a quadratic extrapolation of the previous solutions, so the mechanism stays on
    its assembly branch. Velocities solve J zd = -Phi_t, accelerations
    J zdd = gamma - Phi_q q_zz[zd, zd] (`flexmbs.constraints.acceleration_rhs`), at every time
    at once.

    Returns
    -------
    RigidMotion

    Raises
    ------
    ModelError
        If the drives leave degrees of freedom free (the message says how many and which bodies
        they move), if the mechanism reaches a singular posture or cannot follow its drives
        (the message names the time), or bad arguments.
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
    J0 = P.jacobian(first.z) / np.sqrt(P.weight)
    s0 = np.linalg.svd(J0, compute_uv=False) if J0.shape[0] else np.zeros(0)
    rank0 = int(np.sum(s0 > RANK_RTOL * max(s0.max(initial=0.0), 1e-300)))
    if rank0 < nz:
        nfree, where = free_degrees_of_freedom(model, first.q, t[0])
        raise ModelError(f"rigid reference: {nz - rank0} free degree(s) of freedom remain at "
                         f"t = {t[0]:.6g} s (moving {', '.join(where)}); a rigid reference needs "
                         f"every degree of freedom driven (add a drive, a pin or a prescribed "
                         f"position)")
    val, rate, acc = law_tables(model, t)
    nt = t.size
    z = np.zeros((nt, P.ng, 3))
    its = np.zeros(nt, np.int64)
    resid = np.zeros(nt)
    z[0], its[0], resid[0] = first.z, first.iterations, first.residual
    # continuation in chunks of times solved together: a chunk's guess extrapolates the last
    # three solutions; a chunk that needs more than a few Newton iterations is halved (down to
    # one time, which gets max_iter), a fast one lets the next grow
    k, size = 1, 2
    while k < nt:
        size = min(size, nt - k)
        idx = np.arange(k, k + size)
        guess = _extrapolate(t, z, k, idx)
        limit = max_iter if size == 1 else _CHUNK_ITER
        zk, it, res, phi = _newton_batch(P, guess, val[:, idx], tol, limit)
        ok = res <= tol * P.scale
        if not np.all(ok):
            if size > 1:
                size //= 2
                continue
            raise ModelError(f"rigid reference: the mechanism cannot follow its drives at "
                             f"t = {t[k]:.6g} s (max |Phi| = {res[0]:.3g} after {it} Newton "
                             f"iterations: past a singular posture or out of reach); largest "
                             f"residuals: {_worst_rows(model, phi[0])}")
        z[idx], its[idx], resid[idx] = zk, it, res
        k += size
        if it <= 3:
            size = min(2 * size, _CHUNK_MAX)
    # velocities and accelerations of the poses, on the active nodes' coordinates only
    qa = P.qa(z)
    rra = P.rotated(z, P.active)
    J = P.jacobian(z, qa, rra)                                      # (nt, nc, nz)
    sw = np.sqrt(P.weight)
    u, s, vt = np.linalg.svd(J / sw, full_matrices=False)
    smax = s.max(axis=-1)
    rank = np.sum(s > RANK_RTOL * smax[:, None], axis=-1)
    bad = np.flatnonzero(rank < rank0)
    if bad.size:
        k = int(bad[0])
        raise ModelError(f"rigid reference: the mechanism reaches a singular posture at "
                         f"t = {t[k]:.6g} s (the constraint Jacobian loses rank: {int(rank[k])} "
                         f"of {rank0}); the drives do not determine the motion there")
    rtol = RANK_RTOL * smax
    zd = (_svd_solve(u, s, vt, -constraint_rate(P.rows, rate), rtol) / sw).reshape(nt, P.ng, 3)
    qda = P.qd(z, zd, P.active)
    gamma = acceleration_rhs(P.rows, qa, qda, acc)
    cen = P.centripetal(z, zd, P.active)
    _, _, pq = jacobian_entries(P.rows, qa)                         # Phi_q entries (nt, nent)
    r_idx, node, comp, _ = P._entries
    cols = 3 * node + comp
    pqc = np.zeros((nt, P.rows.nc))
    np.add.at(pqc.T, r_idx, (pq * cen[:, cols]).T)
    zdd = (_svd_solve(u, s, vt, gamma - pqc, rtol) / sw).reshape(nt, P.ng, 3)
    return RigidMotion(t=t, z=z, zd=zd, zdd=zdd, groups=P.groups, iterations=its,
                       residual=resid, poses=P)


def drive_velocities(model, q, t=0.0):
    """The rigid-body velocity field qd (ndof,) that the drives impose at state q and time t.

    Every rigid group (each beam, rigid body, lone node) moves rigidly about its centroid in q;
    the pose rates solve J zd = -Phi_t (minimum norm in the node metric: directions the drives
    leave free get no velocity). Use it to start a moving mechanism from rest without exciting
    its flexible bodies: ``simulate(model, t_end, qd0=drive_velocities(model, q0))``.
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
