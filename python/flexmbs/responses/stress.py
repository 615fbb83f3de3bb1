"""Stress in the beams: normal stress at the extreme fibres, mean shear stress, von Mises.

At a station of an element (see `beam_stress`, stations) the beam's strains are those of the
element itself (flexmbs.responses.strain, fortran/beam2d.f90): axial strain eps = Gamma_1,
shear strain gamma = Gamma_2, curvature kappa, all measured from the reference configuration.
With E the material's Young's modulus and c the half-depth of the section (Circle and Tube:
d/2, Rectangle: h/2; the distance of the extreme fibres from the neutral axis), the normal
stress of the fibres at -c and +c is E (eps -/+ c kappa) (Euler-Bernoulli / Navier, with the
material law N = EA eps, M = EI kappa of the element). The response is the larger in absolute
value of the two, per sample (time step, element, station):

    sigma = max(|E (eps - c kappa)|, |E (eps + c kappa)|) = E (|eps| + c |kappa|).

Optionally the mean shear stress over the shear area A_s = k A of the section (k: Cowper's
shear factor, flexmbs.model.sections), tau = Q / A_s = kGA gamma / (k A) = G |gamma|, and the von
Mises combination sqrt(sigma^2 + 3 tau^2). The latter adds the mean shear of the section to
the normal stress of its extreme fibre, where the shear stress of these sections vanishes: it
is conservative, an upper bound of the von Mises stress of the section under Navier's and
Jourawski's distributions only where tau is the largest shear stress (it is not: the peak of
a solid circle is 4/3 Q/A); use it as a design measure, not as a local stress analysis.

Design gradients (`dc` given): from the design derivatives of the coordinates, Result.dq, of
the body's elements (simulate with DesignDerivatives' properties and dofs covering them) and
from the explicit dependence of c on the design, dc/dp (nel_body, nv), which the caller builds
from its design variables (c = d/2 of a diameter variable: dc/dd = 1/2). E is a material
constant, not a design variable:

    d sigma = E (sign(eps) d eps + sign(kappa) c d kappa + |kappa| dc),
    d tau = G sign(gamma) d gamma,    d vm = (sigma d sigma + 3 tau d tau) / vm.

Kinks: |eps|, |kappa| and |gamma| are not differentiable at zero; there sign(0) = 0 (the mean of
the one-sided derivatives) is used. A stress that changes sign over the design space (a beam
whose axial force passes through zero) makes its magnitude non-smooth there: aggregate with
'ks' or 'pnorm' (flexmbs.responses.aggregate) rather than expect a smooth history. The maximum
over the two fibres is taken per sample, never over the history, so the kink of the max over
fibres is exactly that of |eps| + c |kappa| above.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexmbs.errors import ModelError
from flexmbs.responses.strain import (columns, gauss_points, half_depth, raw_strain_derivatives,
                                      raw_strains, shape)

__all__ = ["BeamStress", "beam_stress", "normal_partials", "STATIONS"]

#: Named station sets: 'gauss' the reduced-integration Gauss points (where the element
#: evaluates its strains and stress resultants), 'nodes' the element's nodes (strains
#: extrapolated by the shape functions).
STATIONS = ("gauss", "nodes")


@dataclass
class BeamStress:
    """Stress histories of the elements of one beam at their stations.

    Attributes
    ----------
    t : (nt,) times.
    elements : (nel,) global element ids, from the beam's first node to its last.
    xi : (nst,) natural coordinates of the stations in each element.
    s : (nel, nst) arc length of each station from the beam's first node (reference).
    half_depth : (nel,) c of each element's section.
    axial : (nt, nel, nst) E eps (Pa, tension positive).
    bending : (nt, nel, nst) E c kappa (Pa; the stress of the fibre at -c from bending).
    normal : (nt, nel, nst) E (|eps| + c |kappa|): the larger |normal stress| of both fibres.
    shear, von_mises : (nt, nel, nst) G |gamma| and sqrt(normal^2 + 3 shear^2), or None.
    d_normal, d_shear, d_von_mises : (nt, nel, nst, nv) design derivatives, or None.
    dofs : (nel, 3 nen) 0-based coordinates of each element (with local=True).
    d_normal_local : (nt, nel, nst, 3 nen) d normal / d (the element's coordinates), or None.
    d_normal_dc : (nt, nel, nst) d normal / d c (the element's half depth), or None.
    """
    t: np.ndarray
    elements: np.ndarray
    xi: np.ndarray
    s: np.ndarray
    half_depth: np.ndarray
    axial: np.ndarray
    bending: np.ndarray
    normal: np.ndarray
    shear: np.ndarray | None = None
    von_mises: np.ndarray | None = None
    d_normal: np.ndarray | None = None
    d_shear: np.ndarray | None = None
    d_von_mises: np.ndarray | None = None
    dofs: np.ndarray | None = None
    d_normal_local: np.ndarray | None = None
    d_normal_dc: np.ndarray | None = None


def _stations(stations, nen):
    if isinstance(stations, str):
        if stations == "gauss":
            return gauss_points(nen)
        if stations == "nodes":
            return np.linspace(-1.0, 1.0, nen)
        raise ModelError(f"stations={stations!r} is unknown; allowed: {', '.join(STATIONS)} or "
                         "an array of xi in [-1, 1]")
    xi = np.atleast_1d(np.asarray(stations, float))
    if xi.ndim != 1 or xi.size == 0 or not np.all(np.isfinite(xi)) or np.abs(xi).max() > 1.0:
        raise ModelError(f"stations must be 'gauss', 'nodes' or a 1-d array of xi in [-1, 1], "
                         f"got {stations!r}")
    return xi


def beam_stress(model, result, body, *, stations="gauss", shear=False, dc=None, local=False):
    """Stress histories of a beam's elements (see the module docstring for the formulas).

    Parameters
    ----------
    model : flexmbs.Model
    result : flexmbs.Result
        Must hold the coordinates of the beam's nodes (simulate(...,
        settings=SimulationSettings(store=...))).
    body : str or Body
        A beam with a Material and sections with a depth (Circle, Tube, Rectangle).
    stations : {'gauss', 'nodes'} or array of xi in [-1, 1], default 'gauss'
        Where in each element: the Gauss points of the element's reduced integration (where
        it evaluates N, Q, M), its nodes, or given natural coordinates.
    shear : bool, default False
        Also the mean shear stress G |gamma| and the von Mises combination.
    dc : (nel, nv) array, optional
        d c / d p of each element of the beam (root first) for nv design variables. When
        given, the design derivatives are returned; they need result.dq with every
        coordinate of the beam among result.sens_dofs.
    local : bool, default False
        Also the partial derivatives of `normal` with respect to each element's own
        coordinates and half depth (d_normal_local, d_normal_dc; no design derivatives
        needed): what the discrete adjoint's right-hand sides are made of.

    Returns
    -------
    BeamStress
    """
    b = model.body(body) if isinstance(body, str) else body
    if getattr(b, "kind", None) != "beam" or model.bodies.get(b.name) is not b:
        raise ModelError(f"beam_stress: body must be a beam of this model, got {body!r}")
    mat = b.material
    if mat is None:
        raise ModelError(f"beam_stress: beam {b.name!r} has no material (a GivenSection beam has "
                         "no Young's modulus and no depth): give it a Material and a Circle, Tube "
                         "or Rectangle section")
    secs = model.element_sections(b)
    c = np.array([np.nan if half_depth(sec) is None else half_depth(sec) for sec in secs])
    if not np.all(np.isfinite(c)):
        k = int(np.argmax(~np.isfinite(c)))
        raise ModelError(f"beam_stress: element {k} of beam {b.name!r} has section {secs[k]!r}, "
                         "which has no depth: use a Circle, Tube or Rectangle")
    cm = model.compile()
    ids = np.asarray(b.elements, int)
    nen_set = {int(cm.el_nen[e]) for e in ids}
    if len(nen_set) != 1:
        raise ModelError(f"beam_stress: beam {b.name!r} mixes elements of {sorted(nen_set)} nodes")
    nen = nen_set.pop()
    xi = _stations(stations, nen)
    edofs = (cm.el_dofs[:3 * nen, ids] - 1).T.astype(np.int64)        # (nel, 3 nen)
    cols = columns(result.dofs, edofs)
    if np.any(cols < 0):
        raise ModelError(f"beam_stress: coordinates of beam {b.name!r} were not stored; "
                         "simulate with store='all' or a store list including the beam")
    nel = ids.size
    nv = None
    if dc is not None:
        dc = np.asarray(dc, float)
        if dc.ndim != 2 or dc.shape[0] != nel or not np.all(np.isfinite(dc)):
            raise ModelError(f"beam_stress: dc must be a finite ({nel}, nv) array (one row per "
                             f"element of beam {b.name!r}), got shape {dc.shape}")
        nv = dc.shape[1]
        if result.dq is None:
            raise ModelError("beam_stress: dc given but the result has no design derivatives; "
                             "simulate with derivatives=DesignDerivatives(properties, dofs) with "
                             f"dofs including the coordinates of beam {b.name!r}")
        if result.dq.shape[2] != nv:
            raise ModelError(f"beam_stress: dc has {nv} design variables, result.dq has "
                             f"{result.dq.shape[2]}")
        scols = columns(result.sens_dofs, edofs)
        if np.any(scols < 0):
            raise ModelError(f"beam_stress: coordinates of beam {b.name!r} are not among the "
                             "sensitivity coordinates (DesignDerivatives.dofs of "
                             "simulate(..., derivatives=...))")

    jac = 0.5 * cm.el_len[ids]
    n, dn = shape(nen, xi)
    r1, r2, rk = raw_strains(cm.qref[edofs], n, dn, jac)              # (nel, nst)
    qe = result.q[:, cols]                                              # (nt, nel, 3 nen)
    e1, e2, kap = raw_strains(qe, n, dn, jac)
    eps, gam, kap = e1 - r1, e2 - r2, kap - rk
    E = float(mat.E)
    cc = c[None, :, None]
    normal = E * (np.abs(eps) + cc * np.abs(kap))
    start = np.concatenate([[0.0], np.cumsum(cm.el_len[ids])[:-1]])
    s = start[:, None] + 0.5 * (xi[None, :] + 1.0) * cm.el_len[ids][:, None]
    out = BeamStress(t=np.asarray(result.t), elements=ids, xi=xi, s=s, half_depth=c,
                     axial=E * eps, bending=E * cc * kap, normal=normal)
    if shear:
        out.shear = float(mat.G) * np.abs(gam)
        out.von_mises = np.sqrt(normal ** 2 + 3.0 * out.shear ** 2)
    if local:
        eye = np.broadcast_to(np.eye(3 * nen), qe.shape + (3 * nen,))
        de1, _, dkap = raw_strain_derivatives(qe, eye, n, dn, jac)     # (nt, nel, nst, 3 nen)
        out.dofs = edofs
        out.d_normal_local = E * (np.sign(eps)[..., None] * de1
                                  + np.sign(kap)[..., None] * cc[..., None] * dkap)
        out.d_normal_dc = E * np.abs(kap)
    if nv is not None:
        dqe = result.dq[:, scols, :]                                    # (nt, nel, 3 nen, nv)
        de1, de2, dkap = raw_strain_derivatives(qe, dqe, n, dn, jac)
        out.d_normal = E * (np.sign(eps)[..., None] * de1
                            + np.sign(kap)[..., None] * cc[..., None] * dkap
                            + np.abs(kap)[..., None] * dc[None, :, None, :])
        if shear:
            out.d_shear = float(mat.G) * np.sign(gam)[..., None] * de2
            vm = np.where(out.von_mises > 0, out.von_mises, 1.0)[..., None]
            out.d_von_mises = (normal[..., None] * out.d_normal
                               + 3.0 * out.shear[..., None] * out.d_shear) / vm
    return out


def normal_partials(model, result, body, stress, steps, elements, stations):
    """The partial derivatives of `stress.normal` (a beam_stress of `result`) at chosen
    (step, element, station) triples only: what beam_stress(local=True) gives for every
    element and station at every step (the discrete adjoint's seeds of a largest stress
    need one station per step). body: the beam (name or Body) of `stress`.

    steps, elements, stations : (m,) indices into the time, element and station axes of
    stress.normal. Returns (dofs (m, 3 nen), the element's 0-based coordinates;
    d (m, 3 nen), d normal / d those coordinates; d_dc (m,), d normal / d the element's half
    depth c). From normal = E (|eps| + c |kappa|) with eps = e1 - e1_ref, e1 = cos(phi) x' +
    sin(phi) y', phi = N_a phi_a, kappa = phi' - kappa_ref (the module's formulas):
    d e1 / d x_a = cos(phi) N_a', d e1 / d y_a = sin(phi) N_a', d e1 / d phi_a = e2 N_a with
    e2 = -sin(phi) x' + cos(phi) y', d kappa / d phi_a = N_a'."""
    steps, elements, stations = (np.asarray(a, int) for a in (steps, elements, stations))
    cm = model.compile()
    ids = np.asarray(stress.elements, int)
    nen = int(cm.el_nen[ids[0]])
    edofs = (cm.el_dofs[:3 * nen, ids] - 1).T.astype(np.int64)[elements]   # (m, 3 nen)
    qe = result.q[steps[:, None], columns(result.dofs, edofs)]
    n, dn = shape(nen, stress.xi)                                         # (nen, nst)
    na = n[:, stations].T                                                 # (m, nen)
    dns = dn[:, stations].T / (0.5 * cm.el_len[ids[elements]])[:, None]
    x, y, p = qe[:, 0::3], qe[:, 1::3], qe[:, 2::3]
    dx, dy = np.sum(x * dns, axis=1), np.sum(y * dns, axis=1)
    phi = np.sum(p * na, axis=1)
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    e2 = (-s[:, 0] * dx + c[:, 0] * dy)[:, None]
    b = model.body(body) if isinstance(body, str) else body
    E = float(b.material.E)
    sa = E * np.sign(stress.axial[steps, elements, stations])[:, None]
    sk = E * np.sign(stress.bending[steps, elements, stations])[:, None]
    hc = stress.half_depth[elements][:, None]
    d = np.empty(qe.shape)
    d[:, 0::3] = sa * c * dns
    d[:, 1::3] = sa * s * dns
    d[:, 2::3] = sa * e2 * na + sk * hc * dns
    d_dc = np.abs(stress.bending[steps, elements, stations]) / hc[:, 0]
    return edofs, d, d_dc

