"""A described mechanism built once onto a flexmbs Model: named points, designs, time laws.

`Mechanism(description)` builds the structure once (nodes, elements, joints, drives, loads,
springs): a new design only changes section properties (`set_design`), never the structure,
its sparsity pattern or its KLU analysis. It also builds the rigid reference of the same
description (every beam rigid; drives whose law is 'reference' replaced by the `paths` they
follow) on the same nodes, so that node ids, and so coordinates, agree between the two.

Every body has its own nodes (paper 3.3): a beam's end nodes are its points `from` and `to`; a
rigid body has a node at its centre and one at each of its points, tied by rigid links; a point
mass is a node (or adds to the node of the body it sits `on`). Joints tie the nodes two bodies
have at the same point.
"""
from __future__ import annotations

import math
import threading
import warnings

import numpy as np

from flexmbs.errors import CaseError, ModelError, ResourceError
from flexmbs.model.arrays import Model
from flexmbs.model.constraints import constraint_values, law_tables
from flexmbs.model.description import (GROUND, Beam, Description, PointMass, Rigid, Section,
                                 body_points, design_layout)
from flexmbs.model.kinematics import assemble, drive_velocities, reference_memory, rigid_reference
from flexmbs.model.laws import TimeLaw
from flexmbs.model.sections import Circle, GivenSection, Material, Rectangle, Tube, has_complex
from flexmbs.resources import MAX_STEPS, time_steps
from flexmbs.resources import CaseLimit, format_bytes, limit_hint, limit_source, memory_limit

__all__ = ["Mechanism", "make_law", "section_at"]

#: section dimension -> (section class parameter)
_PARAM = {"diameter": "d", "thickness": "t", "width": "b", "height": "h"}


# ----------------------------------------------------------------------------- laws
def make_law(spec, name="law", shift=0.0, joined=False):
    """A TimeLaw (analytic value, rate, acceleration) from a description Law, plus `shift`.

    joined=True (a drive's or a path's law, a motion): the segments of a 'piecewise' law
    must meet at their breaks, to 1e-6 of the value's size: a jump of the value is a
    ModelError naming the law, the break and both values; a jump of the rate (an impulsive
    change of speed) is a warning."""
    k = spec.type
    if k == "constant":
        return _analytic(name, "constant", c=spec.value + shift)
    if k == "ramp_to_speed":
        w = spec.speed if spec.speed is not None else spec.speed_rpm * 2 * math.pi / 60
        return _analytic(name, "ramp", w=w, tr=spec.ramp_s, s0=spec.start + shift)
    if k == "smooth_step":
        return _analytic(name, "smooth_step", a=spec.start + shift, b=spec.end + shift,
                         t0=spec.t0, d=spec.t1 - spec.t0)
    if k == "harmonic":
        return _analytic(name, "harmonic", amp=spec.amplitude,
                         om=2 * math.pi * spec.frequency_hz, ph=spec.phase,
                         off=spec.offset, shift=shift)
    if k == "cycloid":
        return _analytic(name, "cycloid", h=spec.stroke, T=spec.period, s0=spec.start + shift,
                         om=2 * math.pi / spec.period)
    if k == "polynomial":
        c = np.array(spec.coefficients, float)
        c[0] = c[0] + shift if c.size else shift
        p = np.polynomial.Polynomial(c)
        return TimeLaw(p, p.deriv(1), p.deriv(2), name=name)
    if k == "samples":
        return TimeLaw.samples(spec.times, np.array(spec.values) + shift, name=name,
                               interpolation=spec.interpolation, extrapolate=spec.extrapolate)
    if k == "piecewise":
        parts = [make_law(g.law, f"{name} segment {i + 1}", shift, joined)
                 for i, g in enumerate(spec.segments)]
        breaks = [g.until for g in spec.segments[:-1]]
        if joined:
            _check_joins(parts, breaks, name)
        return TimeLaw.piecewise(breaks, parts, name=name)
    if k == "sum":
        total = TimeLaw.sum([make_law(law, f"{name} term {i + 1}", shift if i == 0 else 0.0)
                             for i, law in enumerate(spec.laws)], name=name)
        if joined:      # the terms may jump if their jumps cancel: the sum may not
            _check_sum_joins(total, _breaks(spec), name)
        return total
    raise ModelError(f"{name}: a law of type {k!r} has no formula (it is computed from the "
                     "rigid reference)")


