"""The motion of a simulated mechanism as drawable and exportable data: every body's nodes and
elements, and the fields on them, at chosen time steps.

`scene(problem, result, steps)` gathers, for the steps asked (0-based indices of the time
grid), what the animation (flexmbs.visual.animation) draws and the ParaView export (flexmbs.visual.export)
writes:

- points: every node of every body, in node-id order (a node shared by a body and a point
  mass on it appears once); their flexible positions, rotations and the positions and
  rotations of the same nodes in the rigid reference (Mechanism.reference);
- cells: each beam element (its 2 or 3 nodes, root first, as the model numbers them), each
  rigid body's outline (segments between its points through its centre; a closed polygon of
  its points when it has 3 or more), each point mass (one node);
- point fields: displacement (from the position at t = 0), deflection (flexible minus rigid
  position), deviation (the deflection's length), rotation and its deflection;
- cell fields of the beam elements (NaN on the other cells): the axial strain, shear strain
  and curvature (mean of the element's Gauss stations, flexmbs.responses.strain) and the normal
  stress (largest of the Gauss stations, flexmbs.responses.stress; NaN for a section without a
  depth).

Library code: nothing here names a mechanism; the bodies come from the description.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.model.description import GROUND, PointMass
from flexmbs.responses.strain import columns, gauss_points, raw_strains, shape
from flexmbs.responses.stress import beam_stress

__all__ = ["Scene", "scene", "frame_steps", "CELL_FIELDS", "POINT_FIELDS"]

#: Point fields of a Scene: name -> (unit, description).
POINT_FIELDS = {
    "displacement": ("m", "position minus the position at t = 0 (x, y)"),
    "deflection": ("m", "flexible minus rigid-reference position (x, y)"),
    "deviation": ("m", "length of the deflection"),
    "rotation": ("rad", "rotation phi of the node's cross-section"),
    "rotation_deflection": ("rad", "rotation minus the rigid reference's"),
}
#: Cell fields of a Scene (beam elements; NaN on other cells): name -> (unit, description).
CELL_FIELDS = {
    "axial_strain": ("1", "axial strain Gamma_1, mean of the Gauss stations"),
    "shear_strain": ("1", "shear strain Gamma_2, mean of the Gauss stations"),
    "curvature": ("1/m", "curvature change kappa, mean of the Gauss stations"),
    "stress": ("Pa", "normal stress E (|eps| + c |kappa|), largest of the Gauss stations"),
}


@dataclass
class Scene:
    """Nodes, cells and fields of a mechanism at some time steps (see the module docstring).

    Attributes
    ----------
    steps : (k,) 0-based time steps; t : (k,) their times.
    nodes : (n,) node ids of the points.
    position, rigid : (k, n, 2) flexible and rigid-reference positions.
    rotation, rigid_rotation : (k, n) rotations (rad).
    cells : list of (body name, kind, indices into the points): kind 'beam' (one element,
        its nodes in the model's order: root, [middle,] end), 'rigid' (the polyline of the
        outline), 'mass' (one point).
    cell_fields : name -> (k, ncells) values (NaN on cells that are not beam elements).
    bodies : body name -> kind ('beam', 'rigid', 'mass').
    joints : list of (joint type, index into the points, grounded?).
    """
    steps: np.ndarray
    t: np.ndarray
    nodes: np.ndarray
    position: np.ndarray
    rigid: np.ndarray
    rotation: np.ndarray
    rigid_rotation: np.ndarray
    cells: list = field(default_factory=list)
    cell_fields: dict = field(default_factory=dict)
    bodies: dict = field(default_factory=dict)
    joints: list = field(default_factory=list)

    @property
    def deflection(self):
        """(k, n, 2) flexible minus rigid position."""
        return self.position - self.rigid

    @property
    def deviation(self):
        """(k, n) length of the deflection."""
        return np.hypot(*np.moveaxis(self.deflection, -1, 0))

    def point_fields(self):
        """name -> (k, n) or (k, n, 2) values of every point field (POINT_FIELDS)."""
        return {"displacement": self.position - self.position[:1],
                "deflection": self.deflection, "deviation": self.deviation,
                "rotation": self.rotation,
                "rotation_deflection": self.rotation - self.rigid_rotation}

    def magnified(self, factor):
        """(k, n, 2) positions with the deflection magnified: rigid + factor (flexible - rigid).
        Nodes that coincide in both motions (a joint's two nodes) stay together."""
        return self.rigid + float(factor) * self.deflection

    def size(self):
        """A length of the mechanism: the mean of the width and height of its rigid motion."""
        pts = self.rigid.reshape(-1, 2)
        return max(float(np.ptp(pts[:, 0]) + np.ptp(pts[:, 1])) / 2, 1e-9)


def frame_steps(nt, frames=None):
    """0-based steps of `frames` frames spread evenly over a grid of nt time points, the first
    and last included (every step when frames is None or >= nt)."""
    if frames is None or frames >= nt:
        return np.arange(nt)
    if frames < 2:
        raise ModelError(f"frames must be at least 2, got {frames}")
    return np.unique(np.linspace(0, nt - 1, int(frames)).round().astype(int))


def _outline(nodes):
    """The outline of a rigid body (centre node first, then its points) as a polyline of
    positions in `nodes`: a closed polygon of 3 or more points, else the points through the
    centre."""
    centre, pts = nodes[0], list(nodes[1:])
    if len(pts) >= 3:
        return pts + [pts[0]]
    return pts[:1] + [centre] + pts[1:]


class _AtSteps:
    """A Result's time grid and coordinates at some steps only (what the strain and stress
    functions read)."""

    def __init__(self, result, steps):
        self.t, self.q, self.dofs = result.t[steps], result.q[steps], result.dofs


def _element_fields(model, result, body):
    """(k, nel) mean strains and the largest normal stress of a beam's elements."""

    axial, shear, curv = _mean_strains(model, result, body)
    try:
        stress = beam_stress(model, result, body).normal.max(axis=2)
    except ModelError:      # a section without a depth, a beam without a material
        stress = np.full(axial.shape, np.nan)
    return {"axial_strain": axial, "shear_strain": shear, "curvature": curv, "stress": stress}


def _mean_strains(model, result, body):
    """(k, nel) mean axial strain, shear strain and curvature (from the reference) of a beam's
    elements at their Gauss stations (flexmbs.responses.strain)."""

    b = model.body(body)
    cm = model.compile()
    ids = np.asarray(b.elements, int)
    nen = int(cm.el_nen[ids[0]])
    n, dn = shape(nen, gauss_points(nen))
    edofs = (cm.el_dofs[:3 * nen, ids] - 1).T.astype(np.int64)
    jac = 0.5 * cm.el_len[ids]
    ref = raw_strains(cm.qref[edofs], n, dn, jac)
    now = raw_strains(result.q[:, columns(result.dofs, edofs)], n, dn, jac)
    return tuple((a - r).mean(axis=-1) for a, r in zip(now, ref))


def scene(problem, result, steps=None, model=None):
    """The Scene of a simulated problem at `steps` (default: every step).

    Parameters
    ----------
    problem : flexmbs.problem.Problem
    result : flexmbs.analysis.simulate.Result of the problem, simulated with store='all'
    steps : array of 0-based time steps, optional
    model : the model simulated (default: result.design_model, set by Problem.simulate, else
        the problem's model): the sections of the stresses
    """
    mech = problem.mechanism
    m = mech.model
    nt = result.t.size
    steps = np.arange(nt) if steps is None else np.asarray(steps, int)
    if steps.size == 0 or steps.min() < 0 or steps.max() >= nt:
        raise ModelError(f"steps must be 0-based time steps in [0, {nt - 1}], got {steps!r}")
    if model is None:
        model = getattr(result, "design_model", None)
    if model is None:
        model = m
    bodies = {name: b.kind for name, b in m.bodies.items()}
    bodies.update({b.name: "mass" for b in problem.description.bodies if isinstance(b, PointMass)})
    nodes = sorted({n for b in m.bodies.values() for n in b.nodes})
    need = np.array([3 * n + k for n in nodes for k in range(3)])
    have = np.isin(need, result.dofs)
    if not np.all(have):
        raise ModelError("the motion needs every body's coordinates: simulate with "
                         "store='all' (Problem.simulate(x, store='all') or "
                         "Problem.evaluate(x, store='all'))")
    index = {n: i for i, n in enumerate(nodes)}
    cols = np.searchsorted(result.dofs, need).reshape(-1, 3)
    q = result.q[steps]
    ref = mech.reference.q[steps]
    rcols = need.reshape(-1, 3)
    out = Scene(steps=steps, t=np.asarray(result.t)[steps], nodes=np.array(nodes),
                position=np.stack([q[:, cols[:, 0]], q[:, cols[:, 1]]], axis=-1),
                rigid=np.stack([ref[:, rcols[:, 0]], ref[:, rcols[:, 1]]], axis=-1),
                rotation=q[:, cols[:, 2]], rigid_rotation=ref[:, rcols[:, 2]], bodies=bodies)
    fields = {k: [] for k in CELL_FIELDS}
    at = _AtSteps(result, steps)
    k = steps.size
    for name, b in m.bodies.items():
        if b.kind == "beam":
            for e in b.elements:
                ids = m._elements[e][0]
                out.cells.append((name, "beam", [index[n] for n in ids]))
            for key, v in _element_fields(model, at, name).items():
                fields[key].append(v)
        elif b.kind == "rigid":
            out.cells.append((name, "rigid", [index[n] for n in _outline(b.nodes)]))
            for key in fields:
                fields[key].append(np.full((k, 1), np.nan))
    for b in problem.description.bodies:    # point masses, on their own node or another body's
        if isinstance(b, PointMass):
            out.cells.append((b.name, "mass", [index[mech.node[(b.name, b.at)]]]))
            for key in fields:
                fields[key].append(np.full((k, 1), np.nan))
    out.cell_fields = {key: np.concatenate(v, axis=1) for key, v in fields.items()}
    for j in problem.description.joints:
        body = j.body if j.body is not None else next(b for b in j.bodies if b != GROUND)
        grounded = j.body is not None or GROUND in (j.bodies or ())
        out.joints.append((j.type, index[mech.node[(body, j.at)]], grounded))
    return out
