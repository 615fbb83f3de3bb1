"""The weakly coupled method (paper 5.3) on any general-format problem (`flexmbs.problem.Problem`).

One cycle: MBS analysis of the current design -> equivalent static loads (ESL) of every beam the
constraints need, through a corotational frame (`flexmbs.methods.esl`) -> test of eq. (25) -> static
multi-load-case optimization (23) with the ESL held fixed -> next design. The cycle loop, the
oscillation detection and the confirmation cycles are those of `flexmbs.methods.cycles`.

The static model of the responses (the generic form of the paper's eqs. 29, 31, 34-35):

* mass: exact (it does not depend on the loads);
* deviation: a term's point is reached from the ground through a *chain* of bodies, found from
  the joints: a path ground -(pin/clamp)- body -(hinge/weld, or a point mass `on` it)- body ...
  ending at the term's point (or at a point joined to it). A beam traversed from point P to point
  Q contributes R_0,n u_n(Q), the static displacement of Q in the beam's corotational frame at P,
  rotated to the ground; rigid bodies and point masses contribute nothing. The flexible
  deviation of the point is the sum of the contributions along its chain, exactly how (29), (31)
  and (35) sum the arms' deflections; a term `relative_to` another point takes the difference of
  the two chains (a common start cancels: (29)'s second term is arm 2 alone). Where the next
  beam's rotation is tied to the beam's (a rotation drive `relative_to` it, or a weld), the
  beam's exit rotation relative to its entry, phi(Q) = u_n,rot(Q) - u_n,rot(P), turns the rest
  of the chain rigidly: phi(Q) k x (r(point) - r(Q)), r of the rigid reference (a serial robot
  with relative joint drives; the paper's robot drives its arms absolutely, no such term). A frame other than
  the ground rotates the sum by the rigid reference's angle of that body, as the dynamic response.
  A closed loop gives a point several chains (four-bar: A through the crank, and through the
  follower and the coupler): every chain becomes its own constraint, as (34) and (35) do. Sliders
  do not fix a point along their axis and so never start a chain; springs are not links.
  A beam needs one frame: its entry point in the chains (four-bar: crank at O, follower at C,
  coupler at B). When chains enter the same beam from both ends, `frames={body: point}` chooses,
  the chains entering elsewhere are dropped, and a term left with no chain is a CaseError;
  without `frames` the conflict itself is a CaseError naming the beam.
* stress: E (|eps| + c |kappa|) of the beam's static displacement under each load case, the
  strain kinematics of `flexmbs.responses.strain` in the body frame; the largest over the
  elements' stations and the listed beams, step by step (as `Problem` does dynamically).

The ESL bodies are the beams on a chain and the beams with a stress response (frame at the chain
entry, else at the beam's `from` point, or as `frames` says); beams that enter no constraint need
none. Component 'angle' has no static form here (CaseError). The kind of each frame comes from
the beam's joints by default (`frame_by_joints`: tangent where the beam's rotation at its frame
point is held, chord for a beam pinned or hinged at both ends), or is given (`frame_kind`).
At the design of its ESL the static form of a deviation is the chain sum of the frames'
displacements (K^-1 g_eq = u); its ratio to the simulated deviation
(`StaticModel.static_to_simulated`) is recorded every cycle and returned.

Responses with no static form: a motor torque or a joint reaction (`torque`, `reaction`) is a
dynamic quantity (inertia of the whole mechanism, not a beam's deflection under fixed loads).
The static optimization (23) cannot size against it: its constraints are left out of (23) and
checked by the simulation only (`StaticModel.unmodelled`; the result's details
`constraints_checked_by_simulation`). Every cycle simulates its design, so the final design is
checked against ALL constraints by a simulation: details `max_violation` and `feasible`, and the
result's reason says when that design violates a constraint. An objective without a static
form is a CaseError.

Examples
--------
>>> from flexmbs.optimize import optimize_weakly                            # doctest: +SKIP
>>> r = optimize_weakly("robot_2dof")                                      # doctest: +SKIP
>>> round(r.mass_kg, 3)                                                    # doctest: +SKIP
0.959
"""
from __future__ import annotations

import dataclasses
import time
from types import SimpleNamespace

import numpy as np

from flexmbs.errors import CaseError, ModelError
from flexmbs.methods.cycles import (SHRINK_DESIGN_TOL, CycleControl, ShrinkingMoveLimit,
                                     check_remedies, damped_update, move_limited_bounds,
                                     what_to_try)
from flexmbs.methods.esl import (BodyStiffness, ChordFrame, EquivalentStaticLoads, TangentFrame,
                         equivalent_static_loads, esl_change, solve_static)
from flexmbs.methods.result import OptimizationResult, open_history
from flexmbs.methods.verified import finish
from flexmbs.model.description import (Beam, Deviation, Mass, PointMass, Station, Stress,
                                 body_points)
from flexmbs.model.fingerprint import fingerprint, run_options
from flexmbs.model.options import build, from_keywords, WeaklyOptions
from flexmbs.problem import FEASIBILITY_TOL, _scalar, constraint_rows, is_feasible, load_problem
from flexmbs.progress import check_progress, describe_cycle, reporter
from flexmbs.responses.strain import raw_strain_derivatives, raw_strains, shape, gauss_points

__all__ = ["optimize_weakly", "chains", "frame_by_joints", "StaticModel", "blend_loads"]

#: at most this many chain combinations per deviation response (loops multiply them)
MAX_VARIANTS = 16


# ---------------------------------------------------------------------------- chains
def _links(description):
    """Joint graph: roots [(body, point)] fixed to the ground, and same-point links
    {(body, point): [(body, point), ...]} (hinge, weld, point mass `on` a body)."""
    roots, links = [], {}

    def link(a, b):
        links.setdefault(a, []).append(b)
        links.setdefault(b, []).append(a)
    for j in description.joints:
        if j.type in ("pin", "clamp"):
            roots.append((j.body, j.at))
        elif j.type in ("hinge", "weld"):
            link((j.bodies[0], j.at), (j.bodies[1], j.at))
    for b in description.bodies:
        if isinstance(b, PointMass) and b.on is not None:
            link((b.name, b.at), (b.on, b.at))
    return roots, links