class _Formula:
    """Value (which = 0), rate (1) or acceleration (2) of an analytic law of `kind` with
    parameters `p`: a module-level callable, so that a law (and a Problem) can be pickled and
    sent to another process."""

    def __init__(self, kind, which, p):
        self.kind, self.which, self.p = kind, which, p

    def __call__(self, t):
        return getattr(self, "_" + self.kind)(t, **self.p)

    def _constant(self, t, c):
        z = np.zeros_like
        return c + z(t) if self.which == 0 else z(t)

    def _ramp(self, t, w, tr, s0):
        z = np.zeros_like
        if self.which == 0:
            return s0 + np.where(t <= tr, 0.5 * w / tr * t * t, w * (t - 0.5 * tr))
        if self.which == 1:
            return np.where(t <= tr, w / tr * t, w + z(t))
        return np.where(t <= tr, w / tr + z(t), z(t))

    def _smooth_step(self, t, a, b, t0, d):
        def s(t):
            return np.clip((t - t0) / d, 0.0, 1.0)
        if self.which == 0:
            return a + (b - a) * s(t) ** 3 * (10 - 15 * s(t) + 6 * s(t) ** 2)
        if self.which == 1:
            return (b - a) / d * 30 * s(t) ** 2 * (1 - s(t)) ** 2
        return (b - a) / d ** 2 * 60 * s(t) * (1 - s(t)) * (1 - 2 * s(t))

    def _harmonic(self, t, amp, om, ph, off, shift):
        if self.which == 0:
            return off + shift + amp * np.sin(om * t + ph)
        if self.which == 1:
            return amp * om * np.cos(om * t + ph)
        return -amp * om * om * np.sin(om * t + ph)

    def _cycloid(self, t, h, T, s0, om):
        if self.which == 0:
            return s0 + h * (t / T - np.sin(om * t) / (2 * math.pi))
        if self.which == 1:
            return h / T * (1 - np.cos(om * t))
        return h / T * om * np.sin(om * t)


def _analytic(name, kind, **p):
    """The TimeLaw of an analytic law (`_Formula`)."""
    return TimeLaw(*(_Formula(kind, which, p) for which in range(3)), name=name)


class _Interp:
    """t -> np.interp(t, ts, values) (a picklable callable)."""

    def __init__(self, ts, values):
        self.ts, self.values = ts, values

    def __call__(self, t):
        return np.interp(t, self.ts, self.values)


def _breaks(spec):
    """The times where the piecewise parts of a law (nested in sums and segments too) change."""
    if spec.type == "piecewise":
        return ([g.until for g in spec.segments[:-1]]
                + [b for g in spec.segments for b in _breaks(g.law)])
    if spec.type == "sum":
        return [b for law in spec.laws for b in _breaks(law)]
    return []


def _check_sum_joins(total, breaks, name):
    """A motion given as a sum does not jump at the breaks of its piecewise terms: its value
    just before a break (1e-12 of the time earlier) and at it agree (see _check_joins)."""
    for b in sorted(set(breaks)):
        before, at = total.evaluate(np.array([b - 1e-12 * max(1.0, abs(b)), b]))[0]
        if abs(at - before) > 1e-6 * max(1.0, abs(before), abs(at)):
            raise ModelError(f"{name}: the sum of laws jumps at t = {b:g} s from {before:.10g} "
                             f"to {at:.10g} (a piecewise term's break); a motion cannot jump: "
                             "give terms whose sum is continuous")


def _check_joins(parts, breaks, name):
    """The pieces of a piecewise motion meet at the breaks (see make_law(joined=True))."""
    for k, b in enumerate(breaks):
        (v0, r0, _), (v1, r1, _) = (law.evaluate(np.array([b])) for law in parts[k:k + 2])
        if abs(v1[0] - v0[0]) > 1e-6 * max(1.0, abs(v0[0]), abs(v1[0])):
            raise ModelError(f"{name}: the piecewise law jumps at until = {b:g} s from "
                             f"{v0[0]:.10g} (segment {k + 1}) to {v1[0]:.10g} (segment "
                             f"{k + 2}); a motion cannot jump: give segments whose values meet")
        if abs(r1[0] - r0[0]) > 1e-6 * max(1.0, abs(r0[0]), abs(r1[0])):
            warnings.warn(f"{name}: the piecewise law's rate jumps at until = {b:g} s from "
                          f"{r0[0]:.6g} to {r1[0]:.6g} (an impulsive change of speed: an "
                          "unbounded acceleration the time steps smear over one step)",
                          stacklevel=3)


def _law_start(spec):
    """The law's value at t = 0 (for drives measured from the initial angle)."""
    return float(make_law(spec).tabulate(np.zeros(1))[0][0])


