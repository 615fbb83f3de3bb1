"""A strain of a station of a beam: axial, shear (1) or curvature (1/m), those of its element
(flexmbs.responses.station.station_strain)."""
from __future__ import annotations

from flexmbs.model.description import Strain
from flexmbs.responses.kinds.base import ResponseKind, point_nodes
from flexmbs.responses.station import station_strain

__all__ = ["StrainKind"]


class StrainKind(ResponseKind):
    schema = Strain

    def unit(self, r, description):
        return "1/m" if r.component == "curvature" else "1"

    def nodes(self, problem, r):
        return point_nodes(problem.point(r.at.body, r.at))

    def value(self, problem, r, x, result, gradient, model, dprop):
        return station_strain(model or problem.mechanism.model, result,
                              problem.point(r.at.body, r.at), r.component, gradient)