def _same_point(vertex, links):
    """The body-points joined to `vertex` at its point (itself included)."""
    seen, todo = {vertex}, [vertex]
    while todo:
        for w in links.get(todo.pop(), []):
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def chains(description, body, point):
    """Every chain from the ground to the point `point` of `body` (module docstring).

    Returns a list of chains, each a tuple of (beam, entry point, exit point) traversals from
    the ground outwards (an empty tuple: the point is held by rigid links only); chains that
    differ only in rigid bodies are given once. CaseError when no chain reaches the point.
    """
    bodies = {b.name: b for b in description.bodies}
    roots, links = _links(description)
    target = _same_point((body, point), links)
    found = []

    def record(contrib):
        if tuple(contrib) not in found:
            found.append(tuple(contrib))

    def leave(b, p, visited, contrib):
        for nb, np_ in links.get((b, p), []):
            if nb not in visited:
                enter(nb, np_, visited | {nb}, contrib)

    def enter(b, p, visited, contrib):
        if (b, p) in target:
            record(contrib)
            return
        leave(b, p, visited, contrib)
        for q in body_points(bodies[b]):
            if q == p:
                continue
            c = contrib + [(b, p, q)] if isinstance(bodies[b], Beam) else contrib
            if (b, q) in target:
                record(c)
            else:
                leave(b, q, visited, c)

    for b, p in roots:
        enter(b, p, {b}, [])
    if not found:
        raise CaseError(f"weakly coupled method: no chain of joints (pin/clamp to the ground, "
                        f"hinges, welds) reaches point {point!r} of body {body!r}; a slider or "
                        "prismatic joint does not fix a point along its axis, so it cannot "
                        "start a chain")
    return found


def _couplings(description):
    """{(body, point, next body)}: the next body's rotation at the point is tied to the body's
    (a rotation drive `relative_to` it, or a weld), both orders."""
    out = set()
    for dr in description.drives:
        if dr.type == "rotation" and dr.relative_to is not None:
            out |= {(dr.relative_to, dr.at, dr.body), (dr.body, dr.at, dr.relative_to)}
    for j in description.joints:
        if j.type == "weld":
            out |= {(j.bodies[0], j.at, j.bodies[1]), (j.bodies[1], j.at, j.bodies[0])}
    return out


def _rotations(chain, coupled, target, coef):
    """[(beam, entry, exit, coefficient, target)]: the beams of a chain whose exit rotation
    turns the rest of the chain rigidly (the next beam's rotation is tied to it)."""
    return [(b, p, q, coef, target) for (b, p, q), (b2, p2, _) in zip(chain, chain[1:])
            if p2 == q and (b, q, b2) in coupled]


def _difference(chain, rel):
    """{(beam, entry, exit): coefficient} of chain(point) - chain(relative point)."""
    out = {}
    for key in chain:
        out[key] = out.get(key, 0.0) + 1.0
    for key in rel or ():
        out[key] = out.get(key, 0.0) - 1.0
    return {k: v for k, v in out.items() if v != 0.0}


# ---------------------------------------------------------------------------- frames
#: the frame kinds a beam can be given; 'auto' is resolved per beam by `frame_by_joints`
FRAME_KINDS = ("auto", "tangent", "chord")


def _rotation_held(description, body, point):
    """Whether the joints or drives hold or tie the rotation of `body` at `point`: a clamp,
    a slider (the body does not rotate), a weld or a prismatic joint there, a rotation drive of
    the body there, or a rotation drive of another body relative to it there."""
    for j in description.joints:
        if j.at != point:
            continue
        if j.type in ("clamp", "slider") and j.body == body:
            return True
        if j.type in ("weld", "prismatic") and body in j.bodies:
            return True
    return any(dr.type == "rotation" and dr.at == point
               and body in (dr.body, dr.relative_to) for dr in description.drives)


def _joined(description, body, point):
    """Whether a joint (to the ground or to another body) holds `body` at `point`."""
    return any(j.at == point and (j.body == body or body in (j.bodies or ()))
               for j in description.joints)


def frame_by_joints(description, beam, point):
    """The corotational frame kind that the joints give `beam` at its frame point `point`.

    'tangent' where the beam's rotation at `point` is held or tied to another body (clamp,
    slider, weld, prismatic joint, a rotation drive of the beam, or of another body relative to
    it): the static load cases clamped there, as the paper's eqs. (16-19). 'chord' where the
    rotation at `point` is free (a pin or hinge) and the beam's other end is joined too (to the
    ground or another body): both end rotations are free, so the elastic deflection is measured
    from the chord between the ends; in a tangent frame the free end slope would count as
    deflection (the other end's offset: slope times length). 'tangent' again where the other end
    is free (nothing there fixes a chord: in a chord frame the free end's transverse
    displacement would be zero by definition).
    """
    beams = {b.name: b for b in description.bodies if isinstance(b, Beam)}
    if beam not in beams:
        raise CaseError(f"frame_by_joints: {beam!r} is not a beam "
                        f"(beams: {', '.join(beams) or 'none'})")
    b = beams[beam]
    if point not in (b.start, b.end):
        raise CaseError(f"frame_by_joints: beam {beam!r} has no end point {point!r} (its ends: "
                        f"{b.start}, {b.end})")
    if _rotation_held(description, beam, point):
        return "tangent"
    far = b.end if point == b.start else b.start
    return "chord" if _joined(description, beam, far) else "tangent"


# ---------------------------------------------------------------------------- static model
def _frame_kinds(frame_kind, beams):
    """{beam: 'auto' | 'tangent' | 'chord'} from one kind for all beams or a dict beam -> kind
    (beams not named: 'auto')."""
    ok = "', '".join(FRAME_KINDS)
    if isinstance(frame_kind, str):
        if frame_kind not in FRAME_KINDS:
            raise ModelError(f"frame_kind must be '{ok}', got {frame_kind!r} "
                             "(or a dict beam -> kind)")
        return dict.fromkeys(beams, frame_kind)
    if not isinstance(frame_kind, dict):
        raise ModelError(f"frame_kind must be '{ok}' or a dict beam -> kind, got "
                         f"{frame_kind!r}")
    for name, kind in frame_kind.items():
        if name not in beams:
            raise CaseError(f"frame_kind: {name!r} is not a beam (beams: {', '.join(beams)})")
        if kind not in FRAME_KINDS:
            raise ModelError(f"frame_kind of beam {name!r} must be '{ok}', got {kind!r}")
    return {n: frame_kind.get(n, "auto") for n in beams}


#: the response types with a static form here, and the StaticModel method evaluating it
#: (value and gradient at a design from the static solutions under the ESL)
STATIC_FORMS = {Mass: "_mass", Deviation: "_deviation", Stress: "_stress"}