class _CubicHermite:
    """The piecewise cubic through values y and rates dy at the knots t (increasing):
    scipy.interpolate.CubicHermiteSpline's coefficients and sums (the same numbers), in numpy,
    so that building a mechanism with a 'reference' drive does not import scipy.interpolate
    (about 0.5 s of a batch worker's start-up). Extrapolates with the end pieces."""

    def __init__(self, t, y, dy):
        self.t = t = np.asarray(t, float)
        y, dy = np.asarray(y, float), np.asarray(dy, float)
        h = np.diff(t)
        slope = np.diff(y) / h
        c3 = (dy[:-1] + dy[1:] - 2 * slope) / h
        # ascending powers of (s - t_i): y_i, dy_i, c2, c3
        self.c = (y[:-1], dy[:-1], (slope - dy[:-1]) / h - c3, c3 / h)

    def _piece(self, s):
        s = np.asarray(s, float)
        i = np.clip(np.searchsorted(self.t, s, side="right") - 1, 0, self.t.size - 2)
        return i, s - self.t[i]

    def __call__(self, s):
        i, x = self._piece(s)
        c0, c1, c2, c3 = (c[i] for c in self.c)
        return c0 + c1 * x + c2 * (x * x) + c3 * (x * x * x)

    def rate(self, s):
        i, x = self._piece(s)
        _, c1, c2, c3 = (c[i] for c in self.c)
        return c1 + 2 * c2 * x + 3 * c3 * (x * x)


