"""What flexmbs reports of an evaluation, for people and for scripts (docs/json-output.md).

- `units`: the unit of every design variable, response value and gradient (a gradient is per
  unit of its design variable: "m/mm" for a deviation and a diameter in mm);
- `resolution`: the time grid and the elements of every beam the run used;
- `run_statistics`: the simulation's steps, Newton iterations, factorizations, step cuts, wall
  and CPU time and memory estimate;
- `max_gradient_warning`: the gradient of a history's maximum is that of its largest sample;
  when another peak is within PEAK_TIE_REL of it with another gradient, the maximum is not
  differentiable there (a small design change swaps the peaks), and the warning says so;
- `motion_summary`: what a case without responses still gives: the largest deflection of every
  beam from the rigid motion and the largest force of every drive.
"""
from __future__ import annotations

import numpy as np
from flexmbs.responses.forces import constraint_force
from flexmbs.responses.kinds import drive_unit, kind_of

__all__ = ["units", "response_unit", "resolution", "run_statistics", "competing_peak",
           "max_gradient_warning", "motion_summary", "PEAK_TIE_REL", "NO_RESPONSES"]

#: Two peaks of a history whose values differ by at most this fraction of the larger one are
#: "tied": the maximum's gradient may jump to the other's with a small design change.
PEAK_TIE_REL = 1e-2
#: ... when their gradients differ by more than this fraction of the larger one (tied peaks
#: with one gradient, e.g. the same state twice, do not make the maximum non-differentiable).
GRADIENT_DIFFERENCE_REL = 1e-3
#: Said when a case has no responses (the command line's summary and JSON).
NO_RESPONSES = ("the case has no responses: only the motion was simulated; add a "
                "[[responses]] table (deviation, deflection, stress, strain, torque, reaction, "
                "mass: "
                "docs/case-format.md) for values, constraints and design gradients")

#: The units of the statistics of `run_statistics` that have one.
_RUN_UNITS = {"wall_time": "s", "cpu_time": "s", "simulation_wall_time": "s",
              "memory_estimate": "B"}
#: The counters of flexmbs.analysis.simulate.Result.stats copied by `run_statistics`.
_RUN_KEYS = ("steps", "newton_iterations", "factorizations", "step_cuts",
             "residual_evaluations", "static_iterations", "sensitivity_factorizations",
             "symbolic_analyses", "solver", "unknowns", "newton", "adjoint_checkpoints")


def response_unit(response, description):
    """The unit of a response's values (SI), or None when its type has no known one: its
    kind's (flexmbs.responses.kinds; deviation 'm', 'rad' or 'm, rad'; mass 'kg'; stress 'Pa';
    torque 'N m' of a rotation drive, 'N' of a translation drive; reaction 'N'; deflection
    'm'; strain '1' or '1/m')."""
    kind = kind_of(response)
    return None if kind is None else kind.unit(response, description)


def _per(unit, var_unit):
    """The unit of d(value)/d(variable): 'm/mm'; '1/mm' for a dimensionless value."""
    if unit is None:
        return None
    top = "1" if unit == "1" else unit
    return f"{top}/{var_unit}" if var_unit else top


def units(problem):
    """{'time', 'design', 'responses', 'gradients', 'objective', 'd_objective', 'constraints',
    'jacobian'}: the units of every number of an Evaluation's JSON. design: one unit per
    design variable (in the order of 'variables'); gradients[name]: one unit per variable
    (per unit of that variable: 'm/mm'); constraints are relative to their limits ('1')."""
    d = problem.description
    var_units = list(problem.mechanism.units)
    resp = {r.name: response_unit(r, d) for r in d.responses}
    out = {"time": "s", "design": var_units, "responses": resp,
           "gradients": {n: [_per(u, v) for v in var_units] for n, u in resp.items()},
           "constraints": "1", "jacobian": [_per("1", v) for v in var_units]}
    obj = d.objective
    ou = None
    if obj is not None:
        ou = resp.get(obj.response)
        if ou is not None and obj.over == "integral":
            ou = f"{ou} s"
    out["objective"] = ou
    out["d_objective"] = [_per(ou, v) for v in var_units]
    return out


def resolution(problem):
    """The discretisation a Problem's runs use: step h (with error-controlled steps,
    `adaptive`, the spacing of the response grid), end time, steps of the response grid,
    rho_inf, start, the elements of every beam, with error-controlled steps the grid's summary
    (`grid`, Problem.grid_summary: its tolerance and whether it is reached) and the whole
    SimulationSettings of its runs (`settings`,
    flexmbs.analysis.settings.SimulationSettings.to_dict; each run keeps the coordinates its
    responses read, and the adjoint's forward run is polished)."""
    d = problem.description
    mech = problem.mechanism
    out = {"h": float(d.time.grid_h), "adaptive": bool(d.time.adaptive),
           "t_end": float(mech.t_end), "steps": int(mech.t.size - 1),
           "time_points": int(mech.t.size), "rho_inf": float(d.time.rho_inf),
           "start": d.time.start,
           "elements": {b.name: int(b.elements) for b in d.bodies
                        if getattr(b, "type", None) == "beam"}}
    settings = getattr(problem, "settings", None)
    if settings is not None:
        out["settings"] = settings.to_dict()
    if d.time.adaptive and getattr(problem, "_steps", None) is not None:
        out["grid"] = problem.grid_summary()
    return out