class StaticModel:
    """The static responses of a problem for one set of ESL (see the module docstring).

    Parameters
    ----------
    problem : Problem
    frames : dict body -> point, optional (frame point of a beam).
    frame_kind : 'auto' (default: `frame_by_joints` per beam), 'tangent' or 'chord' (from the
        frame point to the beam's other end), for every beam; or a dict beam -> kind (beams not
        named: 'auto').
    """

    def __init__(self, problem, frames=None, frame_kind="auto"):
        self.problem = problem
        d = problem.description
        mech = problem.mechanism
        self.mech = mech
        beams = {b.name: b for b in d.bodies if isinstance(b, Beam)}
        kinds = _frame_kinds(frame_kind, beams)
        frames = dict(frames or {})
        for name, pt in frames.items():
            if name not in beams:
                raise CaseError(f"frames: {name!r} is not a beam (beams: {', '.join(beams)})")
            if pt not in (beams[name].start, beams[name].end):
                raise CaseError(f"frames: beam {name!r} has no end point {pt!r} (its ends: "
                                f"{beams[name].start}, {beams[name].end})")
        used = set()
        if d.objective is not None:
            used.add(d.objective.response)
        used.update(c.response for c in d.constraints)
        resp = {r.name: r for r in d.responses}
        static_types = tuple(STATIC_FORMS)
        if d.objective is not None and not isinstance(resp[d.objective.response], static_types):
            r = resp[d.objective.response]
            raise CaseError(f"weakly coupled method: the objective {r.name!r} (type {r.type!r}) "
                            "has no static form (only mass, deviation and stress have one)")
        self.responses = [resp[n] for n in resp if n in used
                          and isinstance(resp[n], static_types)]
        #: constrained responses with no static form: left to the check by simulation
        self.unmodelled = [n for n in resp if n in used and n not in
                           {r.name for r in self.responses}]
        for r in self.responses:
            at = [getattr(r, "at", None)] + [p for t in getattr(r, "terms", []) for p in
                                             (t.at, getattr(t.relative_to, "at", None))]
            if any(isinstance(a, Station) for a in at):
                raise CaseError(f"weakly coupled method: response {r.name!r} reads a station "
                                "along a beam (at = {body, s}), which has no static form here "
                                "(named points only); use the fully coupled method")
        # chains of every deviation term, then the frame entry of every beam on them
        raw = {}
        for r in self.responses:
            if isinstance(r, Deviation):
                for k, t in enumerate(r.terms):
                    if t.component == "angle":
                        raise CaseError(f"response {r.name!r}, term {k + 1}: component 'angle' "
                                        "has no static form in the weakly coupled method")
                    pc = chains(d, t.body, t.at)
                    rc = chains(d, t.relative_to.body, t.relative_to.at) \
                        if t.relative_to is not None else [None]
                    raw[(r.name, k)] = [(a, b) for a in pc for b in rc]
        entries = {}
        for combos in raw.values():
            for a, b in combos:
                for beam, p, _ in list(a) + list(b or ()):
                    entries.setdefault(beam, set()).add(p)
        for beam, pts in entries.items():
            if len(pts) > 1 and beam not in frames:
                raise CaseError(f"weakly coupled method: chains enter beam {beam!r} from both "
                                f"ends ({', '.join(sorted(pts))}); choose its frame point with "
                                f"frames={{{beam!r}: point}}")
        entry = {b: next(iter(p)) for b, p in entries.items()}
        entry.update({b: p for b, p in frames.items()})
        for r in self.responses:
            if isinstance(r, Stress):
                for b in r.bodies:
                    entry.setdefault(b, beams[b].start)
        # the deviation terms' variants: a chain combination each (loops give several)
        self.variants, self.turns = {}, {}
        coupled = _couplings(d)
        for r in self.responses:
            if not isinstance(r, Deviation):
                continue
            per_term = []
            for k, t in enumerate(r.terms):
                rel = t.relative_to
                ok = [(_difference(a, b),
                       _rotations(a, coupled, (t.body, t.at), 1.0)
                       + (_rotations(b, coupled, (rel.body, rel.at), -1.0) if b else []))
                      for a, b in raw[(r.name, k)]
                      if all(entry[bm] == p for bm, p, _ in list(a) + list(b or ()))]
                if not ok:
                    raise CaseError(f"response {r.name!r}, term {k + 1}: every chain to point "
                                    f"{t.at!r} of {t.body!r} enters a beam away from its frame "
                                    f"point ({entry})")
                per_term.append(ok)
            combos = [[]]
            for opts in per_term:
                combos = [c + [o] for c in combos for o in opts]
            if len(combos) > MAX_VARIANTS:
                raise CaseError(f"response {r.name!r}: {len(combos)} chain combinations (closed "
                                f"loops); at most {MAX_VARIANTS}: choose frames to open the loops")
            self.variants[r.name] = [[diff for diff, _ in c] for c in combos]
            #: per variant and term, the beams whose exit rotation turns the rest of the chain
            self.turns[r.name] = [[turn for _, turn in c] for c in combos]
        # ESL bodies: frames and stiffness (the structure only: built once)
        model = mech.model
        self.frames, self.stiffness, self.exit = [], {}, {}
        for name in beams:
            if name not in entry:
                continue
            if kinds[name] == "auto":
                kinds[name] = frame_by_joints(d, name, entry[name])
            body = model.body(name)
            node = mech.node[(name, entry[name])]
            far = body.last if node == body.first else body.first
            fr = TangentFrame(node) if kinds[name] == "tangent" else ChordFrame(node, far)
            self.frames.append((name, fr))
            self.stiffness[name] = BodyStiffness(model, body, fr)
        self.entry = entry
        self.kinds = {n: kinds[n] for n, _ in self.frames}
        self.loads = None

    # ------------------------------------------------------------------ loads
    def set_loads(self, loads):
        """The cycle's EquivalentStaticLoads."""
        self.loads = loads
        self.nt = len(loads.bodies[0].t)

    # ------------------------------------------------------------------ responses
    def _solutions(self, x, gradient):
        mech = self.mech
        model = mech.design_model(x)
        props = model.element_properties()
        dprops = mech.element_property_derivatives(x)
        out = {}
        for b in self.loads:
            sol = solve_static(b.stiffness, b.g_eq, props, dprops if gradient else None)
            ks = b.stiffness
            nd = len(ks.dofs)
            u = np.zeros((self.nt, nd))
            u[:, ks.free] = sol.u
            du = None
            if gradient:
                du = np.zeros((self.nt, nd, dprops.shape[2]))
                du[:, ks.free, :] = np.transpose(sol.du, (1, 2, 0))
            out[b.name] = (u, du, b)
        return out

    def _point(self, sol, beam, point, gradient):
        """R_0,n u_n of a beam's point: (nt, 2) and (nt, 2, nv) or None."""
        u, du, b = sol[beam]
        k = b.stiffness.nodes.index(self.mech.node[(beam, point)])
        c, s = np.cos(b.angle)[:, None], np.sin(b.angle)[:, None]
        loc = u[:, 3 * k:3 * k + 2]
        w = np.column_stack([c[:, 0] * loc[:, 0] - s[:, 0] * loc[:, 1],
                             s[:, 0] * loc[:, 0] + c[:, 0] * loc[:, 1]])
        dw = None
        if gradient:
            dl = du[:, 3 * k:3 * k + 2, :]
            dw = np.stack([c * dl[:, 0] - s * dl[:, 1], s * dl[:, 0] + c * dl[:, 1]], axis=1)
        return w, dw

    def _mass(self, r, x, sol, nv, gradient):
        """A mass is a function of the design alone: its value and gradient as simulated."""
        return self.problem._response(r, x, None, gradient)

    def _deviation(self, r, x, sol, nv, gradient):
        """(nvar, nt) values and (nvar, nt, nv) gradients of a deviation's chain variants."""
        ref = self.mech.reference.q
        vals, grads = [], []
        for combo in zip(self.variants[r.name], self.turns[r.name]):
            comps, dcomps = [], []
            for t, diff, turns in zip(r.terms, *combo):
                w = np.zeros((self.nt, 2))
                dw = np.zeros((self.nt, 2, nv))
                for (beam, _, q), coef in diff.items():
                    a, da = self._point(sol, beam, q, gradient)
                    w += coef * a
                    if gradient:
                        dw += coef * da
                for beam, p, q, coef, target in turns:
                    u, du, b = sol[beam]
                    kq = b.stiffness.nodes.index(self.mech.node[(beam, q)])
                    kp = b.stiffness.nodes.index(self.mech.node[(beam, p)])
                    phi = u[:, 3 * kq + 2] - u[:, 3 * kp + 2]
                    nq, nt_ = self.mech.node[(beam, q)], self.mech.node[target]
                    lx = ref[:, 3 * nt_] - ref[:, 3 * nq]
                    ly = ref[:, 3 * nt_ + 1] - ref[:, 3 * nq + 1]
                    w += coef * np.column_stack([-phi * ly, phi * lx])
                    if gradient:
                        dphi = du[:, 3 * kq + 2, :] - du[:, 3 * kp + 2, :]
                        dw += coef * np.stack([-dphi * ly[:, None], dphi * lx[:, None]], axis=1)
                if t.frame != "ground":
                    th = ref[:, 3 * self.mech.model.body(t.frame).first + 2]
                    c, s = np.cos(th), np.sin(th)
                    w = np.column_stack([c * w[:, 0] + s * w[:, 1], -s * w[:, 0] + c * w[:, 1]])
                    dw = np.stack([c[:, None] * dw[:, 0] + s[:, None] * dw[:, 1],
                                   -s[:, None] * dw[:, 0] + c[:, None] * dw[:, 1]], axis=1)
                pick = {"x": [0], "y": [1], "norm": [0, 1]}[t.component]
                comps.append(w[:, pick].T)
                dcomps.append(np.moveaxis(dw[:, pick, :], 1, 0))
            cc = np.concatenate(comps)
            v = np.sqrt(np.sum(cc * cc, axis=0))
            vals.append(v)
            if gradient:
                num = np.einsum("kt,ktv->tv", cc, np.concatenate(dcomps))
                grads.append(np.where(v[:, None] > 0, num / np.where(v > 0, v, 1.0)[:, None], 0.0))
        return np.array(vals), (np.array(grads) if gradient else None)

    def _stress(self, r, x, sol, nv, gradient):
        """(1, nt) largest E (|eps| + c |kappa|) over the beams and (1, nt, nv)."""
        mech = self.mech
        cm = mech.model.compile()
        vals, grads = [], []
        for name in r.bodies:
            u, du, b = sol[name]
            ks = b.stiffness
            body = mech.model.body(name)
            c, dc = mech.half_depths(x, name)      # refuses a 'given' section
            E = float(mech.materials[mech._bodies[name].material].E)
            # the body's nodes in its frame: reference X and the static displacement on it
            aref = ks.ref_angle
            xr, yr, pr = ks.q_ref[0::3], ks.q_ref[1::3], ks.q_ref[2::3]
            o, _ = ks.frame.place(xr[None], yr[None], pr[None], ks.nodes)
            cr, sr = np.cos(aref), np.sin(aref)
            base = np.empty(len(ks.dofs))
            base[0::3] = cr * (xr - o[0, 0]) + sr * (yr - o[0, 1])
            base[1::3] = -sr * (xr - o[0, 0]) + cr * (yr - o[0, 1])
            base[2::3] = pr - aref
            ids = np.asarray(body.elements, int)
            nen = int(cm.el_nen[ids[0]])
            pos = {int(g): k for k, g in enumerate(ks.dofs)}
            edofs = np.array([[pos[int(g) - 1] for g in cm.el_dofs[:3 * nen, e]] for e in ids])
            xi = gauss_points(nen)
            n, dn = shape(nen, xi)
            jac = 0.5 * cm.el_len[ids]
            r1, r2, rk = raw_strains(base[edofs], n, dn, jac)
            qe = (base + u)[:, edofs]
            e1, _, kap = raw_strains(qe, n, dn, jac)
            eps, kap = e1 - r1, kap - rk
            cc = c[None, :, None]
            vals.append((E * (np.abs(eps) + cc * np.abs(kap))).reshape(self.nt, -1))
            if gradient:
                de1, _, dkap = raw_strain_derivatives(qe, du[:, edofs, :], n, dn, jac)
                dn_ = E * (np.sign(eps)[..., None] * de1
                           + np.sign(kap)[..., None] * cc[..., None] * dkap
                           + np.abs(kap)[..., None] * dc[None, :, None, :])
                grads.append(dn_.reshape(self.nt, -1, nv))
        v = np.concatenate(vals, axis=1)
        j = np.argmax(v, axis=1)
        rows = np.arange(self.nt)
        g = np.concatenate(grads, axis=1)[rows, j][None] if gradient else None
        return v[rows, j][None], g

    def responses_at(self, x, gradient=True):
        """values[name] (nvar, nt) or a float, gradients[name] alike (or None)."""
        nv = len(self.mech.variables)
        sol = self._solutions(x, gradient)     # also sets the design (mass below)
        values, grads = {}, {}
        for r in self.responses:
            form = getattr(self, STATIC_FORMS[type(r)])
            values[r.name], grads[r.name] = form(r, x, sol, nv, gradient)
        return values, grads

    def static_to_simulated(self, x, loads, values):
        """{deviation response: ratio} of the static form to the simulation at design x, whose
        own ESL are `loads` and simulated response values `values` (the constrained deviations
        only). At the ESL design K^-1 g_eq = u (eq. 19): the static form is then the chain sum
        of the beams' displacements in their frames, so the ratio, the largest static value over
        the steps and chains divided by the largest simulated value over the steps, measures the
        frames alone (1: the chains reproduce the simulated deviation at its peak). Sets the
        static model's loads to `loads`."""
        constrained = {c.response for c in self.problem.description.constraints}
        devs = [r for r in self.responses if isinstance(r, Deviation) and r.name in constrained]
        if not devs:
            return {}
        self.set_loads(loads)
        static, _ = self.responses_at(x, gradient=False)
        out = {}
        for r in devs:
            sim = float(np.max(values[r.name]))
            out[r.name] = float(np.max(static[r.name])) / sim if sim > 0 else None
        return out

    def evaluate(self, x, gradient=True):
        """(f, df, g, J, groups, names): objective and constraint rows g <= 0 of the static
        model; a deviation with several chains gives each chain's rows (paper 34-35)."""
        d = self.problem.description
        t = self.mech.t
        nv = len(self.mech.variables)
        values, grads = self.responses_at(x, gradient)
        f = df = None
        if d.objective is not None:
            v, dv = values[d.objective.response], grads[d.objective.response]
            if np.ndim(v) == 2:
                v, dv = v.max(axis=0), (None if dv is None else dv[np.argmax(v, axis=0),
                                                                     np.arange(v.shape[1])])
            f, df = _scalar(v, dv, d.objective.over, None, t)
        g_all, j_all, groups, names = [], [], [], []
        ngroup = 0
        for c in d.constraints:
            if c.response not in values:          # no static form: checked by simulation
                continue
            v, dv = values[c.response], grads[c.response]
            for k in range(np.shape(v)[0] if np.ndim(v) == 2 else 1):
                vv = v[k] if np.ndim(v) == 2 else v
                dd = None if dv is None else (dv[k] if np.ndim(v) == 2 else dv)
                g, J, nm, grp = constraint_rows(SimpleNamespace(constraints=[c]),
                                                {c.response: vv}, {c.response: dd}, t, nv,
                                                gradient)
                g_all.append(g)
                if gradient:
                    j_all.append(J)
                groups.append(grp + ngroup)
                ngroup += (grp.max() + 1) if grp.size else 0
                names += nm
        # the smoothness limits of element-wise variables: linear, one group per variable
        A, b, lin = self.mech.linear_constraints()
        for name in dict.fromkeys(lin):
            rows = [k for k, n in enumerate(lin) if n == name]
            g_all.append(A[rows] @ np.asarray(x, float) - b[rows])
            if gradient:
                j_all.append(A[rows])
            groups.append(np.full(len(rows), ngroup))
            ngroup += 1
            names += [name] * len(rows)
        g = np.concatenate(g_all) if g_all else np.zeros(0)
        J = (np.vstack(j_all) if j_all else np.zeros((0, nv))) if gradient else None
        return f, df, g, J, (np.concatenate(groups) if groups else np.zeros(0, int)), names


