"""The reaction (N) of a joint on its first body's node, in the ground frame: x, y or its
magnitude (flexmbs.model.description.Reaction), from the multipliers of eq. (1)
(flexmbs.responses.forces)."""
from __future__ import annotations

import numpy as np

from flexmbs.model.description import GROUND, Reaction
from flexmbs.responses.forces import constraint_force, joint_reaction
from flexmbs.responses.kinds.base import ResponseKind

__all__ = ["ReactionKind"]


class ReactionKind(ResponseKind):
    schema = Reaction
    forces = True

    def unit(self, r, description):
        return "N"

    def value(self, problem, r, x, result, gradient, model, dprop):
        k = [j.name for j in problem.description.joints].index(r.joint)
        joint, rows = problem.description.joints[k], problem.mechanism.joint_rows[k]
        m = problem.mechanism.model
        dmu = result.dmu if gradient else None
        if joint.type == "prismatic" and GROUND not in joint.bodies:
            # row 0: n(phi_a) . (x_b - x_a) = c0: the normal force F (F = -mu, forces.py) on
            # b's node, -F n on a's (n turns with a: only the magnitude, description.Reaction)
            f, df = constraint_force(m, result, rows[0], dmu)
            return np.abs(f), None if df is None else np.sign(f)[:, None] * df
        if joint.type in ("slider", "prismatic"):
            # row 0: n . x = c, so the force on the node is F n (F = -mu, forces.py)
            f, df = constraint_force(m, result, rows[0], dmu)
            nx, ny = m._rows[rows[0]].coef
            parts = {"x": (nx * f, None if df is None else nx * df),
                     "y": (ny * f, None if df is None else ny * df),
                     "magnitude": (np.abs(f), None if df is None else np.sign(f)[:, None] * df)}
            return parts[r.component]
        rc = joint_reaction(m, result, (rows[0], rows[1]), dmu)   # rows x, y of the joint
        return {"x": (rc.x, rc.dx), "y": (rc.y, rc.dy),
                "magnitude": (rc.magnitude, rc.dmagnitude)}[r.component]
