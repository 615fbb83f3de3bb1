"""Equivalent static loads (ESL) from the nonlinear finite-element simulation (paper 3.3).

The simulation works in absolute nodal coordinates, so the deformation of a body is not
separated from its rigid motion. This module recovers it in a post-processing step, body by
body, through a corotational frame (paper eqs. 16-19), and builds the static load cases of
the weakly coupled method:

1. reference configuration: the undeformed (stress-free) reference configuration of the model;
2. the body's tangent stiffness K_t^b is extracted from the global one at that state
   (`flexmbs.analysis.simulate.system_matrices`; each body has its own nodes) and expressed in the
   body frame; the root conditions of the frame remove its rigid-body modes;
3. for every time step n at once (vectorized):
   3.1 frame origin x_0 and angle of the body frame (`TangentFrame`, `ChordFrame`),
   3.2 local displacements u_n^b of eq. (18):
       u_i = R(a_n)^T (x_i - x_0) - X_i,  psi_i = (phi_i - a_n) - (phi_i,ref - a_ref),
       where X_i = R(a_ref)^T (x_i,ref - x_0,ref) is the node in the undeformed body frame,
   3.3 the ESL g_eq,n^b = K_t^b u_n^b of eq. (19) on the free coordinates.

Coordinates are expressed in the body frame itself (x along the body's reference frame axis),
i.e. the paper's vector rotated by R(a_ref)^T; the inertial components of a local vector v are
R(a_n) v, the paper's R_0,n^b v.

Since the internal forces and the tangent stiffness are linear in the section stiffnesses
(EA, kGA, EI), the body stiffness is stored as parts, one per element and stiffness:
K^b(p) = sum_e sum_j s_je(p) K_je^b, which gives dK^b/dp from the section property
derivatives (`Case.element_property_derivatives`, `Section.property_derivatives`).

Examples
--------
>>> from flexmbs.methods.esl import TangentFrame, equivalent_static_loads   # doctest: +SKIP
>>> loads = equivalent_static_loads(model, result, [("arm1", TangentFrame(arm1.first))])
>>> loads["arm1"].g_eq.shape                     # (time steps, free body coordinates)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexmbs.analysis.simulate import Result
from flexmbs.core import system_matrices
from flexmbs.errors import ModelError
from flexmbs.model.arrays import Body, Model

__all__ = ["TangentFrame", "ChordFrame", "BodyStiffness", "BodyLoads", "EquivalentStaticLoads",
           "local_displacements", "equivalent_static_loads", "esl_change", "StaticSolution",
           "solve_static", "static_response"]


# ---------------------------------------------------------------------------- frames
class TangentFrame:
    """Corotational frame tangent to the body at one node (paper 3.3).

    Origin at the node, x axis along the node's cross-section direction: the node's local
    displacement and rotation are zero by construction, so the static load cases are
    clamped there (fixed-free beams for a frame at the root).

    Parameters
    ----------
    node : int
        Model node id; must belong to the body.
    """

    kind = "tangent"

    def __init__(self, node):
        self.node = int(node)

    def _index(self, nodes):
        try:
            return list(nodes).index(self.node)
        except ValueError:
            raise ModelError(f"tangent frame node {self.node} is not a node of the body "
                             f"(nodes {list(nodes)})") from None

    def fixed_dofs(self, nodes):
        """Body-local coordinates held by the frame: the node's x, y and rotation."""
        k = self._index(nodes)
        return [3 * k, 3 * k + 1, 3 * k + 2]

    def place(self, x, y, phi, nodes):
        """Origin (n, 2) and angle (n,) of the frame from nodal x, y, phi of shape (n, nnodes)."""
        k = self._index(nodes)
        return np.column_stack([x[:, k], y[:, k]]), phi[:, k].copy()

    def __repr__(self):
        return f"TangentFrame(node={self.node})"