# ---------------------------------------------------------------------------- static optimum
def _optimize_static(static, x0, lower, upper, *, screen, ftol, maxiter, active_tol):
    """Solve (23) with SLSQP on z = x / upper, objective f / |f(x0)|, screening the rows."""
    from scipy.optimize import minimize

    scale = np.asarray(upper, float)
    f0, _, _, _, _, _ = static.evaluate(x0, gradient=False)
    fs = abs(f0) if f0 else 1.0
    cache = {}

    def ev(z):
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = static.evaluate(z * scale, gradient=True)
        return cache[key]

    def select(g, groups, current):
        level = g + 1.0
        keep = current.copy()
        for k in np.unique(groups):
            m = groups == k
            top = level[m].max()
            keep[m] |= (level[m] >= screen * top) if top > 0 else True
        return keep

    z = np.clip(np.asarray(x0, float), lower, upper) / scale
    zl, zu = lower / scale, upper / scale
    _, _, g, _, groups, names = static.evaluate(z * scale, gradient=False)
    keep = select(g, groups, np.zeros(g.size, bool))
    nit, res = 0, None
    for _ in range(20):
        idx = np.flatnonzero(keep)
        cons = [{"type": "ineq", "fun": lambda z, idx=idx: -ev(z)[2][idx],
                 "jac": lambda z, idx=idx: -ev(z)[3][idx] * scale}] if idx.size else []
        res = minimize(lambda z: (ev(z)[0] / fs, ev(z)[1] * scale / fs), z, jac=True,
                       method="SLSQP", bounds=list(zip(zl, zu)), constraints=cons,
                       options=dict(ftol=ftol, maxiter=maxiter))
        nit += int(res.nit)
        z = np.clip(res.x, zl, zu)
        _, _, g, _, groups, names = static.evaluate(z * scale, gradient=False)
        violated = (g > FEASIBILITY_TOL) & ~keep
        if not violated.any():
            break
        keep = select(g, groups, keep)
    x = z * scale
    f, _, g, _, groups, names = static.evaluate(x, gradient=False)
    active = {}
    for k in np.unique(groups):
        rows = np.flatnonzero(groups == k)
        hit = (np.flatnonzero(g[rows] >= -active_tol) + 1).tolist()
        active[f"{names[rows[0]]}#{k + 1}"] = hit
    return SimpleNamespace(x=x, objective=float(f), iterations=nit, success=bool(res.success),
                           message=str(res.message),
                           max_violation=float(g.max()) if g.size else -np.inf,
                           active_steps=active, screened_rows=int(keep.sum()))


