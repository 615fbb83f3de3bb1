"""Responses at a station along a beam: anywhere between its nodes, not only at named points.

A station is the fraction s (0 to 1) of a beam's reference length from its first node. With n
equal elements it lies in element k = floor(s n) (the last one at s = 1; at an element
boundary, the element after it) at the natural coordinate xi = 2 (s n - k) - 1. The element's
own Lagrange shape functions N_a(xi) (flexmbs.responses.strain.shape, fortran/beam2d.f90)
interpolate its nodes' coordinates there: position r(s) = sum N_a r_a, rotation
phi(s) = sum N_a phi_a, and the strains of flexmbs.responses.strain at xi. At the element's
Gauss points (its reduced-integration stations) the strains are those the element itself
evaluates; elsewhere they are the same interpolation, less accurate.

Responses (each with design derivatives from Result.dq, linear in dq: so the same code gives
the discrete adjoint's per-step partials when dq is an identity):

    locate(model, body, s)              the StationPoint (element, nodes, xi, shape values)
    chord_deflection(result, point)     distance of the station from the chord through the
                                        beam's end nodes (signed, positive on the chord's left)
    station_strain(model, result, point, component)   axial, shear strain or curvature

A deviation term at a station (flexmbs.responses.deviation.deviation_terms) takes the
StationPoint in place of a node id; a stress at a station is flexmbs.responses.stress.beam_stress
at stations=[xi], element `point.index` of the beam.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.responses.deviation import _history
from flexmbs.responses.strain import raw_strain_derivatives, raw_strains, shape

__all__ = ["StationPoint", "locate", "chord_deflection", "station_strain", "STRAIN_COMPONENTS"]

#: station_strain's components: Gamma_1, Gamma_2, kappa (flexmbs.responses.strain)
STRAIN_COMPONENTS = ("axial", "shear", "curvature")


@dataclass(frozen=True)
class StationPoint:
    """A station of a beam (see the module docstring).

    body, s: the beam and the fraction of its length; index: the element's position in the
    beam (0 from its first node); element: its global id; nodes: its node ids (nen,); xi: the
    natural coordinate; n, dn: the shape functions and dN/dxi at xi (nen,); length: the
    element's reference length; first, last: the beam's end nodes."""
    body: str
    s: float
    index: int
    element: int
    nodes: tuple
    xi: float
    n: np.ndarray
    dn: np.ndarray
    length: float
    first: int
    last: int


def locate(model, body, s):
    """The StationPoint at fraction s (0 to 1) of the length of beam `body` of `model`."""
    b = model.body(body) if isinstance(body, str) else body
    if getattr(b, "kind", None) != "beam":
        raise ModelError(f"station: body {getattr(b, 'name', body)!r} is not a beam (a station "
                         "s along a body exists on beams only)")
    if isinstance(s, bool) or not isinstance(s, (int, float, np.floating, np.integer)) \
            or not 0.0 <= float(s) <= 1.0:
        raise ModelError(f"station of beam {b.name!r}: s must be a number in [0, 1] (the "
                         f"fraction of the beam's length from its first node), got {s!r}")
    nel = len(b.elements)
    u = float(s) * nel
    # a station on an element boundary (s n a whole number up to rounding, e.g. 0.58 of 50
    # elements: 28.999999999999996) is in the element after it, at xi = -1
    k = min(int(math.floor(u + 1e-9 * max(1, nel))), nel - 1)
    xi = min(1.0, max(-1.0, 2.0 * (u - k) - 1.0))
    e = b.elements[k]
    ids, length, _ = model._elements[e]
    n, dn = shape(len(ids), np.array([xi]))
    return StationPoint(body=b.name, s=float(s), index=k, element=int(e), nodes=tuple(ids),
                        xi=xi, n=n[:, 0], dn=dn[:, 0], length=float(length),
                        first=int(b.first), last=int(b.last))


def _position(result, point, derivatives):
    """r(s) (nt, 2) and its derivatives (nt, 2, nv) or None."""
    r = dr = 0.0
    for a, w in zip(point.nodes, point.n):
        q, dq = _history(result, [3 * a, 3 * a + 1], derivatives)
        r = r + w * q
        if derivatives:
            dr = dr + w * dq
    return r, (dr if derivatives else None)


def chord_deflection(result, point, derivatives=False):
    """Deflection of the station from the chord through its beam's end nodes A, B:
    w = (c x p) / |c| with c = r_B - r_A, p = r(s) - r_A (the z component of the cross
    product: positive on the left of the chord A -> B), (nt,), and its design derivatives
    (nt, nv) or None:

        dw = [(c x dp) + (dc x p)] / |c| - w (c . dc) / |c|^2,   dp = dr - dr_A, dc = dr_B - dr_A.
    """
    r, dr = _position(result, point, derivatives)
    ra, dra = _history(result, [3 * point.first, 3 * point.first + 1], derivatives)
    rb, drb = _history(result, [3 * point.last, 3 * point.last + 1], derivatives)
    c, p = rb - ra, r - ra
    length = np.hypot(c[:, 0], c[:, 1])
    w = (c[:, 0] * p[:, 1] - c[:, 1] * p[:, 0]) / length
    if not derivatives:
        return w, None
    dc, dp = drb - dra, dr - dra
    cross = (c[:, 0, None] * dp[:, 1] - c[:, 1, None] * dp[:, 0]
             + dc[:, 0] * p[:, 1, None] - dc[:, 1] * p[:, 0, None])
    dot = c[:, 0, None] * dc[:, 0] + c[:, 1, None] * dc[:, 1]
    return w, cross / length[:, None] - (w / length ** 2)[:, None] * dot


def station_strain(model, result, point, component="axial", derivatives=False):
    """Strain `component` ('axial' Gamma_1, 'shear' Gamma_2, 'curvature' kappa, 1/m) at the
    station, from the reference configuration, (nt,), and its design derivatives (nt, nv)
    or None."""
    if component not in STRAIN_COMPONENTS:
        raise ModelError(f"station_strain: component must be one of "
                         f"{', '.join(STRAIN_COMPONENTS)}, got {component!r}")
    k = STRAIN_COMPONENTS.index(component)
    dofs = [3 * a + c for a in point.nodes for c in range(3)]
    q, dq = _history(result, dofs, derivatives)
    n, dn = point.n[:, None], point.dn[:, None]
    jac = np.array([0.5 * point.length])
    qref = model.compile().qref[dofs]
    ref = raw_strains(qref[None, :], n, dn, jac)[k][0, 0]
    value = raw_strains(q[:, None, :], n, dn, jac)[k][:, 0, 0] - ref
    if not derivatives:
        return value, None
    d = raw_strain_derivatives(q[:, None, :], dq[:, None, :, :], n, dn, jac)[k]
    return value, d[:, 0, 0, :]