class ChordFrame:
    """Corotational chord frame: origin at `root`, x axis through the node `tip`.

    Held coordinates: the root's translations and the tip's transverse displacement (a
    simply supported body); the frame angle is taken on the branch nearest the root node's
    rotation, so it is continuous in time.

    Parameters
    ----------
    root, tip : int
        Model node ids of the body.
    """

    kind = "chord"

    def __init__(self, root, tip):
        self.root = int(root)
        self.tip = int(tip)
        if self.root == self.tip:
            raise ModelError("chord frame: root and tip must be different nodes")

    def _index(self, nodes, node):
        try:
            return list(nodes).index(node)
        except ValueError:
            raise ModelError(f"chord frame node {node} is not a node of the body "
                             f"(nodes {list(nodes)})") from None

    def fixed_dofs(self, nodes):
        """Body-local coordinates held: root x and y, tip transverse y."""
        r = self._index(nodes, self.root)
        t = self._index(nodes, self.tip)
        return [3 * r, 3 * r + 1, 3 * t + 1]

    def place(self, x, y, phi, nodes):
        r = self._index(nodes, self.root)
        t = self._index(nodes, self.tip)
        a = np.arctan2(y[:, t] - y[:, r], x[:, t] - x[:, r])
        ref = phi[:, r]
        a = ref + np.angle(np.exp(1j * (a - ref)))
        return np.column_stack([x[:, r], y[:, r]]), a

    def __repr__(self):
        return f"ChordFrame(root={self.root}, tip={self.tip})"


def _frame_from_spec(body: Body, spec):
    """A frame object from a frame, a node id (tangent frame) or 'tangent'/'chord'."""
    if hasattr(spec, "place") and hasattr(spec, "fixed_dofs"):
        return spec
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        return TangentFrame(int(spec))
    if spec == "tangent":
        return TangentFrame(body.first)
    if spec == "chord":
        return ChordFrame(body.first, body.last)
    raise ModelError(f"body {body.name!r}: frame must be a TangentFrame/ChordFrame, a node id, "
                     f"'tangent' or 'chord', got {spec!r}")


def _split(q_body):
    q = np.atleast_2d(np.asarray(q_body, float))
    return q[:, 0::3], q[:, 1::3], q[:, 2::3]


def _rotation_blocks(angle, nn):
    """Block-diagonal T = diag(R(angle), 1) repeated over nn nodes: (3nn, 3nn)."""
    c, s = np.cos(angle), np.sin(angle)
    block = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.kron(np.eye(nn), block)


def local_displacements(q_body, q_ref_body, nodes, frame):
    """Local displacement vectors u_n^b of eq. (18), all time steps at once.

    Parameters
    ----------
    q_body : (nt, 3 nn) nodal coordinates (x, y, phi) of the body, node by node.
    q_ref_body : (3 nn,) the same in the undeformed reference configuration.
    nodes : the body's node ids (in the order of the columns).
    frame : TangentFrame or ChordFrame.

    Returns
    -------
    u : (nt, 3 nn) local displacements and rotations in the body frame.
    origin : (nt, 2) frame origin x_0.
    angle : (nt,) frame angle a_n w.r.t. the inertial x axis (the rotation of R_0,n is
        a_n; the body frame coordinates are aligned with the reference frame angle a_ref).
    ref_angle : float, the frame angle a_ref in the reference configuration.
    """
    x, y, phi = _split(q_body)
    xr, yr, phir = _split(q_ref_body)
    origin, angle = frame.place(x, y, phi, nodes)
    oref, aref = frame.place(xr, yr, phir, nodes)
    aref = float(aref[0])
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    dx, dy = x - origin[:, :1], y - origin[:, 1:]
    cr, sr = np.cos(aref), np.sin(aref)
    X = cr * (xr - oref[:, :1]) + sr * (yr - oref[:, 1:])
    Y = -sr * (xr - oref[:, :1]) + cr * (yr - oref[:, 1:])
    u = np.empty_like(np.atleast_2d(np.asarray(q_body, float)))
    u[:, 0::3] = c * dx + s * dy - X
    u[:, 1::3] = -s * dx + c * dy - Y
    u[:, 2::3] = (phi - angle[:, None]) - (phir - aref)
    return u, origin, angle, aref