# ---------------------------------------------------------------------------- cycles
def blend_loads(loads, previous, weight):
    """ESL of the last two cycles averaged: g = (1 - weight) g_current + weight g_previous for
    every body and time step (the frames' origins and angles are the current cycle's).
    weight 0 or no previous loads: `loads` itself."""
    if previous is None or weight == 0.0:
        return loads
    out = []
    for b in loads:
        p = previous[b.name]
        if p.g_eq.shape != b.g_eq.shape:
            raise ModelError(f"body {b.name!r}: ESL of different shapes {p.g_eq.shape} and "
                             f"{b.g_eq.shape} (different time grids?)")
        out.append(dataclasses.replace(b, g_eq=(1.0 - weight) * b.g_eq + weight * p.g_eq))
    return EquivalentStaticLoads(out)


def _simulate_design(problem, x):
    """Simulate design x (every coordinate stored, for the ESL): (result, response values,
    constraint rows g, their names, the constrained deviation history)."""
    result = problem.simulate(x, store="all")
    values = {}
    for r in problem.description.responses:
        values[r.name], _ = problem._response(r, x, result, False)
    g, _, names, _ = constraint_rows(problem.description, values, {}, problem.mechanism.t,
                                     len(problem.variables), False)
    return result, values, g, names, problem.constrained_deviation(values)


