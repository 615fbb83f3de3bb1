"""The largest normal stress (Pa) over beams' elements and stations, step by step
(flexmbs.responses.stress.beam_stress): at every element's Gauss points, or at a station.
It depends on the design through the motion and, explicitly, through the section's half
depth c, so its adjoint partials are its own (the largest station's at each step only)."""
from __future__ import annotations

import numpy as np

from flexmbs.model.description import Stress
from flexmbs.responses.kinds.base import Partials, ResponseKind
from flexmbs.responses.stress import beam_stress, normal_partials

__all__ = ["StressKind"]


class StressKind(ResponseKind):
    schema = Stress
    design_model = True

    def unit(self, r, description):
        return "Pa"

    def nodes(self, problem, r):
        for b in r.beams:
            yield from problem.mechanism.model.body(b).nodes

    def places(self, problem, r):
        """(beam, stations of beam_stress, element slice) of response r: every element at its
        Gauss points, or the element of its station at the station's xi."""
        if r.at is None:
            return [(b, "gauss", slice(None)) for b in r.bodies]
        p = problem.point(r.at.body, r.at)
        return [(p.body, [p.xi], slice(p.index, p.index + 1))]

    def value(self, problem, r, x, result, gradient, model, dprop):
        vals, grads = [], []
        for b, stations, k in self.places(problem, r):
            c, dc = problem.mechanism.half_depths(x, b)
            bs = beam_stress(model, result, b, stations=stations,
                             dc=dc if gradient else None)
            nt = bs.normal.shape[0]
            vals.append(bs.normal[:, k].reshape(nt, -1))
            if gradient:
                grads.append(bs.d_normal[:, k].reshape(nt, vals[-1].shape[1], -1))
        v = np.concatenate(vals, axis=1)
        j = np.argmax(v, axis=1)
        rows = np.arange(v.shape[0])
        return v[rows, j], (np.concatenate(grads, axis=1)[rows, j] if gradient else None)

    def partials(self, problem, r, x, result, model, nc):
        """Its value at each step is its largest station's, so its partials are that
        station's, with respect to its element's coordinates and half depth (`local`)."""
        if model is None:
            model = problem.mechanism.design_model(x)
        v, j, dloc, ddc, dofs, dcs = self.local(problem, r, x, result, model)
        return v[np.arange(v.shape[0]), j], Partials(dofs, dloc, None, ddc[:, None] * dcs)

    def local(self, problem, r, x, result, model):
        """(values (nt, stations), station index j (nt,), its partials on its element's
        coordinates (nt, 3 nen) and half depth (nt,), those coordinates (nt, 3 nen), dc/dp of
        its element (nt, nv)) at each step: the partials of the largest station of each step
        only (flexmbs.responses.stress.normal_partials)."""
        mech = problem.mechanism
        places, vals = [], []
        for b, stations, k in self.places(problem, r):
            c, dc = mech.half_depths(x, b)
            bs = beam_stress(model, result, b, stations=stations)
            normal = bs.normal[:, k]
            nt, nel, nst = normal.shape
            places.append((b, bs, np.arange(bs.normal.shape[1])[k], nst, dc))
            vals.append(normal.reshape(nt, -1))
        offsets = np.cumsum([0] + [v.shape[1] for v in vals])
        v = np.concatenate(vals, axis=1)
        j = np.argmax(v, axis=1)
        owner = np.searchsorted(offsets, j, side="right") - 1
        chunks = []
        for i, (b, bs, elems, nst, dc) in enumerate(places):
            steps = np.flatnonzero(owner == i)
            if steps.size == 0:
                continue
            local = j[steps] - offsets[i]
            el = elems[local // nst]
            chunks.append((steps, *normal_partials(model, result, b, bs, steps, el, local % nst),
                           dc[el]))
        # beams of 2- and 3-node elements in one response: rows as wide as the widest element,
        # the narrower ones padded with zero partials on their own first coordinate (the seeds
        # are summed with np.add.at, so a repeated coordinate adds nothing)
        width = max(c[2].shape[1] for c in chunks)
        dloc, dofs = np.zeros((nt, width)), np.zeros((nt, width), int)
        ddc, dcs = np.zeros(nt), np.zeros((nt, chunks[0][4].shape[1]))
        for steps, d_dofs, d, d_dc, dc_el in chunks:
            n = d.shape[1]
            dloc[steps, :n], dofs[steps, :n], ddc[steps], dcs[steps] = d, d_dofs, d_dc, dc_el
            dofs[steps, n:] = d_dofs[:, :1]
        return v, j, dloc, ddc, dofs, dcs
