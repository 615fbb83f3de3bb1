"""Time responses of a simulated mechanism and their design gradients.

    beam_stress, BeamStress          normal stress at the extreme fibres, shear, von Mises
                                     of a beam's elements at their stations (stress.py)
    motor_torque, joint_reaction,    constraint forces from the multipliers of eq. (1)
    constraint_force, find_rows      (forces.py)
    aggregate, ks, pnorm             every step, max, KS, p-norm over time windows
                                     (aggregate.py)
    strain                           the beam elements' strain kinematics (strain.py), shared
                                     with flexmbs.analysis.validity
    deviation, deviation_terms       deviation from the rigid reference (deviation.py)
    locate, chord_deflection,        a station anywhere along a beam: its deflection from the
    station_strain                   chord, its strains (station.py)

Each works on a flexmbs.Model and the Result of simulate(); gradients come from Result.dq
(coordinates) and, for constraint forces, from the derivatives of Result.mu passed as dmu.
"""
from flexmbs.responses.aggregate import AGGREGATES, aggregate, ks, pnorm
from flexmbs.responses.deviation import deviation, deviation_terms
from flexmbs.responses.forces import (Reaction, constraint_force, find_rows, joint_reaction,
                                      motor_torque)
from flexmbs.responses.station import chord_deflection, locate, station_strain
from flexmbs.responses.stress import BeamStress, beam_stress

__all__ = ["beam_stress", "BeamStress", "motor_torque", "joint_reaction", "constraint_force",
           "find_rows", "Reaction", "aggregate", "ks", "pnorm", "AGGREGATES", "deviation",
           "deviation_terms", "locate", "chord_deflection", "station_strain"]