# ---------------------------------------------------------------------------- stiffness
class BodyStiffness:
    """Tangent stiffness of one body at the reference state, in its body frame (paper 3.3 step 2).

    Stored as parts per element and per stiffness (EA, kGA, EI), so that for any element
    properties s (5, nel) of the model, K^b = sum_e sum_j s[j, e] parts[j, e] (the reference
    state is stress free, so K_t there is linear in the stiffnesses).

    Attributes
    ----------
    name : body name.  nodes : node ids.  dofs : model coordinates of the body (0-based).
    elements : global element indices of the body.  frame : the corotational frame.
    ref_angle : frame angle in the reference configuration.
    fixed, free : body-local coordinate indices held by the frame / left free.
    parts : (3, nel_b, 3nn, 3nn) stiffness parts in the body frame (all coordinates).
    """

    def __init__(self, model: Model, body, frame="tangent"):
        if not isinstance(model, Model):
            raise ModelError(f"BodyStiffness expects a flexmbs Model, got {type(model).__name__}")
        b = model.body(body) if isinstance(body, str) else body
        if b.kind != "beam" or not b.elements:
            raise ModelError(f"body {b.name!r} is not a flexible beam: it has no stiffness for ESL")
        self.name = b.name
        self.nodes = list(b.nodes)
        self.dofs = b.dofs
        self.elements = list(b.elements)
        self.frame = _frame_from_spec(b, frame)
        nd = len(self.dofs)
        self.fixed = np.array(sorted(set(self.frame.fixed_dofs(self.nodes))), int)
        self.free = np.setdiff1d(np.arange(nd), self.fixed)
        qref = model.reference_coordinates()
        self.q_ref = qref[self.dofs]
        _, _, _, self.ref_angle = local_displacements(self.q_ref[None, :], self.q_ref,
                                                      self.nodes, self.frame)
        T = _rotation_blocks(self.ref_angle, len(self.nodes))
        nel = model.compile().nel
        self.parts = np.zeros((3, len(self.elements), nd, nd))
        ix = np.ix_(self.dofs, self.dofs)
        for k, e in enumerate(self.elements):
            for j in range(3):
                props = np.zeros((5, nel))
                props[j, e] = 1.0
                _, S = system_matrices(model, qref, props=props)   # K_t at the reference
                Kb = T.T @ S[ix] @ T
                self.parts[j, k] = 0.5 * (Kb + Kb.T)
        self._parts_free = np.ascontiguousarray(self.parts[:, :, self.free][:, :, :, self.free])

    @property
    def nfree(self):
        return self.free.size

    def _check_props(self, props):
        props = np.asarray(props, float)
        if props.ndim < 2 or props.shape[0] < 3 or props.shape[1] <= max(self.elements):
            raise ModelError(f"body {self.name!r}: element properties must have shape (5, nel), "
                             f"got {props.shape}")
        return props[:3, self.elements]

    def matrix(self, props, full=False):
        """K^b for element properties props (5, nel): free coordinates (default) or all."""
        s = self._check_props(props)
        parts = self.parts if full else self._parts_free
        return np.einsum("je,jeab->ab", s, parts)

    def derivative(self, dprops, full=False):
        """dK^b/dp (nv, nf, nf) from element property derivatives dprops (5, nel, nv)."""
        dprops = np.asarray(dprops, float)
        if dprops.ndim != 3 or dprops.shape[0] < 3:
            raise ModelError(f"body {self.name!r}: property derivatives must have shape "
                             f"(5, nel, nv), got {dprops.shape}")
        ds = dprops[:3, self.elements, :]
        parts = self.parts if full else self._parts_free
        return np.einsum("jev,jeab->vab", ds, parts)

    def design_variables(self, dprops):
        """Indices of the design variables on which this body's stiffness depends."""
        ds = np.asarray(dprops, float)[:3, self.elements, :]
        return np.flatnonzero(np.any(ds != 0, axis=(0, 1)))


