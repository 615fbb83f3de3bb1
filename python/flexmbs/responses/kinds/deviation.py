"""The deviation of points from their rigid-body reference (m, or rad for a rotation term):
flexmbs.responses.deviation, eq. (34)-(35)."""
from __future__ import annotations

from flexmbs.model.description import Deviation
from flexmbs.responses.deviation import deviation, deviation_terms
from flexmbs.responses.kinds.base import ResponseKind, point_nodes

__all__ = ["DeviationKind"]


class DeviationKind(ResponseKind):
    schema = Deviation

    def unit(self, r, description):
        # 'rad' when every term is a rotation, 'm, rad' when both mix
        angles = {t.component == "angle" for t in r.terms}
        return {frozenset({True}): "rad", frozenset({False}): "m"}.get(frozenset(angles),
                                                                        "m, rad")

    def nodes(self, problem, r):
        for t in r.terms:
            yield from point_nodes(problem.point(t.body, t.at))
            if t.relative_to is not None:
                yield from point_nodes(problem.point(t.relative_to.body, t.relative_to.at))

    def value(self, problem, r, x, result, gradient, model, dprop):
        mech = problem.mechanism
        ref = mech.reference          # the reference coordinates of these nodes only
        parts = []
        for t in r.terms:
            node = problem.point(t.body, t.at)
            rel = problem.point(t.relative_to.body, t.relative_to.at) \
                if t.relative_to is not None else None
            frame = mech.model.body(t.frame).first if t.frame != "ground" else None
            parts.append(deviation_terms(node, ref, result, t, frame, rel, gradient))
        return deviation(parts, gradient)