def _active_rows(g, names, active_tol):
    """{response: 1-based rows of its constraint block with g >= -active_tol}."""
    rows = {}
    for j, name in enumerate(names):
        rows.setdefault(name, []).append(j)
    return {n: (np.flatnonzero(g[idx] >= -active_tol) + 1).tolist() for n, idx in rows.items()}


def optimize_weakly(problem, x0=None, *, options=None, history=None, progress=None,
                    resume=False, **keywords):
    """Optimize a problem with the weakly coupled method (paper 5.3).

    Parameters
    ----------
    problem : flexmbs.problem.Problem, or a case path, the name of a shipped case, a dict or a
        Description
    x0 : array, optional
        Starting design in the variables' units; default the problem's start.
    options : flexmbs.model.options.WeaklyOptions or dict, optional
        The method's options (one table in `flexmbs.model.options.WeaklyOptions` and
        docs/optimizers.md; default: the case's ``[optimize.weakly]`` table, else the
        defaults):
        eps : float, default 1e-2
            Tolerance of the relative ESL change, eq. (25) (the largest over the ESL bodies).
        max_cycles : int, default 30
            Maximum number of cycles (MBS analyses).
        confirm_cycles : int, default 1
            Eq. (25) must hold in 1 + confirm_cycles consecutive cycles (0: the paper's test).
        move_limit : float, optional
            Relative move limit per cycle (bounds clipped to x (1 -+ move_limit)); a remedy
            against oscillation.
        frames : dict beam -> point, optional
            Frame point of a beam (default: where the chains enter it; stress-only beams: `from`).
        frame_kind : {'auto', 'tangent', 'chord'} or dict beam -> kind, default 'auto'
            Corotational frame of every ESL beam at its frame point: 'tangent' to the beam there
            (static load cases clamped at that point; the paper's eqs. 16-19), 'chord', from that
            point to the beam's other end (simply supported), or 'auto': chosen per beam from its
            joints by `frame_by_joints` (tangent where the beam's rotation at its frame point is
            held: clamp, weld, driven rotation; chord for a beam pinned or hinged at both ends,
            as the four-bar's coupler and follower and the press's rod). A dict sets it per beam
            (beams not named: 'auto'). docs/optimizers.md, "Corotational frames".
        screen : float in [0, 1], default 0.3
            The static problem starts with the rows (time steps) whose value is at least
            `screen` times the current maximum of its constraint (0: all rows); rows found
            violated at its solution are added and the problem solved again.
        ftol : float, default 1e-8
            SLSQP's tolerance (objective normalized by the cycle's starting value).
        max_inner : int, default 200
            SLSQP iterations per static problem.
        active_tol : float, default 1e-3
            A row counts as active when g >= -active_tol (history's active_steps).
        stop_on_oscillation : bool, default True
            Stop when the designs repeat with a period of 2 to 6 cycles (diagnosis
            'oscillating') or the ESL change grows cycle after cycle ('diverging').
        damping : float in (0, 1], default 1
            Damped design update x_next = x + damping (x_static_optimum - x) (1: the paper's
            update); a remedy against oscillation.
        esl_blend : float in [0, 1), default 0
            The static problem (23) takes the ESL of the last two cycles averaged,
            (1 - esl_blend) g_k + esl_blend g_(k-1) (0: the paper's, the current ESL only); a
            remedy against oscillation. Test (25) always compares the cycles' own ESL.
        design_tol : float, optional
            Also converged when the largest relative change of a design variable that the static
            optimization proposed (x* - x, before damping) is below design_tol and the cycle's
            design is feasible (simulated), in 1 + confirm_cycles consecutive cycles (a criterion
            of the kind of OptiStruct's ESLM outer loop: design change and constraint violation).
        shrink : float in [0, 1), default 0.5
            On an oscillation the cycles go on with relative move limits per variable
            (`flexmbs.methods.cycles.ShrinkingMoveLimit`): shrink times the oscillation's
            amplitude, then shrunk by `shrink` for each variable whose change reverses its
            direction; the design-change criterion (design_tol, else SHRINK_DESIGN_TOL = 1e-3)
            ends the settled cycles. 0: stop on the oscillation (the paper's cycles).
        verify : bool, float or 'check', default True
            Verify the final design at converged resolution (as `optimize_fully`'s verify: when
            it is infeasible at the step that resolves its responses to 1e-3, the cycles continue
            at that step from the design, and the new design is verified in turn).
    history : str, path or HistoryWriter, optional
        File receiving one JSON line per cycle as the run goes.
    progress : bool, text stream or callable, optional
        True: a tqdm bar on stderr (cycle, mass, violation, ESL change); a text stream: that
        bar on the stream; a callable: called with each history record; None/False
        (default): nothing shown (`flexmbs.progress`).
    resume : bool, default False
        Continue an interrupted run from its `history` file (required; a missing file starts
        afresh): the cycles it recorded are taken from the file, the designs of its last
        two cycles are simulated again (the previous ESL, for eq. (25), and the last cycle's
        own), and the run goes on from there exactly as the interrupted one would have,
        appending to the file. details resumed_cycles: the cycles taken from the file.
    **keywords
        Deprecated: the options as keywords (eps=..., max_cycles=..., ...), with a
        DeprecationWarning naming the options= spelling.

    Returns
    -------
    flexmbs.optimize.OptimizationResult
        method 'weakly'; iterations = cycles (MBS analyses); inner_iterations = SLSQP
        iterations summed. A converged run returns its last design; a run that stops
        oscillating, diverging or at the cycle cap returns the best feasible design seen
        (lowest objective among the cycles whose simulation satisfied every constraint; the
        last design when none did), its cycle in details best_feasible_cycle and the last
        cycle's design in details last_design. details: diagnosis ('converged',
        'oscillating', 'diverging' or 'cap'), predicted_max_violation (static model,
        normalised g of the final design), feasible, paper_test_cycle (the cycle at which
        eq. (25) first held), static_optimizations, oscillation_period, esl_change,
        esl_bodies, frames, frame_kinds (the kind each ESL beam got), damping, esl_blend,
        design_tol, options (the WeaklyOptions used, as plain data), static_to_simulated
        ({constrained deviation: the largest static value over steps and chains / the largest
        simulated value} at the returned design, from its own ESL:
        `StaticModel.static_to_simulated`; also in every cycle's history record).
    """
    t_start = time.perf_counter()
    if keywords:
        options = from_keywords("optimize_weakly", WeaklyOptions, options, keywords)
    opts = None if options is None else build(WeaklyOptions, options)
    problem = load_problem(problem)
    if opts is None:        # the case's [optimize.weakly] table when the call gives none
        section = getattr(problem.description, "optimize", None)
        opts = WeaklyOptions() if section is None else section.weakly
    verify = opts.verify
    eps, max_cycles, confirm_cycles = opts.eps, opts.max_cycles, opts.confirm_cycles
    max_inner, ftol, active_tol = opts.max_inner, opts.ftol, opts.active_tol
    move_limit, screen = opts.move_limit, opts.screen
    frames, frame_kind = (None if opts.frames is None else dict(opts.frames)), opts.frame_kind
    if isinstance(frame_kind, dict):
        frame_kind = dict(frame_kind)
    stop_on_oscillation = opts.stop_on_oscillation
    damping, esl_blend, design_tol = check_remedies(opts.damping, opts.esl_blend,
                                                    opts.design_tol)
    d = problem.description
    mech = problem.mechanism
    if not mech.variables:
        raise CaseError("the weakly coupled method needs design variables ([[design]])")
    if d.objective is None:
        raise CaseError("the weakly coupled method needs an [objective]")
    check_progress(progress)
    if not isinstance(resume, bool):
        raise ModelError(f"resume must be True or False, got {resume!r}")
    lower, upper = problem.lower, problem.upper
    x = mech.start.copy() if x0 is None else mech.design_values(x0).copy()
    if np.any(x < lower) or np.any(x > upper):
        raise ModelError(f"x0 = {x.tolist()} lies outside the bounds [{lower.tolist()}, "
                         f"{upper.tolist()}]")
    static = StaticModel(problem, frames, frame_kind)
    if not static.frames:
        raise CaseError("the weakly coupled method: no constraint or objective depends on a "
                        "beam's deformation (no deviation chain through a beam, no stress)")
    mass_resp = [r for r in d.responses if isinstance(r, Mass)]

    writer, own_writer = open_history(history, resume)
    used = opts.as_dict()
    # what a history answers: the options used (but the cycle limit) and the start
    writer.check_fingerprint(fingerprint(problem.description, "weakly",
                                         run_options(dict(used, x0=x))), options=used)
    prev_loads, pending, x_prev = None, None, x
    control = CycleControl(eps, confirm_cycles, max_cycles, stop_on_oscillation, design_tol)
    mover = ShrinkingMoveLimit(opts.shrink, move_limit) if opts.shrink > 0 else None
    inner_total = n_static = 0
    change = None
    values = g_dyn = names = result = None
    progress = reporter(progress, total=max_cycles, label="cycles", describe=describe_cycle,
                        position=lambda r: r["iteration"])
    first, resumed = 1, 0
    try:
        if resume and writer.previous:
            first, x, x_prev, prev_loads, pending, inner_total, n_static = _resume_cycles(
                problem, static, writer, control, progress, x, max_cycles, mover)
            resumed = first - 1
        for cycle in range(first, max_cycles + 1):
            result, values, g_dyn, names, dev = _simulate_design(problem, x)
            model = mech.design_model(x)
            loads = equivalent_static_loads(model, result, static.frames,
                                            stiffness=static.stiffness,
                                            props=model.element_properties())
            changes = None if prev_loads is None else esl_change(loads, prev_loads)
            change = None if changes is None else max(changes.values())
            ratios = static.static_to_simulated(x, loads, values)
            record = dict(
                iteration=cycle, design=x, mass_kg=problem.design_mass(x, values),
                objective=float(_scalar(values[d.objective.response], None, d.objective.over,
                                        None, mech.t)[0]),
                max_violation=float(g_dyn.max()) if g_dyn.size else None,
                max_deviation_m=None if dev is None else float(dev.max()),
                t_at_max_s=None if dev is None else float(mech.t[int(np.argmax(dev))]),
                esl_change=change, esl_change_per_body=changes,
                inner_iterations=None if pending is None else pending.iterations,
                predicted_max_violation=None if pending is None else pending.max_violation,
                active_steps=None if pending is None else pending.active_steps,
                simulation_active_steps=_active_rows(g_dyn, names, active_tol),
                static_message=None if pending is None or pending.success else pending.message,
                static_design=None if pending is None else pending.x,
                static_to_simulated=ratios)
            control.observe(cycle, x, change, record, objective=record["objective"],
                            violation=record["max_violation"],
                            data=(record, values, g_dyn, names, dev),
                            step=None if pending is None else float(np.max(
                                np.abs(pending.x - x_prev) / np.abs(x_prev))))
            _shrink_on_oscillation(control, mover, cycle, record)
            writer.write(record)
            if progress is not None:
                progress(writer.records[-1])
            if control.stop(cycle):
                break
            lo, hi = (move_limited_bounds(x, lower, upper, move_limit) if mover is None
                      else mover.bounds(x, lower, upper))
            static.set_loads(blend_loads(loads, prev_loads, esl_blend))
            pending = _optimize_static(static, x, lo, hi, screen=screen, ftol=ftol,
                                       maxiter=max_inner, active_tol=active_tol)
            inner_total += pending.iterations
            n_static += 1
            prev_loads = loads
            x_prev, x = x, damped_update(x, pending.x, damping)
            if mover is not None and len(control.designs) >= 2:
                mover.step(control.designs[-2], x_prev, x)
    finally:
        if own_writer:
            writer.close()
        if progress is not None:
            progress.close()
    last_design, last_record = x.copy(), record
    best = control.best
    use_best = (not control.converged and best is not None and best.cycle != len(control.designs))
    if use_best:                  # the best feasible design seen: its own cycle's simulation
        x = best.design.copy()
        if best.data is None:     # a cycle taken from the history of a resumed run
            best.data = _cycle_data(problem, x, writer.records[best.cycle - 1])
        record, values, g_dyn, names, dev = best.data
    mech.set_design(x)
    final_violation = float(g_dyn.max()) if g_dyn.size else None
    feasible = is_feasible(final_violation)
    reason = control.reason
    if mover is not None and mover.active:
        reason += (f"; the designs oscillated (period {mover.periods[0]}, cycle {mover.cycle}): "
                   f"the cycles went on with move limits shrinking by {mover.shrink:g}, "
                   f"now {np.max(mover.limits):.2g} at most")
    if use_best:
        lv = last_record["max_violation"]
        reason += (f"; returned the best feasible design seen (cycle {best.cycle}, "
                   f"objective {record['objective']:.4g}; the last cycle's design: "
                   f"{last_record['objective']:.4g}"
                   + ("" if lv is None else f", largest constraint value {lv:.3g}") + ")")
    unmodelled = [c.response for c in d.constraints if c.response in static.unmodelled]
    if unmodelled:
        reason += (f"; constraints with no static form, left out of the static optimization "
                   f"and checked by simulation only: {', '.join(dict.fromkeys(unmodelled))}")
    if not feasible:
        worst = int(np.argmax(g_dyn))
        names = constraint_rows(d, values, {}, mech.t, len(problem.variables), False)[2]
        reason += (f"; the final design violates {names[worst]!r} by {final_violation:.3g} "
                   "(relative to its limit, simulated; no cycle's design was feasible)"
                   if best is None else
                   f"; the final design violates {names[worst]!r} by {final_violation:.3g} "
                   "(relative to its limit, simulated)")
    if not control.converged:
        reason += "; " + what_to_try(control.diagnosis, opts.shrink, damping, max_cycles)
    details = dict(
        predicted_max_violation=(None if pending is None or use_best
                                 else pending.max_violation),
        feasible=feasible, diagnosis=control.diagnosis,
        best_feasible_cycle=None if best is None else best.cycle,
        last_design=last_design.tolist(), last_mass_kg=last_record["mass_kg"],
        last_max_violation=last_record["max_violation"],
        damping=damping, esl_blend=esl_blend, design_tol=design_tol, options=used,
        constraints_checked_by_simulation=list(dict.fromkeys(unmodelled)),
        max_deviation_responses=[r.name for r in d.responses if isinstance(r, Deviation)
                                 and r.name in {c.response for c in d.constraints}],
        paper_test_cycle=control.paper_cycle, static_optimizations=n_static,
        oscillation_period=(control.period if mover is None or not mover.periods
                            else mover.periods[0]),
        shrink=opts.shrink, shrink_cycle=None if mover is None else mover.cycle,
        move_limits=None if mover is None or not mover.active else mover.limits.tolist(),
        esl_change=change, eps=eps,
        confirm_cycles=confirm_cycles,
        move_limit=move_limit, frame=frame_kind if isinstance(frame_kind, str) else "mixed",
        frame_kinds=dict(static.kinds), frames=dict(static.entry),
        static_to_simulated=record.get("static_to_simulated"),
        esl_bodies=[n for n, _ in static.frames], variables=list(mech.variables),
        t_end=float(mech.t[-1]),
        active_steps=(record["active_steps"] if use_best else
                      None if pending is None else pending.active_steps),
        mass_responses=[r.name for r in mass_resp])
    if resume:
        details["resumed_cycles"] = resumed
    result = OptimizationResult(
        method="weakly", case=d.case.name, variables=list(mech.variables),
        units=list(mech.units), design=x.copy(), start=control.designs[0],
        objective=record["objective"], objective_name=d.objective.response,
        mass_kg=record["mass_kg"],
        max_violation=None if final_violation is None else max(0.0, final_violation),
        max_deviation_m=record["max_deviation_m"], iterations=len(control.designs),
        inner_iterations=inner_total, evaluations=len(control.designs),
        simulations=len(control.designs) - resumed + (resumed > 0),
        converged=control.converged, reason=reason,
        history=list(writer.records), wall_time_s=time.perf_counter() - t_start,
        details=details, t=np.asarray(mech.t), deviation=dev)
    # a continuation on a finer step (flexmbs.methods.verified): the same options, unverified
    again = opts.model_copy(update=dict(verify=False))
    return finish(problem, result, lambda fine, x: optimize_weakly(fine, x, options=again),
                  verify)