# ---------------------------------------------------------------------------- loads
@dataclass
class BodyLoads:
    """The ESL of one body over all time steps (paper eq. 19).

    Attributes
    ----------
    name : body name.
    stiffness : BodyStiffness (frame, free coordinates, stiffness parts).
    props : (5, nel) element properties of the design the loads were computed at.
    t : (nt,) time grid.
    origin : (nt, 2), angle : (nt,) corotational frame at every step.
    u : (nt, 3nn) local displacements u_n^b (eq. 18), all body coordinates.
    g_eq : (nt, nf) equivalent static loads on the free coordinates (eq. 19).
    """
    name: str
    stiffness: BodyStiffness
    props: np.ndarray
    t: np.ndarray
    origin: np.ndarray
    angle: np.ndarray
    u: np.ndarray
    g_eq: np.ndarray

    @property
    def u_free(self):
        """(nt, nf) local displacements on the free coordinates."""
        return self.u[:, self.stiffness.free]

    def to_inertial(self, v_local):
        """Rotate local in-plane vectors (nt, 2) to inertial components R_0,n v (nt, 2)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        v = np.asarray(v_local, float)
        return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])

    def node_displacement(self, node):
        """(nt, 2) local displacement of a body node, inertial components (R_0,n u_i)."""
        k = self.stiffness.nodes.index(int(node))
        return self.to_inertial(self.u[:, 3 * k:3 * k + 2])


class EquivalentStaticLoads:
    """ESL of several bodies from one simulation: a mapping body name -> BodyLoads."""

    def __init__(self, bodies):
        self.bodies = list(bodies)
        self._by_name = {b.name: b for b in self.bodies}

    def __getitem__(self, name):
        return self._by_name[name]

    def __iter__(self):
        return iter(self.bodies)

    def __len__(self):
        return len(self.bodies)

    def names(self):
        return [b.name for b in self.bodies]

    def change(self, previous):
        """Relative change of eq. (25) w.r.t. `previous`, per body: dict name -> value."""
        return esl_change(self, previous)


def esl_change(current, previous):
    """Relative ESL change of eq. (25), per body.

    sum_n ||g_n,it - g_n,it-1|| / sum_n ||g_n,it-1||, norms over the free coordinates of each
    time step. Returns a dict body name -> value.
    """
    out = {}
    for b in current:
        p = previous[b.name]
        if p.g_eq.shape != b.g_eq.shape:
            raise ModelError(f"body {b.name!r}: ESL of different shapes {p.g_eq.shape} and "
                             f"{b.g_eq.shape} (different time grids?)")
        num = np.linalg.norm(b.g_eq - p.g_eq, axis=1).sum()
        den = np.linalg.norm(p.g_eq, axis=1).sum()
        out[b.name] = float(num / den) if den > 0 else (0.0 if num == 0 else float("inf"))
    return out


def equivalent_static_loads(model: Model, result: Result, frames, stiffness=None, props=None):
    """Equivalent static loads of eq. (19) for bodies of a simulated model, all steps at once.

    Parameters
    ----------
    model : Model
        The simulated model (its reference configuration is the reference state).
    result : Result
        Its simulation; must hold the coordinates of every listed body.
    frames : list of (body name, frame)
        frame: TangentFrame / ChordFrame, a node id (tangent frame there), 'tangent' (at the
        body's first node) or 'chord' (first to last node).
    stiffness : dict name -> BodyStiffness, optional
        Precomputed stiffness parts (they depend on the structure only, not on the design);
        built when missing.
    props : (5, nel) array, optional
        Element properties defining K^b; default: the model's current sections.

    Returns
    -------
    EquivalentStaticLoads
    """
    if props is None:
        props = model.element_properties()
    props = np.asarray(props, float)
    stiffness = {} if stiffness is None else stiffness
    qref = model.reference_coordinates()
    out = []
    for name, spec in frames:
        b = model.body(name) if isinstance(name, str) else name
        ks = stiffness.get(b.name)
        if ks is None:
            ks = BodyStiffness(model, b, spec)
        try:
            qb = result.coordinates(b.dofs)
        except ModelError as exc:
            raise ModelError(f"ESL of body {b.name!r}: {exc}") from None
        u, origin, angle, _ = local_displacements(qb, qref[b.dofs], ks.nodes, ks.frame)
        K = ks.matrix(props)
        g = u[:, ks.free] @ K          # K symmetric: g_n = K u_n for every row
        out.append(BodyLoads(name=b.name, stiffness=ks, props=props.copy(), t=result.t,
                             origin=origin, angle=angle, u=u, g_eq=g))
    return EquivalentStaticLoads(out)


# ---------------------------------------------------------------------------- static solution
@dataclass
class StaticSolution:
    """Static response of one body to all its load cases: K^b(p) u_n = g_eq,n (problem 23).

    Attributes
    ----------
    u : (nt, nf) local displacements on the free coordinates.
    du : (nv, nt, nf) their derivatives du/dp (du/dp = -K^-1 (dK/dp) u), or None.
    """
    u: np.ndarray
    du: np.ndarray | None


def _factor(stiffness: BodyStiffness, props):
    """K^b(p) and its Cholesky factorization (ModelError if not positive definite)."""
    import scipy.linalg as sla      # here: importing flexmbs does not load scipy.linalg
    K = stiffness.matrix(props)
    try:
        return K, sla.cho_factor(K, check_finite=False)
    except sla.LinAlgError:
        raise ModelError(f"body {stiffness.name!r}: stiffness not positive definite at this "
                         "design (a zero section, or the frame does not hold the rigid modes)") from None


def solve_static(stiffness: BodyStiffness, g_eq, props, dprops=None):
    """Solve K^b(p) u_n = g_eq,n for every load case with one factorization (problem 23).

    Parameters
    ----------
    stiffness : BodyStiffness
    g_eq : (nt, nf) load cases.
    props : (5, nel) element properties of the design p.
    dprops : (5, nel, nv) their derivatives, optional: then du/dp is returned too, by
        du/dp_v = -K^-1 (dK/dp_v) u, reusing the factorization for all cases.

    Returns
    -------
    StaticSolution
    """
    import scipy.linalg as sla
    K, fac = _factor(stiffness, props)
    g = np.asarray(g_eq, float)
    u = sla.cho_solve(fac, g.T, check_finite=False).T
    du = None
    if dprops is not None:
        dK = stiffness.derivative(dprops)                      # (nv, nf, nf)
        rhs = np.einsum("vab,nb->avn", dK, u).reshape(K.shape[0], -1)
        du = -sla.cho_solve(fac, rhs, check_finite=False).reshape(K.shape[0], dK.shape[0], -1)
        du = np.transpose(du, (1, 2, 0))                       # (nv, nt, nf)
    return StaticSolution(u=u, du=du)


def static_response(stiffness: BodyStiffness, g_eq, props, columns, dprops=None):
    """Selected free coordinates of K^b(p)^-1 g_eq,n for all load cases, with derivatives.

    The cheap form of `solve_static` when only a few coordinates enter the constraints: with
    the adjoint vectors lambda = K^-1 e_c (one per selected coordinate c, one factorization),
    u_c = lambda^T g and du_c/dp_v = -lambda^T (dK/dp_v) u.

    Parameters
    ----------
    stiffness : BodyStiffness
    g_eq : (nt, nf) load cases.
    props : (5, nel) element properties of the design.
    columns : sequence of indices into the free coordinates.
    dprops : (5, nel, nv) property derivatives, optional.

    Returns
    -------
    u : (nt, nsel); du : (nv, nt, nsel) or None.
    """
    import scipy.linalg as sla
    K, fac = _factor(stiffness, props)
    cols = np.asarray(columns, int)
    g = np.asarray(g_eq, float)
    if dprops is None:
        E = np.zeros((K.shape[0], cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        lam = sla.cho_solve(fac, E, check_finite=False)            # (nf, nsel)
        return g @ lam, None
    Kinv = sla.cho_solve(fac, np.eye(K.shape[0]), check_finite=False)
    Kinv = 0.5 * (Kinv + Kinv.T)
    U = g @ Kinv                                                   # (nt, nf), K symmetric
    lam = Kinv[:, cols]                                            # (nf, nsel)
    dK = stiffness.derivative(dprops)                              # (nv, nf, nf)
    du = -np.stack([U @ (dK[v] @ lam) for v in range(dK.shape[0])])
    return U[:, cols], du
