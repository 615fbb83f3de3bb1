"""Building a planar mechanism: nodes, beams, masses, joints, motors, loads.

Absolute nodal coordinates (x, y, phi) in the inertial frame, three per node;
every body has its own nodes, never shared with another body (paper 3.3);
joints connect nodes by constraints (eq. 1). A model compiles, once per
structure, into the flat arrays of the Fortran core; a change of section
(a new design) only refreshes the element properties.

Examples
--------
>>> import numpy as np
>>> from flexmbs import Model, Material, Circle, TimeLaw, simulate
>>> steel = Material(E=210e9, nu=0.3, rho=7800)
>>> m = Model()
>>> arm = m.add_beam("arm", start=(0, 0), end=(1, 0), elements=4, material=steel,
...                  section=Circle(0.02))
>>> m.pin(arm.first)
>>> m.drive_rotation(arm.first, TimeLaw(lambda t: 0.5 * t**2, lambda t: t, lambda t: 1 + 0 * t))
>>> m.set_gravity(0, -9.81)
>>> r = simulate(m, t_end=0.1, h=1e-3)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.model.laws import as_law
from flexmbs.model.sections import Material, Section, real_number, section_properties

__all__ = ["Model", "Body", "CompiledModel"]

CON_LINEAR, CON_RIGID_X, CON_RIGID_Y, CON_PRISMATIC = 1, 2, 3, 4
MAX_EDOF, MAX_CDOF = 9, 5


@dataclass
class Body:
    """A named group of nodes: a beam, a rigid body or a point."""
    name: str
    kind: str
    nodes: list
    elements: list = field(default_factory=list)
    material: Material | None = None
    section: Section | None = None

    @property
    def first(self):
        """Id of the body's first node (a beam's root)."""
        return self.nodes[0]

    @property
    def last(self):
        """Id of the body's last node (a beam's free end)."""
        return self.nodes[-1]

    @property
    def dofs(self):
        """The body's coordinates (0-based), node by node: x, y, phi."""
        return np.array([[3 * n, 3 * n + 1, 3 * n + 2] for n in self.nodes]).ravel()


@dataclass
class _Row:
    kind: int
    dofs: list
    coef: list
    c0: float
    law: int  # 1-based law index, 0 = none
    lawcoef: float
    label: str


@dataclass
class CompiledModel:
    """Flat arrays of a model for the Fortran core (see fortran/model_data.f90)."""
    ndof: int
    nc: int
    n: int
    qref: np.ndarray
    lumped: np.ndarray
    gacc: np.ndarray
    el_nen: np.ndarray
    el_dofs: np.ndarray
    el_len: np.ndarray
    ld_dof: np.ndarray
    ld_law: np.ndarray
    ld_amp: np.ndarray
    c_kind: np.ndarray
    c_dofs: np.ndarray
    c_coef: np.ndarray
    c_c0: np.ndarray
    c_law: np.ndarray
    c_lawcoef: np.ndarray
    nel: int
    nload: int
    row_labels: list
    patterns: dict  # 'dense' / 'klu' -> maps
    nsd: int = 0                     # spring-dampers
    sd_dofs: np.ndarray | None = None   # (4, nsda) 1-based x_a, y_a, x_b, y_b
    sd_prop: np.ndarray | None = None   # (4, nsda) k, c, l0, f0
    el_eta: np.ndarray | None = None    # (nela) Kelvin–Voigt time of each element's material (s)