def run_statistics(stats, wall_time=None, cpu_time=None):
    """The run's statistics as JSON: the counters of a simulation (flexmbs.analysis.simulate.Result
    .stats: steps are the time steps, the time points one more), its memory estimate (bytes)
    and wall time, and the evaluation's wall and CPU time (s; all its simulations and the
    responses). Empty when nothing was simulated, but for the times."""
    s = dict(stats or {})
    out = {k: s[k] for k in _RUN_KEYS if k in s}
    if "memory_estimate" in s:
        out["memory_estimate"] = float(s["memory_estimate"])
    if "wall_time" in s:
        out["simulation_wall_time"] = float(s["wall_time"])
    if wall_time is not None:
        out["wall_time"] = float(wall_time)
    if cpu_time is not None:
        out["cpu_time"] = float(cpu_time)
    out["units"] = {k: u for k, u in _RUN_UNITS.items() if k in out}
    return out


def _local_maxima(v):
    """(first, last) sample of every local maximum of v (nt,): a run of equal samples above
    the runs on both sides (beyond the ends: below everything)."""
    change = np.flatnonzero(np.diff(v) != 0) + 1
    first = np.concatenate([[0], change])
    last = np.concatenate([change, [v.size]]) - 1
    run = v[first]
    left = np.concatenate([[-np.inf], run[:-1]])
    right = np.concatenate([run[1:], [-np.inf]])
    peak = (run > left) & (run > right)
    return first[peak], last[peak]


def competing_peak(v, rel=PEAK_TIE_REL):
    """(j, k): the largest sample j of a history v (nt,) (np.argmax) and the first sample k of
    the highest other local maximum (a peak or a plateau not containing j; the ends count)
    within `rel` |v[j]| of it; None when there is none."""
    v = np.asarray(v, float)
    if v.ndim != 1 or v.size < 3 or not np.all(np.isfinite(v)):
        return None
    j = int(np.argmax(v))
    first, last = _local_maxima(v)
    near = ((first > j) | (last < j)) & (v[first] >= v[j] - rel * abs(v[j]))
    if not near.any():
        return None
    cand = first[near]
    return j, int(cand[np.argmax(v[cand])])


def max_gradient_warning(name, v, g, t, unit=None, rel=PEAK_TIE_REL):
    """A sentence when the gradient of history v's maximum (g[j], g (nt, nv)) is not that of
    a differentiable function: another peak is within `rel` of the maximum with a gradient
    that differs by more than GRADIENT_DIFFERENCE_REL; else None."""
    if g is None or np.ndim(v) != 1:
        return None
    pair = competing_peak(v, rel)
    if pair is None:
        return None
    j, k = pair
    g = np.asarray(g, float)
    gj, gk = g[j], g[k]
    scale = max(np.linalg.norm(gj), np.linalg.norm(gk))
    if scale == 0.0 or np.linalg.norm(gj - gk) <= GRADIENT_DIFFERENCE_REL * scale:
        return None
    u = f" {unit}" if unit else ""
    gap = abs(v[j] - v[k]) / abs(v[j]) if v[j] else 0.0
    return (f"{name}: its maximum {v[j]:.10g}{u} at t = {t[j]:.6g} s and another peak "
            f"{v[k]:.10g}{u} at t = {t[k]:.6g} s differ by {gap:.2%} with other gradients: the "
            f"maximum is not differentiable there (its gradient is the first peak's and "
            f"jumps when a design change swaps them); a constraint or objective on it is "
            f"smooth with over = 'ks' (or 'pnorm')")


def motion_summary(problem, result):
    """{'deflection': {beam: {'max' (m), 't' (s)}}, 'drives': {drive: {'max_abs', 't',
    'unit'}}} of a simulation storing every coordinate (store='all'): the largest distance
    of a beam's nodes from their rigid-reference positions, and the largest absolute force
    (N) or torque (N m) of every drive, over time."""

    mech = problem.mechanism
    ref = mech.reference.q
    out = {"deflection": {}, "drives": {}}
    t = result.t
    for name in mech.beams:
        nodes = mech.model.body(name).nodes
        dist = np.zeros(t.size)
        for n in nodes:
            dx = result.position(n) - ref[:, [3 * n, 3 * n + 1]]
            dist = np.maximum(dist, np.hypot(dx[:, 0], dx[:, 1]))
        j = int(np.argmax(dist))
        out["deflection"][name] = {"max": float(dist[j]), "t": float(t[j])}
    for k, d in enumerate(problem.description.drives):
        rows = mech.drive_rows[k]
        if not rows:
            continue
        f, _ = constraint_force(mech.model, result, rows[0])
        j = int(np.argmax(np.abs(f)))
        out["drives"][d.name or f"drive {k + 1}"] = {
            "max_abs": float(abs(f[j])), "t": float(t[j]),
            "unit": drive_unit(d)}
    return out