# ----------------------------------------------------------------------------- sections
def _groups(value, nel):
    """A dimension's entry for every element (a scalar, or one per element / equal group)."""
    if not isinstance(value, list):
        return [value] * nel
    per = nel // len(value)
    return [value[e // per] for e in range(nel)]


def section_at(spec: Section, values):
    """The flexmbs Section of one element from its dimensions' values {dimension: metres}."""
    if spec.shape == "circle":
        return Circle(values["diameter"])
    if spec.shape == "tube":
        if spec.wall_ratio is not None:
            return Tube.with_wall_ratio(values["diameter"], spec.wall_ratio)
        return Tube(values["diameter"], values["thickness"])
    if spec.shape == "rectangle":
        return Rectangle(values["width"], values["height"])
    # given: without GA, kGA = EA (shear deflection 12 EI/(EA L^2) of the bending one: under
    # 1 % for a slenderness L/r above 35, the Euler-Bernoulli limit in practice)
    return GivenSection(EA=spec.EA, kGA=spec.GA if spec.GA is not None else spec.EA, EI=spec.EI,
                        rhoA=spec.rhoA, rhoI=spec.rhoI if spec.rhoI is not None else 0.0)


# ----------------------------------------------------------------------------- mechanism
class Mechanism:
    """The description built onto a Model (see the module docstring).

    Attributes
    ----------
    description : Description
    model : Model                 the flexible mechanism
    reference_model : Model       the same nodes with the rigid reference's constraints
    node : dict (body, point) -> node id
    nsteps, t : the time grid (t_end rounded to a whole number of steps h)
    variables : list of the design vector's components: a scalar variable's name, or
        'name[k]' (k = 1, 2, ...) for each component of an element-wise one; x is in their
        own units (`units`); lower, upper, start: (nv,) arrays
    variable_components : dict variable name -> indices of its components in x
    joint_rows, drive_rows : per joint / drive of the description (in its order), the indices
        of the model's constraint rows it added (motor torques and joint reactions read them)
    """

    def __init__(self, description: Description):
        if not isinstance(description, Description):
            raise ModelError(f"Mechanism expects a flexmbs Description, got "
                             f"{type(description).__name__}")
        self.description = d = description
        ts = d.time
        h = ts.grid_h       # the response grid's spacing (h, or time.output with h = "auto")
        ratio = ts.t_end / h
        if not math.isfinite(ratio) or ratio > MAX_STEPS:
            raise CaseError(f"time.t_end = {ts.t_end:g} s with time.h = {h:g} s is "
                            f"{ratio:.3g} time steps, more than the core's {MAX_STEPS}: give a "
                            "shorter t_end or a coarser h")
        nsteps = max(1, int(round(ratio)))
        self.t_end_requested = ts.t_end
        self.h = h
        self.nsteps = time_steps(nsteps * h, h)
        self.t = h * np.arange(self.nsteps + 1)
        self.t_end = float(self.t[-1])
        if abs(self.t_end - ts.t_end) > 1e-9 * max(1.0, ts.t_end):
            warnings.warn(f"time.t_end = {ts.t_end} s is not a whole number of steps "
                          f"h = {h} s: simulating to {self.t_end:.10g} s ({self.nsteps} steps)",
                          stacklevel=2)
        self._expand_design(d)
        self.materials = {k: Material(m.E, m.nu, m.rho, damping_time=m.damping_time or 0.0,
                                      damping_ratio=m.damping_ratio,
                                      damping_frequency=m.damping_frequency)
                          for k, m in d.materials.items()}
        self._bodies = {b.name: b for b in d.bodies}
        self.model, self.node = self._structure(d.case.name)
        self._reference = None
        self._initial = None
        self._lazy = threading.RLock()     # the reference and initial state: made once
        # drives whose law is 'reference' follow the rigid reference: compute it first
        needs = any(dr.law.type == "reference" for dr in d.drives)
        self._add_constraints(self.model, reference=False,
                              motion=self.reference if needs else None)
        self.set_design(self.start)

    def __getstate__(self):
        state = dict(self.__dict__)
        del state["_lazy"]                 # a lock is not copied: the copy makes its own
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lazy = threading.RLock()

    def _expand_design(self, d):
        """The design vector's components: a scalar variable is one, an element-wise one
        (DesignVariable.elementwise) one per element or group, named 'name[k]' (k from 1)."""
        layout = design_layout(d)
        self.variables, self.units, scale, lower, upper, start = [], [], [], [], [], []
        self._offset, self._component, self._linear = {}, {}, None
        self.variable_components = {}
        for v in d.design:
            ncomp, per_beam = layout[v.name]
            first = len(self.variables)
            self._offset[v.name] = first
            self._component[v.name] = per_beam
            names = [v.name] if not v.elementwise else [f"{v.name}[{k + 1}]" for k in range(ncomp)]
            self.variables += names
            self.variable_components[v.name] = list(range(first, first + ncomp))
            self.units += [v.unit] * ncomp
            scale += [v.scale] * ncomp
            lower += [v.lower] * ncomp
            upper += [v.upper] * ncomp
            start += [v.start] * ncomp
        self._scale, self.lower = np.array(scale), np.array(lower)
        self.upper, self.start = np.array(upper), np.array(start)

    def _index(self, variable, beam, element):
        """The design vector index of `variable` at element `element` (0-based) of `beam`."""
        comp = self._component[variable].get(beam)
        # a scalar variable may also sit in a list of per-element entries: one component
        return self._offset[variable] + (comp[element] if comp and len(comp) > 1 else 0)

    def linear_constraints(self):
        """The smoothness limits of element-wise variables (max_step, max_step_relative) as
        normalised linear rows g = A x - b <= 0 (x in user units): (A (m, nv), b (m,), names).

        max_step s:           (x[k+1] - x[k]) / s - 1 <= 0 and (x[k] - x[k+1]) / s - 1 <= 0
        max_step_relative r:  (x[k+1] - (1 + r) x[k]) / (r upper) <= 0 and the same with k,
                              k+1 swapped (normalised by the step r allows at the upper bound)
        Neighbours are consecutive components (elements, or groups in the order given); a
        variable's max_step rows come before its max_step_relative rows."""
        if self._linear is not None:
            A, b, names = self._linear
            return A.copy(), b.copy(), list(names)
        nv = len(self.variables)
        rows, rhs, names = [], [], []
        for v in self.description.design:
            idx = self.variable_components[v.name]
            pairs = [(i, j) for a, b in zip(idx, idx[1:]) for i, j in ((b, a), (a, b))]
            if v.max_step is not None:
                for i, j in pairs:
                    r = np.zeros(nv)
                    r[i], r[j] = 1.0 / v.max_step, -1.0 / v.max_step
                    rows.append(r)
                    rhs.append(1.0)
                    names.append(f"{v.name} max_step")
            if v.max_step_relative is not None:
                s = v.max_step_relative * v.upper
                for i, j in pairs:
                    r = np.zeros(nv)
                    r[i], r[j] = 1.0 / s, -(1.0 + v.max_step_relative) / s
                    rows.append(r)
                    rhs.append(0.0)
                    names.append(f"{v.name} max_step_relative")
        A = np.array(rows) if rows else np.zeros((0, nv))
        self._linear = (A, np.array(rhs, float), names)
        return self.linear_constraints()

    # ------------------------------------------------------------------ structure
    def _structure(self, name):
        d = self.description
        m = Model(name)
        node = {}
        pts = {k: np.array(v, float) for k, v in d.points.items()}
        beams = []
        for b in d.bodies:
            if isinstance(b, Beam):
                mat = self.materials.get(b.material)     # None: a 'given' section
                body = m.add_beam(b.name, pts[b.start], pts[b.end], b.elements, material=mat,
                                  section=Circle(1.0) if mat is not None
                                  else section_at(b.section, {}), order=b.order)
                node[(b.name, b.start)] = body.first
                node[(b.name, b.end)] = body.last
                beams.append(b.name)
            elif isinstance(b, Rigid):
                names = [p for p in body_points(b) if p != b.center]
                ids = [m.add_node(*pts[p]) for p in names]
                center = pts[b.center] if b.center is not None else None
                body = m.add_rigid_body(b.name, ids, b.mass, b.inertia, center=center)
                node.update({(b.name, p): i for p, i in zip(names, ids)})
                if b.center is not None:
                    node[(b.name, b.center)] = body.first
            elif isinstance(b, PointMass) and b.on is None:
                i = m.add_node(*pts[b.at])
                m.add_point_mass(i, b.mass, b.inertia)
                m._new_body(b.name, "mass", [i])
                node[(b.name, b.at)] = i
        for b in d.bodies:       # masses on other bodies, once those have their nodes
            if isinstance(b, PointMass) and b.on is not None:
                i = node[(b.on, b.at)]
                m.add_point_mass(i, b.mass, b.inertia)
                node[(b.name, b.at)] = i
        self.beams = beams        # the same names for the reference's structure
        m.set_gravity(*d.gravity)
        for k, ld in enumerate(d.loads):
            law = make_law(ld.law, f"load {k + 1}") if ld.law is not None else None
            m.add_load(node[(ld.body, ld.at)], ld.fx, ld.fy, ld.moment, law=law)
        for s in d.springs:
            a, b = (node[(bb, p)] for bb, p in zip(s.bodies, s.at))
            if not hasattr(m, "add_spring_damper"):
                raise ModelError("spring-dampers need a core with force elements")
            m.add_spring_damper(a, b, s.stiffness, damping=s.damping,
                                free_length=s.free_length)
        return m, node

    def _add_constraints(self, m, reference, motion=None):
        """Joints and drives (reference=False: the flexible mechanism, drives with law
        'reference' take their motion from `motion`; True: the rigid reference's constraints,
        paths instead of those drives)."""
        d, node = self.description, self.node
        joint_rows, drive_rows = [], []
        for k, j in enumerate(d.joints):
            first = len(m._rows)
            if j.type in ("pin", "clamp", "slider"):
                n = node[(j.body, j.at)]
                if j.type == "pin":
                    m.pin(n)
                elif j.type == "clamp":
                    m.clamp(n)
                else:
                    m.slider(n, j.axis)
            elif j.type == "prismatic":
                if GROUND in j.bodies:              # on the ground: a slider
                    other = j.bodies[1] if j.bodies[0] == GROUND else j.bodies[0]
                    m.slider(node[(other, j.at)], j.axis)
                else:
                    a, b = (node[(bb, j.at)] for bb in j.bodies)
                    if a == b:
                        raise ModelError(f"joint {j.name or k + 1}: bodies {j.bodies} share one node")
                    m.prismatic(a, b, j.axis)
            else:
                a, b = (node[(bb, j.at)] for bb in j.bodies)
                if a == b:
                    raise ModelError(f"joint {j.name or k + 1}: bodies {j.bodies} share one node")
                (m.hinge if j.type == "hinge" else m.weld)(a, b)
            joint_rows.append(list(range(first, len(m._rows))))
        q0 = m.reference_coordinates()
        for k, dr in enumerate(d.drives):
            first = len(m._rows)
            name = f"drive {dr.name or k + 1}"
            n = node[(dr.body, dr.at)]
            other = node[(dr.relative_to, dr.at)] if dr.relative_to is not None else None
            if dr.law.type == "reference":
                if reference:
                    drive_rows.append([])
                    continue
                law = self._reference_law(dr, n, other, motion, name)
            elif dr.type == "rotation":
                base = 0.0 if dr.law.absolute else q0[3 * n + 2] - _law_start(dr.law) - (
                    q0[3 * other + 2] if other is not None else 0.0)
                law = make_law(dr.law, name, shift=base, joined=True)
            else:
                law = make_law(dr.law, name, shift=-_law_start(dr.law), joined=True)
            if dr.type == "rotation":
                m.drive_rotation(n, law, relative_to=other)
            else:
                m.drive_translation(n, law, dr.axis)
            drive_rows.append(list(range(first, len(m._rows))))
        if not reference:
            self.joint_rows, self.drive_rows = joint_rows, drive_rows
        if reference:
            for k, p in enumerate(d.paths):
                n = node[(p.body, p.at)]
                # path laws are displacements from the point's initial position
                m.prescribe_position(
                    n, x=make_law(p.x, f"path {k + 1} x", shift=q0[3 * n] - _law_start(p.x),
                                  joined=True),
                    y=make_law(p.y, f"path {k + 1} y", shift=q0[3 * n + 1] - _law_start(p.y),
                               joined=True))

    def _reference_law(self, dr, n, other, motion, name):
        """The drive's motion in the rigid reference, as a law exact on the time grid."""
        # the histories of the drive's coordinates alone (not of every node: motion.q)
        if dr.type == "rotation":
            v, r, a = (motion.coordinates(3 * n + 2, rate) for rate in (0, 1, 2))
            if other is not None:
                v = v - motion.coordinates(3 * other + 2, 0)
                r = r - motion.coordinates(3 * other + 2, 1)
                a = a - motion.coordinates(3 * other + 2, 2)
        else:
            ax = np.asarray(dr.axis, float) / math.hypot(*dr.axis)
            sl = [3 * n, 3 * n + 1]
            q = motion.coordinates(sl, 0)
            v = (q - q[0]) @ ax
            r, a = motion.coordinates(sl, 1) @ ax, motion.coordinates(sl, 2) @ ax
        t = motion.t
        spline = _CubicHermite(t, v, r)
        return TimeLaw(spline, spline.rate, _Interp(t, a), name=name)

    # ------------------------------------------------------------------ rigid reference
    def _check_reference_memory(self, ref):
        """ResourceError, before the rigid reference is computed, when its memory over the
        time grid (flexmbs.model.kinematics.reference_memory) exceeds the memory limit
        ([solver] memory_limit, else flexmbs.resources.memory_limit: FLEXMBS_MEMORY_LIMIT, else
        the memory available)."""
        d = self.description
        following = sum(dr.law.type == "reference" for dr in d.drives)
        need = reference_memory(ref, self.t.size, following)
        limit = None if d.solver.memory_limit is None else CaseLimit(d.solver.memory_limit)
        avail = memory_limit(limit)
        if need > avail:
            hint = limit_hint(limit, setting="[solver] memory_limit")
            raise ResourceError(
                f"case {d.case.name!r}: the rigid reference over {self.t.size} time points "
                f"(time.t_end = {d.time.t_end:g} s, time.h = {d.time.grid_h:g} s) needs about "
                f"{format_bytes(need)}, more than {limit_source(limit)} ({format_bytes(avail)}), "
                f"before any simulation: use a coarser time.h or a shorter time.t_end ({hint})",
                required=need, available=avail)

    @property
    def reference(self):
        """The rigid reference motion on the time grid (flexmbs.model.kinematics.RigidMotion)."""
        with self._lazy:
            if self._reference is None:
                ref, _ = self._structure(self.description.case.name + " (rigid reference)")
                self._add_constraints(ref, reference=True)
                self._check_reference_memory(ref)
                q0 = assemble(ref, 0.0).q
                self.reference_model = ref
                self._reference = rigid_reference(ref, self.t, q0=q0)
        return self._reference

    def initial_state(self):
        """(q0, qd0): the assembled initial configuration (loops closed by position analysis,
        every beam straight) and the rigid velocity field the drives impose at t = 0. Both are
        rigid kinematics, independent of the design: computed once per mechanism."""
        with self._lazy:
            if self._initial is None:
                a = assemble(self.model, 0.0)
                self._initial = (a.q, drive_velocities(self.model, a.q, 0.0))
        q0, qd0 = self._initial
        return q0.copy(), qd0.copy()

    def start_state(self, x=None, gradient=False, static=None):
        """(q0, qd0) of a simulation of design x: `initial_state` with the description's
        [initial] deformation and rates on top (InitialState), or as it is without one.

        static_loads: q0 is the static equilibrium at t = 0 of design x under those loads
        (and gravity; the case's loads left out), solved by `static(model, q0)` (the static
        equilibrium of a built model from q0: the Problem hands in the core's static start). It depends on the design, and the simulation's direct and
        adjoint differentiation start from dq0/dx = 0: gradient=True (a design derivative
        or adjoint run) is refused with a ModelError rather than computed wrong. Given beam
        deflections and rates do not depend on the design: their derivatives are zero and
        the gradients stay exact."""
        q0, qd0 = self.initial_state()
        ini = self.description.initial
        if ini is None:
            return q0, qd0
        if ini.static_loads is not None:
            if gradient:
                raise ModelError(
                    "[initial] static_loads: the initial deformation is a static solution that "
                    "depends on the design, and the simulation's design derivatives (direct and "
                    "adjoint) start from a design-independent state: gradients of this case "
                    "would be wrong and are refused; evaluate without gradients, or give the "
                    "initial deflection as values ([[initial.beams]] deflection), or use "
                    "time.start = 'static' (static equilibrium under the case's own loads, "
                    "differentiated exactly)")
            if static is None:
                raise ModelError("[initial] static_loads: start_state needs the static solve "
                                 "(static=...; flexmbs.problem.Problem gives it)")
            q0 = self._static_start(x, static)
        for b in ini.beams:
            self._deflect(b, q0, qd0)
        if any(b.deflection is not None or b.axial is not None for b in ini.beams):
            self._check_joined(q0)
        return q0, qd0

    def _check_joined(self, q0):
        """The given deflections keep the joints (Phi(q0, 0) = 0, to the core's 1e-8 of the
        coordinates' scale): a ModelError naming the first violated row otherwise."""
        m = self.model
        laws = law_tables(m, [0.0])[0] if m.laws() else None
        phi = constraint_values(m.compile(), q0, laws)
        if phi.size and np.max(np.abs(phi)) > 1e-8 * max(1.0, float(np.max(np.abs(q0)))):
            r = int(np.argmax(np.abs(phi)))
            raise ModelError(f"[initial] beams: the given deflections violate constraint "
                             f"'{m.row_label(r)}' by {phi[r]:.3g}: a joined end keeps its "
                             "position (and a clamped or welded one its rotation); give zero "
                             "deflection (and slope) there")

    def _static_start(self, x, static):
        """The static equilibrium of design x under [initial] static_loads (all coordinates)."""
        with self._lazy:
            if getattr(self, "_preload", None) is None:
                d = self.description
                with warnings.catch_warnings():       # the same grid: warned once already
                    warnings.simplefilter("ignore")
                    self._preload = Mechanism(d.model_copy(
                        update={"loads": d.initial.static_loads, "initial": None}))
            model = self._preload.design_model(self.start if x is None else x)
        q0, _ = self.initial_state()
        return static(model, q0)

    def _deflect(self, spec, q0, qd0):
        """Add an InitialBeam's deflection, axial displacement and their rates to q0, qd0
        (in place)."""
        from scipy.interpolate import CubicSpline
        body = self.model.body(spec.body)
        nodes = np.asarray(body.nodes)
        length = sum(self.model._elements[e][1] for e in body.elements)
        sn = np.linspace(0.0, 1.0, nodes.size)
        s = sn if spec.s is None else np.asarray(spec.s, float)
        a = q0[3 * nodes[0] + 2]                      # the beam's axis angle
        nx, ny = -math.sin(a), math.cos(a)            # its left normal
        for values, q in ((spec.axial, q0), (spec.axial_rate, qd0)):
            if values is not None:                    # along the axis, towards `to`
                u = CubicSpline(s, np.asarray(values, float))(sn)
                q[3 * nodes] += u * ny
                q[3 * nodes + 1] -= u * nx
        for values, q, rate in ((spec.deflection, q0, False), (spec.deflection_rate, qd0, True)):
            if values is None:
                continue
            spline = CubicSpline(s, np.asarray(values, float))
            w, slope = spline(sn), spline(sn, 1) / length
            q[3 * nodes] += w * nx
            q[3 * nodes + 1] += w * ny
            if rate:
                base = spec.deflection
                w0 = (np.zeros_like(sn) if base is None else
                      CubicSpline(s, np.asarray(base, float))(sn, 1) / length)
                q[3 * nodes + 2] += slope / (1.0 + w0 * w0)
            else:
                q[3 * nodes + 2] += np.arctan(slope)

    def layout(self, dofs=None):
        """What the coordinates are, for files of results (`flexmbs simulate --out`): a dict
        of arrays.

        dof_node, dof_component : (len(dofs),) the node of each coordinate of `dofs` (default
            all) and which of its coordinates it is ('x', 'y' or 'angle'; coordinate
            3 node + 0, 1, 2)
        node_body : (nnode,) the body each node belongs to (a point mass sitting `on` a
            body: that body's)
        node_point : (nnode,) the named point at the node ('' for an inner node of a beam)
        node_s : (nnode,) the node's fraction of its beam's length from `from` (NaN off
            beams): a station's s
        node_xy : (nnode, 2) the node's position in the assembled initial configuration
        body_names, body_kinds : (nbody,) each body and its kind ('beam', 'rigid', 'mass')
        body_nodes : (nbody,) the node ids of each body joined by ',' (a beam's from its
            `from` end)
        """
        m = self.model
        nn = m.ndof // 3
        dofs = np.arange(m.ndof) if dofs is None else np.asarray(dofs, int)
        body = np.full(nn, "", dtype=object)
        point = np.full(nn, "", dtype=object)
        frac = np.full(nn, np.nan)
        for b in m.bodies.values():
            for k, n in enumerate(b.nodes):
                if body[n] == "":
                    body[n] = b.name
                if b.kind == "beam":
                    frac[n] = k / (len(b.nodes) - 1)
        for (_, p), n in self.node.items():
            point[n] = p
        q0, _ = self.initial_state()
        return dict(dof_node=dofs // 3, dof_component=np.array(["x", "y", "angle"])[dofs % 3],
                    node_body=body.astype(str), node_point=point.astype(str), node_s=frac,
                    node_xy=q0.reshape(-1, 3)[:, :2],
                    body_names=np.array(list(m.bodies), dtype=str),
                    body_kinds=np.array([b.kind for b in m.bodies.values()], dtype=str),
                    body_nodes=np.array([",".join(map(str, b.nodes)) for b in m.bodies.values()],
                                        dtype=str))

    # ------------------------------------------------------------------ design
    def _summary(self):
        """The variables for messages: 'd[1..8]' for an element-wise one."""
        out = []
        for v in self.description.design:
            n = len(self.variable_components[v.name])
            out.append(f"{v.name}[1..{n}]" if v.elementwise else v.name)
        return ", ".join(out)

    def design_values(self, x):
        """x (user units) as a checked float array: numbers only (a bool or a string is
        refused, even a numeric one)."""
        if has_complex(x):
            raise ModelError(f"design must be {len(self.variables)} real numbers "
                             f"({self._summary()}), got complex values {x!r}")
        items = np.ravel(np.asarray(x, dtype=object)) if not isinstance(x, (str, bytes)) else [x]
        if any(isinstance(v, (bool, np.bool_, str, bytes)) for v in items):
            raise ModelError(f"design must be {len(self.variables)} numbers "
                             f"({self._summary()}), got {x!r}")
        try:
            arr = np.asarray(x, dtype=float)
        except (TypeError, ValueError):
            raise ModelError(f"design must be {len(self.variables)} numbers "
                             f"({self._summary()}), got {x!r}") from None
        if arr.shape != (len(self.variables),) or not np.all(np.isfinite(arr)):
            raise ModelError(f"design must be {len(self.variables)} finite numbers "
                             f"({self._summary()}), got {x!r}")
        if np.any(arr <= 0):
            raise ModelError(f"design values must be positive (section sizes), got {x!r}")
        return arr

    def _element_values(self, b: Beam, x_m):
        """Per element of beam b: {dimension: (value m, variable index or -1)}."""
        out = [dict() for _ in range(b.elements)]
        for dim, spec in b.section.dimensions().items():
            for e, item in enumerate(_groups(spec, b.elements)):
                if isinstance(item, str):
                    i = self._index(item, b.name, e)
                    out[e][dim] = (x_m[i], i)
                else:
                    out[e][dim] = (float(item), -1)
        return out

    def _sections(self, x):
        """{beam name: the Section of each of its elements} for design x (user units)."""
        x_m = self.design_values(x) * self._scale
        return {name: [section_at(self._bodies[name].section, {k: v for k, (v, _) in vals.items()})
                       for vals in self._element_values(self._bodies[name], x_m)]
                for name in self.beams}

    def design_model(self, x):
        """The model of design x (user units): a copy of `model` with the design's sections
        (Model.with_sections: the structure, its compiled arrays and KLU analysis shared),
        `model` itself unchanged. What a simulation or a response of one design reads, so
        that several threads may evaluate different designs of one mechanism at once."""
        return self.model.with_sections(self._sections(x))

    def set_design(self, x):
        """Set the sections of every beam of `model` for design x (user units) and return
        it. This changes the mechanism's shared model: for one thread at a time; evaluations
        (Problem) use `design_model`, which leaves it alone."""
        for name, secs in self._sections(x).items():
            self.model.set_element_sections(self.model.body(name), secs)
        self._x = self.design_values(x)
        return self.model

    def element_property_derivatives(self, x):
        """d[EA, kGA, EI, rhoA, rhoI]/dx of every element, (5, nel, nv), x in user units."""
        x = self.design_values(x)
        x_m = x * self._scale
        out = np.zeros((5, len(self.model._elements), len(self.variables)))
        for name in self.beams:
            b = self._bodies[name]
            mat = self.materials.get(b.material)
            body = self.model.body(name)
            for e, vals in zip(body.elements, self._element_values(b, x_m)):
                sec = section_at(b.section, {k: v for k, (v, _) in vals.items()})
                dsec = sec.property_derivatives(mat)          # (5, nparam)
                for dim, (_, i) in vals.items():
                    if i < 0 or (dim == "thickness" and b.section.wall_ratio is not None):
                        continue
                    k = list(sec.parameters).index(_PARAM[dim])
                    out[:, e, i] += dsec[:, k] * self._scale[i]
        return out

    def half_depths(self, x, body):
        """Half-depth c (m) of every element of a beam and dc/dx (nel_body, nv)."""
        x = self.design_values(x)
        b = self._bodies[body]
        vals = self._element_values(b, x * self._scale)
        c = np.zeros(b.elements)
        dc = np.zeros((b.elements, len(self.variables)))
        key = "height" if b.section.shape == "rectangle" else "diameter"
        if b.section.shape == "given":
            raise ModelError(f"beam {body!r}: a 'given' section has no depth for stresses")
        for e, v in enumerate(vals):
            c[e] = 0.5 * v[key][0]
            if v[key][1] >= 0:
                dc[e, v[key][1]] = 0.5 * self._scale[v[key][1]]
        return c, dc