class Model:
    """A planar flexible mechanism. See the module docstring for an example."""

    def __init__(self, name="model"):
        if not isinstance(name, str):
            raise ModelError(f"Model name must be a string, got {name!r}")
        self.name = name
        self._nodes = []            # reference (x, y, phi)
        self.bodies = {}
        self._elements = []         # (node ids, length, body name)
        self._lumped = {}           # dof -> mass
        self._rows = []
        self._laws = []
        self._loads = []            # (dof, amp, law index)
        self._gravity = (0.0, 0.0)
        self._springs = []          # (node_a, node_b, k, c, l0, f0)
        self._compiled = None

    # ------------------------------------------------------------------ nodes
    @property
    def nnodes(self):
        return len(self._nodes)

    @property
    def ndof(self):
        return 3 * len(self._nodes)

    def _changed(self):
        self._compiled = None

    def add_node(self, x, y, phi=0.0):
        """A new node at (x, y) with cross-section rotation phi (rad); returns its id."""
        vals = [real_number(f"add_node: {k}", v) for k, v in (("x", x), ("y", y), ("phi", phi))]
        self._nodes.append(vals)
        self._changed()
        return len(self._nodes) - 1

    def _check_node(self, node, what="node"):
        if isinstance(node, (bool, np.bool_)) or not isinstance(node, (int, np.integer)):
            raise ModelError(f"{what}: expected a node id (int), got {node!r}")
        if not 0 <= node < len(self._nodes):
            raise ModelError(f"{what}: unknown node {node} (the model has {len(self._nodes)} nodes)")
        return int(node)

    def body(self, name):
        """The body called `name`."""
        if not isinstance(name, str):
            raise ModelError(f"body: expected a body name (str), got {name!r}")
        try:
            return self.bodies[name]
        except KeyError:
            raise ModelError(f"unknown body {name!r}; bodies are {sorted(self.bodies)}") from None

    def node_position(self, node):
        """Reference position (x, y) of a node."""
        node = self._check_node(node)
        return np.array(self._nodes[node][:2])

    def _check_new_name(self, name):
        if not isinstance(name, str) or not name:
            raise ModelError(f"body name must be a non-empty string, got {name!r}")
        if name in self.bodies:
            raise ModelError(f"a body called {name!r} already exists")

    def _beam_of(self, body, what):
        """A beam of this model given by its name or its Body."""
        if isinstance(body, Body):
            if self.bodies.get(body.name) is not body:
                raise ModelError(f"{what}: body {body.name!r} is not a body of this model")
            b = body
        else:
            b = self.body(body)
        if b.kind != "beam":
            raise ModelError(f"{what}: body {b.name!r} is not a beam")
        return b

    @staticmethod
    def _point(what, p):
        """A finite (x, y) pair of real numbers."""
        if isinstance(p, (str, bytes)) or not hasattr(p, "__len__") or len(p) != 2:
            raise ModelError(f"{what} must be an (x, y) pair of finite numbers, got {p!r}")
        return np.array([real_number(f"{what} {k}", v) for k, v in zip("xy", p)])

    def _new_body(self, name, kind, nodes):
        self._check_new_name(name)
        b = Body(name, kind, nodes)
        self.bodies[name] = b
        return b

    # ------------------------------------------------------------------ bodies
    def add_beam(self, name, start, end, elements=2, *, material=None, section=None, order=2):
        """A straight beam from `start` to `end` with `elements` elements.

        order=2: 3-node quadratic elements (accurate with 2 per arm, the default);
        order=1: 2-node linear elements. Returns the Body (its nodes run from start to end).
        The material's Kelvin–Voigt damping (Material.damping_time, or damping_ratio at
        damping_frequency) damps the beam's strain rates (fortran/beam2d.f90).
        """
        self._check_new_name(name)
        if not isinstance(section, Section):
            raise ModelError(f"beam {name!r}: section must be a flexmbs Section, got {section!r}")
        if material is not None and not isinstance(material, Material):
            raise ModelError(f"beam {name!r}: material must be a flexmbs Material, got {material!r}")
        section_properties(section, material)   # validates the pair
        if isinstance(order, (bool, np.bool_)) or order not in (1, 2):
            raise ModelError(f"beam {name!r}: order must be 1 or 2, got {order!r}")
        if isinstance(elements, (bool, np.bool_)) or not isinstance(elements, (int, np.integer)) \
                or elements < 1:
            raise ModelError(f"beam {name!r}: elements must be a positive integer, got {elements!r}")
        p0 = self._point(f"beam {name!r}: start", start)
        p1 = self._point(f"beam {name!r}: end", end)
        length = float(np.hypot(*(p1 - p0)))
        if length <= 0:
            raise ModelError(f"beam {name!r}: start and end coincide")
        phi = math.atan2(p1[1] - p0[1], p1[0] - p0[0])
        npts = elements * order + 1
        body = self._new_body(name, "beam", [])
        for k in range(npts):
            x, y = p0 + (p1 - p0) * k / (npts - 1)
            body.nodes.append(self.add_node(x, y, phi))
        for e in range(elements):
            ids = tuple(body.nodes[e * order:e * order + order + 1])
            body.elements.append(len(self._elements))
            self._elements.append((ids, length / elements, name))
        body.material = material
        body.section = section
        self._changed()
        return body

    def set_section(self, body, section):
        """Change the section of a beam (all its elements): a new design, same structure."""
        b = self._beam_of(body, "set_section")
        try:
            section_properties(section, b.material)
        except ModelError as exc:
            raise ModelError(f"beam {b.name!r}: {exc}") from None
        b.section = section

    def set_element_sections(self, body, sections):
        """Give each element of a beam its own section (list, root element first)."""
        b = self._beam_of(body, "set_element_sections")
        if isinstance(sections, (Section, str)) or not hasattr(sections, "__len__"):
            raise ModelError(f"set_element_sections: sections must be a list of {len(b.elements)} "
                             f"Sections (one per element of beam {b.name!r}), got {sections!r}")
        if len(sections) != len(b.elements):
            raise ModelError(f"beam {b.name!r} has {len(b.elements)} elements, got {len(sections)} sections")
        for k, s in enumerate(sections):
            try:
                section_properties(s, b.material)
            except ModelError as exc:
                raise ModelError(f"beam {b.name!r}, element {k + 1}: {exc}") from None
        b.section = list(sections)

    def with_sections(self, sections):
        """A copy of this model with other sections: {beam name: list of Sections (one per
        element, root first)}; the beams not named keep theirs. The copy shares everything
        else with this model (nodes, elements, constraints, laws, the compiled arrays and
        sparsity patterns with their KLU analysis, the law tables) and this model is left as
        it is: each design's sections belong to its own copy, so several designs can be
        simulated at once from one structure (Mechanism.design_model)."""
        import copy
        self.compile()                            # shared by the copies from now on
        self.__dict__.setdefault("_law_tables", {})
        out = copy.copy(self)
        out.bodies = dict(self.bodies)
        for name, secs in sections.items():
            b = self._beam_of(name, "with_sections")
            nb = Body(b.name, b.kind, b.nodes, b.elements, b.material, b.section)
            out.bodies[name] = nb
            out.set_element_sections(nb, secs)
        return out

    def element_sections(self, body):
        """The section of each element of a beam."""
        b = self._beam_of(body, "element_sections")
        if isinstance(b.section, list):
            return list(b.section)
        return [b.section] * len(b.elements)

    def add_point_mass(self, node, mass, inertia=0.0):
        """A point mass (kg) with optional rotary inertia (kg m^2) at a node."""
        node = self._check_node(node, "add_point_mass")
        mass = real_number(f"point mass at node {node}: mass", mass, nonnegative=True)
        inertia = real_number(f"point mass at node {node}: inertia", inertia, nonnegative=True)
        self._lumped[3 * node] = self._lumped.get(3 * node, 0.0) + float(mass)
        self._lumped[3 * node + 1] = self._lumped.get(3 * node + 1, 0.0) + float(mass)
        self._lumped[3 * node + 2] = self._lumped.get(3 * node + 2, 0.0) + float(inertia)
        self._changed()

    def add_rigid_body(self, name, nodes, mass, inertia, center=None):
        """A rigid body holding `nodes` at fixed distances and relative angles.

        A new node at `center` (default: the nodes' centroid) carries the mass (kg)
        and the inertia about it (kg m^2); each listed node is tied to it by a rigid
        link. Returns the Body (its first node is the centre).
        """
        self._check_new_name(name)
        if isinstance(nodes, (str, bytes)) or not hasattr(nodes, "__iter__"):
            raise ModelError(f"rigid body {name!r}: nodes must be a list of node ids, got {nodes!r}")
        ids = [self._check_node(n, f"rigid body {name!r}") for n in nodes]
        if not ids:
            raise ModelError(f"rigid body {name!r}: needs at least one node")
        real_number(f"rigid body {name!r}: mass", mass, nonnegative=True)
        real_number(f"rigid body {name!r}: inertia", inertia, nonnegative=True)
        pts = np.array([self._nodes[i][:2] for i in ids])
        c = pts.mean(axis=0) if center is None else self._point(f"rigid body {name!r}: center", center)
        cid = self.add_node(c[0], c[1], 0.0)
        self.add_point_mass(cid, mass, inertia)
        body = self._new_body(name, "rigid", [cid] + ids)
        for i in ids:
            self.rigid_link(cid, i)
        return body

    # ------------------------------------------------------------------ constraints
    def _law(self, law, name):
        law = as_law(law, name)
        self._laws.append(law)
        return len(self._laws)

    def _row(self, kind, dofs, coef, c0=0.0, law=0, lawcoef=0.0, label=""):
        self._rows.append(_Row(kind, list(dofs), list(coef), float(c0), int(law), float(lawcoef), label))
        self._changed()

    def clamp(self, node):
        """Clamp a node to the ground at its reference position and rotation."""
        node = self._check_node(node, "clamp")
        x, y, phi = self._nodes[node]
        for k, v, lab in ((0, x, "x"), (1, y, "y"), (2, phi, "phi")):
            self._row(CON_LINEAR, [3 * node + k], [1.0], v, label=f"clamp node {node} {lab}")

    def pin(self, node):
        """Pin a node to the ground at its reference position (rotation free)."""
        node = self._check_node(node, "pin")
        x, y, _ = self._nodes[node]
        self._row(CON_LINEAR, [3 * node], [1.0], x, label=f"pin node {node} x")
        self._row(CON_LINEAR, [3 * node + 1], [1.0], y, label=f"pin node {node} y")

    def hinge(self, node_a, node_b):
        """A hinge (pin joint) between two nodes of different bodies at the same point."""
        a = self._check_node(node_a, "hinge")
        b = self._check_node(node_b, "hinge")
        if a == b:
            raise ModelError(f"hinge: both nodes are node {a}")
        gap = math.dist(self._nodes[a][:2], self._nodes[b][:2])
        scale = max(1.0, max(abs(v) for n in self._nodes for v in n[:2]))
        if gap > 1e-9 * scale:
            raise ModelError(f"hinge between nodes {a} and {b}: they are {gap:.3g} m apart")
        for k, lab in ((0, "x"), (1, "y")):
            self._row(CON_LINEAR, [3 * a + k, 3 * b + k], [1.0, -1.0], 0.0, label=f"hinge {a}-{b} {lab}")

    def _coincide(self, a, b, what):
        gap = math.dist(self._nodes[a][:2], self._nodes[b][:2])
        scale = max(1.0, max(abs(v) for n in self._nodes for v in n[:2]))
        if gap > 1e-9 * scale:
            raise ModelError(f"{what} between nodes {a} and {b}: they are {gap:.3g} m apart")

    def _axis(self, axis, what):
        try:
            ax = np.asarray(axis, float)
        except (TypeError, ValueError):
            raise ModelError(f"{what}: axis must be a nonzero (x, y) pair, got {axis!r}") from None
        if ax.shape != (2,) or not np.all(np.isfinite(ax)) or not np.any(ax):
            raise ModelError(f"{what}: axis must be a finite nonzero (x, y) pair, got {axis!r}")
        return ax / np.linalg.norm(ax)

    def _line_point(self, node, point, what):
        """A point of a joint's line: `point`, or the node's reference position if None."""
        if point is None:
            return np.array(self._nodes[node][:2])
        return self._point(f"{what}: point", point)

    def weld(self, node_a, node_b):
        """A rigid connection of two nodes of different bodies at the same point.

        Three linear rows: the same position (x_b = x_a, y_b = y_a) and a fixed relative
        rotation (phi_b - phi_a kept at its reference value). The nodes must coincide in
        the reference configuration (for nodes apart, use `rigid_link`).
        """
        a = self._check_node(node_a, "weld node_a")
        b = self._check_node(node_b, "weld node_b")
        if a == b:
            raise ModelError(f"weld: both nodes are node {a}")
        self._coincide(a, b, "weld")
        for k, lab in ((0, "x"), (1, "y")):
            self._row(CON_LINEAR, [3 * a + k, 3 * b + k], [1.0, -1.0], 0.0, label=f"weld {a}-{b} {lab}")
        self._row(CON_LINEAR, [3 * b + 2, 3 * a + 2], [1.0, -1.0], self._nodes[b][2] - self._nodes[a][2],
                  label=f"weld {a}-{b} angle")

    def slider(self, node, axis, point=None):
        """A prismatic joint on the ground: `node` moves along a fixed line, its rotation fixed.

        The line passes through `point` (default: the node's reference position) with
        direction `axis` (any length). Two linear rows: n . (x - point) = 0 with n the unit
        normal of the axis, and phi = its reference value. The node must lie on the line in
        the reference configuration. Combine with `drive_translation` to prescribe the
        motion along the line, or leave it free (a slider block). For a line fixed in another
        body, use `prismatic`.
        """
        node = self._check_node(node, "slider")
        ax = self._axis(axis, "slider")
        pt = self._line_point(node, point, "slider")
        nrm = self._on_line(node, pt, ax, "slider", "the node")
        self._row(CON_LINEAR, [3 * node, 3 * node + 1], [nrm[0], nrm[1]], float(nrm @ pt),
                  label=f"slider node {node} normal")
        self._row(CON_LINEAR, [3 * node + 2], [1.0], self._nodes[node][2],
                  label=f"slider node {node} phi")

    def _on_line(self, node, pt, ax, what, who):
        """The unit normal of the line through pt along ax; ModelError if `node` (its
        reference position) is not on that line."""
        nrm = np.array([-ax[1], ax[0]])
        x = np.array(self._nodes[node][:2])
        off = float(nrm @ (x - pt))
        scale = max(1.0, max(abs(v) for n in self._nodes for v in n[:2]))
        if abs(off) > 1e-9 * scale:
            raise ModelError(f"{what}: node {node} at ({x[0]:.6g}, {x[1]:.6g}) is {abs(off):.3g} m "
                             f"off the line through point=({pt[0]:.6g}, {pt[1]:.6g}) along "
                             f"axis=({ax[0]:.6g}, {ax[1]:.6g}); {who} must lie on the line")
        return nrm

    def prismatic(self, node_a, node_b, axis, point=None):
        """A prismatic joint between two bodies: `node_b` slides along an axis fixed in the
        frame of `node_a` (its body), and keeps its rotation relative to `node_a`.

        `axis` (any length) is the direction in the reference configuration; the line passes
        through `point` (default: node b's reference position). Two rows:

        - n . (x_b - x_a) = c0, with n = R(phi_a - phi_a0) n0 the unit normal of the axis
          turning with node a and c0 = n0 . (point - x_a0) (0 when node b starts at node a):
          a nonlinear row (kind CON_PRISMATIC, fortran/constraints.f90);
        - phi_b - phi_a = its reference value (linear).

        Node b must lie on the line in the reference configuration. For a line fixed in the
        ground use `slider`.
        """
        a = self._check_node(node_a, "prismatic node_a")
        b = self._check_node(node_b, "prismatic node_b")
        if a == b:
            raise ModelError(f"prismatic: node_a and node_b are both node {a}; give the nodes "
                             "of two different bodies")
        ax = self._axis(axis, "prismatic")
        pt = self._line_point(b, point, "prismatic")
        nrm = self._on_line(b, pt, ax, "prismatic", "node_b")
        xa = np.array(self._nodes[a][:2])
        pa, pb = self._nodes[a][2], self._nodes[b][2]
        c, s = math.cos(pa), math.sin(pa)
        n0 = (c * nrm[0] + s * nrm[1], -s * nrm[0] + c * nrm[1])     # R(-phi_a0) n
        self._row(CON_PRISMATIC, [3 * a, 3 * a + 1, 3 * b, 3 * b + 1, 3 * a + 2], n0,
                  float(nrm @ (pt - xa)), label=f"prismatic {a}-{b} normal")
        self._row(CON_LINEAR, [3 * b + 2, 3 * a + 2], [1.0, -1.0], pb - pa,
                  label=f"prismatic {a}-{b} angle")

    def drive_translation(self, node, law, axis, point=None):
        """A linear motor: prescribe the position of `node` along `axis`.

        One linear row: a . (x - point) = law(t), with a the unit vector of `axis` and
        `point` (default: the node's reference position, so law(0) = 0 starts there).
        The other directions are free: combine with `slider` for a driven prismatic joint.
        `law` is a TimeLaw (analytic rate and acceleration), a callable or a number.
        """
        node = self._check_node(node, "drive_translation")
        ax = self._axis(axis, "drive_translation")
        pt = self._line_point(node, point, "drive_translation")
        li = self._law(law, f"translation drive at node {node}")
        self._row(CON_LINEAR, [3 * node, 3 * node + 1], [ax[0], ax[1]], float(ax @ pt), li, 1.0,
                  label=f"translation drive node {node}")

    def drive_rotation(self, node, law, relative_to=None):
        """A motor: prescribe the rotation of `node`.

        Absolute (default): phi_node(t) = law(t), the angle w.r.t. the ground.
        Relative: phi_node(t) - phi_other(t) = law(t) with other = `relative_to`.
        `law` is a TimeLaw (analytic rate and acceleration), a callable or a number.
        """
        node = self._check_node(node, "drive_rotation")
        if relative_to is not None and self._check_node(relative_to, "drive_rotation relative_to") == node:
            raise ModelError(f"drive_rotation: relative_to is the driven node {node} itself")
        li = self._law(law, f"motor at node {node}")
        if relative_to is None:
            self._row(CON_LINEAR, [3 * node + 2], [1.0], 0.0, li, 1.0, label=f"motor node {node}")
        else:
            other = self._check_node(relative_to, "drive_rotation relative_to")
            self._row(CON_LINEAR, [3 * node + 2, 3 * other + 2], [1.0, -1.0], 0.0, li, 1.0,
                      label=f"motor node {node} relative to node {other}")

    def prescribe_position(self, node, x=None, y=None):
        """Prescribe x(t) and/or y(t) of a node (laws, callables or numbers)."""
        node = self._check_node(node, "prescribe_position")
        if x is None and y is None:
            raise ModelError(f"prescribe_position at node {node}: give x, y or both (laws, "
                             "callables or numbers)")
        laws = [(k, as_law(law, f"position {lab} of node {node}"), lab)
                for k, law, lab in ((0, x, "x"), (1, y, "y")) if law is not None]
        for k, law, lab in laws:
            li = self._law(law, f"position {lab} of node {node}")
            self._row(CON_LINEAR, [3 * node + k], [1.0], 0.0, li, 1.0, label=f"position node {node} {lab}")

    def rigid_link(self, node_i, node_j):
        """Hold node j at its reference offset and relative angle in the frame of node i."""
        i = self._check_node(node_i, "rigid_link")
        j = self._check_node(node_j, "rigid_link")
        xi, yi, pi = self._nodes[i]
        xj, yj, pj = self._nodes[j]
        c, s = math.cos(pi), math.sin(pi)
        dx = c * (xj - xi) + s * (yj - yi)
        dy = -s * (xj - xi) + c * (yj - yi)
        self._row(CON_RIGID_X, [3 * i, 3 * j, 3 * i + 2], [dx, dy], 0.0, label=f"rigid link {i}-{j} x")
        self._row(CON_RIGID_Y, [3 * i + 1, 3 * j + 1, 3 * i + 2], [dx, dy], 0.0, label=f"rigid link {i}-{j} y")
        self._row(CON_LINEAR, [3 * j + 2, 3 * i + 2], [1.0, -1.0], pj - pi, label=f"rigid link {i}-{j} angle")

    # ------------------------------------------------------------------ loads
    def set_gravity(self, gx, gy):
        """Uniform gravity acceleration (m/s^2), any direction; acts on beams and masses."""
        self._gravity = (real_number("set_gravity: gx", gx), real_number("set_gravity: gy", gy))
        self._changed()

    def add_load(self, node, fx=0.0, fy=0.0, moment=0.0, law=None):
        """Nodal force (N) and moment (N m), multiplied by law(t) if given (constant otherwise)."""
        node = self._check_node(node, "add_load")
        comps = [real_number(f"load at node {node}: {lab}", v)
                 for lab, v in (("fx", fx), ("fy", fy), ("moment", moment))]
        li = self._law(law, f"load at node {node}") if law is not None else 0
        for k, v in enumerate(comps):
            if v != 0.0:
                self._loads.append((3 * node + k, v, li))
        self._changed()

    def add_spring_damper(self, node_a, node_b, stiffness, damping=0.0, free_length=None,
                          preload=0.0):
        """A point-to-point spring-damper between the positions of two nodes.

        The force acts along the current line between the nodes, with tension
        N = stiffness (l - free_length) + damping dl/dt + preload (positive: pulls the
        nodes together); l is the current distance, `free_length` defaults to the
        reference distance. Rotations are not involved. Units: N/m, N s/m, m, N.
        Returns the index of the spring-damper.
        """
        a = self._check_node(node_a, "add_spring_damper node_a")
        b = self._check_node(node_b, "add_spring_damper node_b")
        if a == b:
            raise ModelError(f"add_spring_damper: node_a and node_b are both node {a}")
        vals = {}
        for name, v in (("stiffness", stiffness), ("damping", damping), ("preload", preload)):
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ModelError(f"add_spring_damper: {name} must be a number, got {v!r}") from None
            if not math.isfinite(v) or (name != "preload" and v < 0):
                allowed = "finite" if name == "preload" else "finite and >= 0"
                raise ModelError(f"add_spring_damper: {name} must be {allowed}, got {v!r}")
            vals[name] = v
        dist = math.dist(self._nodes[a][:2], self._nodes[b][:2])
        if free_length is None:
            l0 = dist
        else:
            try:
                l0 = float(free_length)
            except (TypeError, ValueError):
                raise ModelError(f"add_spring_damper: free_length must be a number or None, "
                                 f"got {free_length!r}") from None
            if not (math.isfinite(l0) and l0 >= 0):
                raise ModelError(f"add_spring_damper: free_length must be finite and >= 0, "
                                 f"got {free_length!r}")
        if dist <= 0:
            raise ModelError(f"add_spring_damper: nodes {a} and {b} coincide in the reference "
                             "configuration (the direction of the force is undefined there)")
        self._springs.append((a, b, vals["stiffness"], vals["damping"], l0, vals["preload"]))
        self._changed()
        return len(self._springs) - 1

    # ------------------------------------------------------------------ compile
    def reference_coordinates(self):
        """q of the reference (undeformed) configuration."""
        return np.array(self._nodes, dtype=float).ravel()

    def element_properties(self):
        """(5, nel) array [EA, kGA, EI, rhoA, rhoI] of every element for the current sections."""
        props = np.zeros((5, max(len(self._elements), 1)))
        for b in self.bodies.values():
            if b.kind != "beam":
                continue
            for e, sec in zip(b.elements, self.element_sections(b)):
                props[:, e] = section_properties(sec, b.material)
        return props

    def compile(self):
        """Flat arrays and sparsity patterns (cached until the structure changes)."""
        if self._compiled is not None:
            return self._compiled
        if not self._nodes:
            raise ModelError("the model has no nodes")
        ndof = self.ndof
        nc = len(self._rows)
        n = ndof + nc
        nel = len(self._elements)
        nela = max(nel, 1)
        el_nen = np.full(nela, 2, np.int32)
        el_dofs = np.ones((MAX_EDOF, nela), np.int32, order="F")
        el_len = np.ones(nela)
        el_eta = np.zeros(nela)
        for e, (ids, length, body) in enumerate(self._elements):
            mat = self.bodies[body].material
            el_eta[e] = mat.damping_time if mat is not None else 0.0
            el_nen[e] = len(ids)
            d = np.array([[3 * i, 3 * i + 1, 3 * i + 2] for i in ids]).ravel()
            el_dofs[:len(d), e] = d + 1
            el_len[e] = length
        lumped = np.zeros(ndof)
        for d, mval in self._lumped.items():
            lumped[d] = mval
        gacc = np.zeros(ndof)
        gacc[0::3], gacc[1::3] = self._gravity
        nca = max(nc, 1)
        c_kind = np.ones(nca, np.int32)
        c_dofs = np.zeros((MAX_CDOF, nca), np.int32, order="F")
        c_coef = np.zeros((MAX_CDOF, nca), order="F")
        c_c0 = np.zeros(nca)
        c_law = np.zeros(nca, np.int32)
        c_lawcoef = np.zeros(nca)
        for r, row in enumerate(self._rows):
            c_kind[r] = row.kind
            c_dofs[:len(row.dofs), r] = np.array(row.dofs) + 1
            c_coef[:len(row.coef), r] = row.coef
            c_c0[r] = row.c0
            c_law[r] = row.law
            c_lawcoef[r] = row.lawcoef
        nlda = max(len(self._loads), 1)
        ld_dof = np.ones(nlda, np.int32)
        ld_law = np.zeros(nlda, np.int32)
        ld_amp = np.zeros(nlda)
        for k, (d, amp, li) in enumerate(self._loads):
            ld_dof[k], ld_amp[k], ld_law[k] = d + 1, amp, li
        nsda = max(len(self._springs), 1)
        sd_dofs = np.ones((4, nsda), np.int32, order="F")
        sd_prop = np.zeros((4, nsda), order="F")
        for k, (a, b, ks, cs, l0, f0) in enumerate(self._springs):
            sd_dofs[:, k] = [3 * a + 1, 3 * a + 2, 3 * b + 1, 3 * b + 2]
            sd_prop[:, k] = [ks, cs, l0, f0]
        cm = CompiledModel(ndof=ndof, nc=nc, n=n, qref=self.reference_coordinates(), lumped=lumped,
                           gacc=gacc, el_nen=el_nen, el_dofs=el_dofs, el_len=el_len,
                           ld_dof=ld_dof, ld_law=ld_law, ld_amp=ld_amp, c_kind=c_kind,
                           c_dofs=c_dofs, c_coef=c_coef, c_c0=c_c0, c_law=c_law,
                           c_lawcoef=c_lawcoef, nel=nel, nload=len(self._loads),
                           row_labels=[r.label for r in self._rows], patterns={},
                           nsd=len(self._springs), sd_dofs=sd_dofs, sd_prop=sd_prop,
                           el_eta=el_eta)
        self._compiled = cm
        return cm

    def pattern(self, kind):
        """Value positions of the iteration matrix: kind 'dense' or 'klu' (cached)."""
        if not isinstance(kind, str) or kind not in ("dense", "klu"):
            raise ModelError(f"unknown matrix storage {kind!r}: use 'dense' or 'klu'")
        cm = self.compile()
        if kind in cm.patterns:
            return cm.patterns[kind]
        n, ndof, nc = cm.n, cm.ndof, cm.nc
        nela = cm.el_dofs.shape[1]
        nca = cm.c_dofs.shape[1]
        rows, cols = [], []
        # element blocks
        ed = cm.el_dofs.astype(np.int64) - 1                  # (9, nela)
        valid = np.arange(MAX_EDOF)[:, None] < 3 * cm.el_nen[None, :]
        ed = np.where(valid, ed, 0)
        er = np.repeat(ed[:, None, :], MAX_EDOF, axis=1)      # (a, b, e) -> row dof a
        ec = np.repeat(ed[None, :, :], MAX_EDOF, axis=0)      # (a, b, e) -> col dof b
        rows.append(er.ravel())
        cols.append(ec.ravel())
        # diagonal
        rows.append(np.arange(ndof))
        cols.append(np.arange(ndof))
        # constraints
        cd = cm.c_dofs.astype(np.int64) - 1                   # (MAX_CDOF, nca)
        cvalid = cd >= 0
        cd0 = np.where(cvalid, cd, 0)
        rr = ndof + np.arange(nca)[None, :].repeat(MAX_CDOF, 0)
        rr = np.where(cvalid, rr, 0) if nc > 0 else np.zeros_like(cd0)
        if nc > 0:
            rows += [rr.ravel(), cd0.ravel()]
            cols += [cd0.ravel(), rr.ravel()]
            qa = np.repeat(cd0[:, None, :], MAX_CDOF, axis=1)
            qb = np.repeat(cd0[None, :, :], MAX_CDOF, axis=0)
            rows.append(qa.ravel())
            cols.append(qb.ravel())
        # spring-damper blocks (4 x 4 of x_a, y_a, x_b, y_b)
        sdd = cm.sd_dofs.astype(np.int64) - 1                 # (4, nsda)
        sr = np.repeat(sdd[:, None, :], 4, axis=1)
        sc = np.repeat(sdd[None, :, :], 4, axis=0)
        if cm.nsd > 0:
            rows.append(sr.ravel())
            cols.append(sc.ravel())
        r_all = np.concatenate(rows)
        c_all = np.concatenate(cols)
        if kind == "dense":
            def pos(r, c):
                return (np.asarray(c, np.int64) * n + np.asarray(r, np.int64) + 1)
            ap = np.zeros(1, np.int32)
            ai = np.zeros(1, np.int32)
            nnz = n * n
        elif kind == "klu":
            keys = np.unique(c_all * n + r_all)
            ccol = keys // n
            ap = np.searchsorted(ccol, np.arange(n + 1)).astype(np.int32)
            ai = (keys % n).astype(np.int32)
            nnz = int(keys.size)

            def pos(r, c):
                return np.searchsorted(keys, np.asarray(c, np.int64) * n + np.asarray(r, np.int64)) + 1
        else:
            raise ModelError(f"unknown matrix storage {kind!r}: use 'dense' or 'klu'")
        # Fortran reads map_el(:, e) as a 9 x 9 array, row index fastest
        map_el = np.asfortranarray(np.transpose(pos(er, ec), (1, 0, 2)).reshape(MAX_EDOF * MAX_EDOF, nela))
        map_diag = pos(np.arange(ndof), np.arange(ndof)).astype(np.int32)
        map_cq = np.asfortranarray(pos(rr, cd0).astype(np.int32))
        map_qc = np.asfortranarray(pos(cd0, rr).astype(np.int32))
        qa = np.repeat(cd0[:, None, :], MAX_CDOF, axis=1)
        qb = np.repeat(cd0[None, :, :], MAX_CDOF, axis=0)
        map_qq = np.asfortranarray(np.transpose(pos(qa, qb), (1, 0, 2)).reshape(MAX_CDOF * MAX_CDOF, nca))
        map_sd = np.asfortranarray(np.transpose(pos(sr, sc), (1, 0, 2)).reshape(16, sdd.shape[1]))
        pat = dict(nnz=nnz, ap=ap, ai=ai, map_el=map_el.astype(np.int32), map_diag=map_diag,
                   map_sd=map_sd.astype(np.int32),
                   map_cq=map_cq, map_qc=map_qc, map_qq=map_qq.astype(np.int32))
        cm.patterns[kind] = pat
        return pat

    def laws(self):
        """The model's time laws (index k+1 in the compiled arrays)."""
        return list(self._laws)

    def row_label(self, r):
        """Description of constraint row r (0-based), for messages."""
        if isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, np.integer)):
            raise ModelError(f"row_label: expected a constraint row index (int), got {r!r}")
        return self._rows[r].label if 0 <= r < len(self._rows) else f"row {r}"
