"""The protocol of a response type: how a sizing problem (flexmbs.problem.Problem) evaluates it.

A response type is a schema class of the case file (flexmbs.model.description: its keys,
checked with the rest of the description) and one class here, a `ResponseKind`, in a file of
its own in this folder, registered in `flexmbs.responses.kinds.KINDS` by that schema class. The
kind says

    schema          the description class it evaluates
    unit(r, d)      the unit of its values (SI) for response r of description d
    timed           a history of the simulation (False: a function of the design alone)
    forces          it reads the constraint multipliers (motor torques, joint reactions)
    design_model    its value needs the design's model (its sections)
    nodes(p, r)     the nodes whose coordinates it reads (stored and differentiated)
    value(...)      its value at every step and its design gradient (or None)
    partials(...)   its value and its `Partials` at every step at once, for the adjoint

The problem `p` handed to these is the evaluating flexmbs.problem.Problem; a kind reads its
`mechanism`, its `description` and `p.point(body, at)` (a named point's node or a station
along a beam) and nothing else of it. The static form a response has in the weakly coupled
method (mass, deviation, stress) belongs to that method (flexmbs.methods.weakly).
"""
from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np

__all__ = ["ResponseKind", "Partials", "point_nodes"]


class Partials(NamedTuple):
    """The per-step partial derivatives of a history response (nt steps) for the adjoint's
    right-hand sides (`ResponseKind.partials`): dofs, the coordinates it reads ((m,), the same
    at every step, or (nt, m), distinct within a step); dq (nt, m), with respect to them; dmu
    (nt, nc) or None, with respect to the constraint multipliers; design (nt, nv) or None,
    with respect to the design variables directly (a stress through its section depth; the
    rest of its dependence on the design goes through the motion)."""
    dofs: np.ndarray
    dq: np.ndarray
    dmu: np.ndarray | None
    design: np.ndarray | None


def point_nodes(p):
    """The nodes a point reads: a named point's node, or the nodes of a station's element."""
    return list(p.nodes) if hasattr(p, "nodes") else [p]


class ResponseKind:
    """How a Problem evaluates one type of response (the module docstring lists the parts).

    The defaults fit a history that reads a few nodes' coordinates and depends on the design
    through the motion only: override `value` and `nodes` (or `forces`), and `partials` only
    when the identity derivatives below are not right or too costly (a stress)."""

    schema: type = None
    timed = True
    forces = False
    design_model = False

    def unit(self, r, description):
        """The unit (SI) of response r's values, or None when it has none known."""
        return None

    def nodes(self, problem, r):
        """The nodes whose coordinates response r reads (an iterable of node ids)."""
        return ()

    def value(self, problem, r, x, result, gradient, model, dprop):
        """Value of response r at design x on simulation `result` (an array over the steps,
        or a number when not timed) and its gradient (steps x variables, or None). model: the
        design's model when `design_model` (else possibly None); dprop: the element
        properties' design derivatives when already computed (or None)."""
        raise NotImplementedError

    def partials(self, problem, r, x, result, model, nc):
        """Value (nt,) of history response r on the adjoint's forward run and its `Partials` at
        every step, all steps at once. This default evaluates `value` once with identity
        derivatives of the coordinates of `nodes` and of the nc multipliers (len(dofs) + nc
        columns per step): right for a response that depends on the design through the motion
        only."""
        nt = result.q.shape[0]
        nodes = sorted(set(self.nodes(problem, r)))
        dofs = np.array([3 * n + k for n in nodes for k in range(3)], dtype=int)
        m = dofs.size
        eye = np.eye(m + nc)
        vres = replace(result, sens_dofs=dofs,
                       dq=np.broadcast_to(eye[:m], (nt, m, m + nc)),
                       dmu=np.broadcast_to(eye[m:], (nt, nc, m + nc)))
        if model is None and self.design_model:
            model = problem.mechanism.design_model(x)
        value, g = self.value(problem, r, x, vres, True, model, None)
        g = np.asarray(g, float).reshape(nt, m + nc)
        return value, Partials(dofs, g[:, :m], g[:, m:], None)
