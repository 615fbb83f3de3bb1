"""Response types: how a sizing problem evaluates each (`ResponseKind`, base.py), one file per
type, registered here by the case file's schema class it evaluates (flexmbs.model.description).

A new response type is its schema class in flexmbs.model.description (the case file's keys,
and a member of its `Response` union) and a file here with its `ResponseKind`, added to
`KINDS` below (tests/test_problem_responses.py checks that every schema class has a kind).
"""
from __future__ import annotations

from flexmbs.responses.kinds.base import Partials, ResponseKind, point_nodes
from flexmbs.responses.kinds.deflection import DeflectionKind
from flexmbs.responses.kinds.deviation import DeviationKind
from flexmbs.responses.kinds.mass import MassKind
from flexmbs.responses.kinds.reaction import ReactionKind
from flexmbs.responses.kinds.strain import StrainKind
from flexmbs.responses.kinds.stress import StressKind
from flexmbs.responses.kinds.torque import TorqueKind, drive_unit

__all__ = ["KINDS", "kind_of", "ResponseKind", "Partials", "point_nodes", "drive_unit"]

#: the kind of every response type, by the schema class it evaluates
KINDS = {k.schema: k for k in (MassKind(), DeviationKind(), StressKind(), DeflectionKind(),
                               StrainKind(), TorqueKind(), ReactionKind())}


def kind_of(r):
    """The ResponseKind of response r (a flexmbs.model.description response), or None."""
    for cls in type(r).__mro__:
        if cls in KINDS:
            return KINDS[cls]
    return None