def _resume_cycles(problem, static, writer, control, progress, x0, max_cycles, mover=None):
    """The state of an interrupted run after the cycles of its history (`writer.previous`):
    cycles 1 .. c-1 are taken from the file (`control` observes them, `writer` and `progress`
    get their records), the design of cycle c-1 is simulated again for its ESL (eq. (25) of
    cycle c) and the static problem that produced cycle c's design is restored from cycle c's
    record; cycle c itself is run again (its record is checked against the file's).
    Returns (c, design of cycle c, design of cycle c-1, ESL of cycle c-1, static result,
    inner iterations so far, static optimizations so far)."""
    recs = writer.previous[:max_cycles]
    if not np.array_equal(np.asarray(recs[0]["design"], float), x0):
        raise ModelError(f"history {writer.path!r} starts from design {recs[0]['design']}, "
                         f"this run from {x0.tolist()}: resume with the same start")
    c = len(recs)
    for k, rec in enumerate(recs[:-1]):
        control.observe(rec["iteration"], np.asarray(rec["design"], float),
                        rec.get("esl_change"), dict(rec), objective=rec.get("objective"),
                        violation=rec.get("max_violation"), step=rec.get("design_change"))
        _shrink_on_oscillation(control, mover, rec["iteration"], {})
        if mover is not None and k >= 1:
            mover.step(*(np.asarray(r["design"], float) for r in recs[k - 1:k + 2]))
        writer.write(rec)
        if progress is not None:
            progress(rec)
    last = recs[-1]
    x = np.asarray(last["design"], float).copy()
    prev_loads = pending = None
    xp = x
    if c > 1:
        xp = np.asarray(recs[-2]["design"], float)
        result = problem.simulate(xp, store="all")
        model = problem.mechanism.design_model(xp)
        prev_loads = equivalent_static_loads(model, result, static.frames,
                                             stiffness=static.stiffness,
                                             props=model.element_properties())
        xs = last.get("static_design")       # the static optimum before damping
        pending = SimpleNamespace(x=x if xs is None else np.asarray(xs, float),
                                  iterations=last.get("inner_iterations") or 0,
                                  max_violation=last.get("predicted_max_violation"),
                                  active_steps=last.get("active_steps"),
                                  success=last.get("static_message") is None,
                                  message=last.get("static_message"))
    inner = sum(r.get("inner_iterations") or 0 for r in recs[1:])
    return c, x, xp, prev_loads, pending, inner, c - 1


def _shrink_on_oscillation(control, mover, cycle, record):
    """An oscillation the control found at this cycle, with a shrinking move limit: the limits
    shrink (`ShrinkingMoveLimit.oscillation`), the control goes on (its period is noted in
    `mover.periods`, not a stop) with the design-change criterion (design_tol, else
    SHRINK_DESIGN_TOL). `record` gets the move limits of the next static optimization."""
    if mover is None:
        return
    if control.period is not None and not control.converged:
        mover.oscillation(cycle, control.designs, control.period)
        mover.periods.append(control.period)
        control.period = None
        if control.design_tol is None:
            control.design_tol = SHRINK_DESIGN_TOL
    if mover.active:
        record["move_limits"] = mover.limits.tolist()


def _cycle_data(problem, x, record):
    """(record, values, g_dyn, names, deviation) of a cycle taken from a resumed run's history:
    its design simulated again (the dynamic responses are not in the history)."""
    return (dict(record),) + _simulate_design(problem, x)[1:]
