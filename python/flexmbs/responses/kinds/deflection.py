"""The deflection (m) of a station of a beam from the chord through the beam's end nodes
(flexmbs.responses.station.chord_deflection)."""
from __future__ import annotations

from flexmbs.model.description import Deflection
from flexmbs.responses.kinds.base import ResponseKind, point_nodes
from flexmbs.responses.station import chord_deflection

__all__ = ["DeflectionKind"]


class DeflectionKind(ResponseKind):
    schema = Deflection

    def unit(self, r, description):
        return "m"

    def nodes(self, problem, r):
        p = problem.point(r.at.body, r.at)
        return point_nodes(p) + [p.first, p.last]

    def value(self, problem, r, x, result, gradient, model, dprop):
        return chord_deflection(result, problem.point(r.at.body, r.at), gradient)
