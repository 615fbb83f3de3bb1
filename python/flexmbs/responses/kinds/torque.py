"""The force of a drive (N m of a rotation drive, N of a translation drive): its constraint
row's force on its body, from the multipliers of eq. (1) (flexmbs.responses.forces)."""
from __future__ import annotations

from flexmbs.model.description import Torque
from flexmbs.responses.forces import constraint_force
from flexmbs.responses.kinds.base import ResponseKind

__all__ = ["TorqueKind", "drive_unit"]


def drive_unit(drive):
    """The unit of a drive's force: a torque (N m) of a rotation drive, else a force (N)."""
    return "N m" if drive.type == "rotation" else "N"


class TorqueKind(ResponseKind):
    schema = Torque
    forces = True

    def unit(self, r, description):
        for d in description.drives:
            if d.name == r.drive:
                return drive_unit(d)
        return None

    def value(self, problem, r, x, result, gradient, model, dprop):
        # the force of the drive's row: the torque on its body (the module's convention)
        k = [dr.name for dr in problem.description.drives].index(r.drive)
        rows = problem.mechanism.drive_rows[k]
        return constraint_force(problem.mechanism.model, result, rows[0],
                                result.dmu if gradient else None)
