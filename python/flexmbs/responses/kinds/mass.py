"""The mass of beams (kg): sum over their elements of length x rho A. A function of the design
alone (no simulation); its gradient from the design derivatives of rho A."""
from __future__ import annotations

import numpy as np

from flexmbs.model.description import Mass
from flexmbs.responses.kinds.base import ResponseKind

__all__ = ["MassKind"]


class MassKind(ResponseKind):
    schema = Mass
    timed = False
    design_model = True

    def unit(self, r, description):
        return "kg"

    def value(self, problem, r, x, result, gradient, model, dprop):
        mech = problem.mechanism
        bodies = r.bodies if r.bodies is not None else mech.beams
        if gradient and dprop is None:
            dprop = mech.element_property_derivatives(x)
        props = model.element_properties()
        value, grad = 0.0, np.zeros(len(mech.variables))
        for b in bodies:
            for e in model.body(b).elements:
                length = model._elements[e][1]
                value += length * props[3, e]
                if gradient:
                    grad += length * dprop[3, e]
        return value, (grad if gradient else None)
