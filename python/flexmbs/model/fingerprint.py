"""Fingerprints of stored results: what a history, a stored start or a stored job answers.

A result kept on disk (an optimization history that a run resumes from, a multi-start's
stored start, a study's stored job) is reused only for the question it answers. Its
fingerprint is a JSON dict of

    flexmbs      the flexmbs version that computed it
    method       what was run (e.g. 'weakly', 'fully', 'start', a job function's name)
    options      the method's options (JSON values; the start design among them)
    description  {top-level key of the case description: SHA-256 of its JSON}, of the
                 description as resolved (case file read, overrides applied, validated),
                 without what cannot change an answer (ANSWER_NEUTRAL)
    settings     the simulation settings of the case as they run (readable; the fields of
                 flexmbs.analysis.settings.SimulationSettings.to_dict() that a case sets:
                 [time]'s rho_inf, start and newton, its deprecated reuse_jacobian resolved
                 to the newton it names, and [solver]'s, linear_solver as 'solver', the
                 validity mode and limits as a table, null: the default); compared through
                 the description's digests

The digests leave out the [solver] key that cannot change an answer, ANSWER_NEUTRAL: the
memory limit (it only decides whether a run may start, and whether the adjoint keeps its
states or checkpoints, whose gradients agree to rounding). A stored result computed under
another memory limit is the same answer and is reused. Everything else stays in: tol,
max_iter, max_cuts, linear_solver, kscale, penalty, polish (and all of [time]), and the
validity checks' mode and limits, since a result stored under looser checks may be one that
the current checks refuse.

and `differences(stored, current)` names what differs, for messages: a resumed history that
differs is refused (flexmbs.methods.result.HistoryWriter.check_fingerprint), a stored
result that differs is computed again with a warning naming its file
(flexmbs.batch.run_batch's `fingerprints`).
"""
from __future__ import annotations

import hashlib
import json
from flexmbs.files import jsonable
from flexmbs.version import __version__

__all__ = ["fingerprint", "description_digest", "differences", "run_options", "canonical",
           "simulation_settings_record"]

#: arguments of an optimizer that do not change its answer (where it is written, how it is
#: shown, whether it resumes), that only say how far it goes (a resumed run may go further:
#: the records it replays are the same), or that are fingerprinted on their own (the problem)
NOT_OPTIONS = ("problem", "history", "progress", "resume", "max_iterations", "max_simulations",
               "max_cycles")

#: [solver] keys that cannot change an answer (module docstring): left out of the digests
ANSWER_NEUTRAL = ("memory_limit",)
#: [solver]'s validity limits (the record gathers them under 'validity')
VALIDITY_LIMITS = ("strain_warn", "strain_fail", "drift_warn", "drift_fail", "energy_warn",
                   "energy_fail")


def canonical(obj):
    """obj as plain JSON data (what a JSON round trip gives back: tuples -> lists, numpy ->
    numbers; anything else as its str)."""
    return json.loads(json.dumps(jsonable(obj), sort_keys=True, default=str))


def description_digest(description):
    """{top-level key: SHA-256 (hex, 16 digits) of its canonical JSON} of a Description (a
    pydantic model), or of a dict; {'object': type name} for anything else (a Problem-like
    test object has no description to hash)."""
    if hasattr(description, "model_dump"):
        # keys left at their defaults are left out: a key added to the format with a
        # default (the same question) does not change the fingerprint of older results
        data = description.model_dump(mode="json", by_alias=True, exclude_defaults=True)
    elif isinstance(description, dict):
        data = description
    else:
        return {"object": type(description).__qualname__}
    data = canonical(data)
    # the [optimize] table is the run's options, fingerprinted as such (a resumed run may
    # raise its limits)
    data.pop("optimize", None)
    if isinstance(data.get("solver"), dict):
        data["solver"] = {k: v for k, v in data["solver"].items() if k not in ANSWER_NEUTRAL}
        if not data["solver"]:       # as a case without [solver]
            del data["solver"]
    return {k: hashlib.sha256(json.dumps(v, sort_keys=True).encode()).hexdigest()[:16]
            for k, v in sorted(data.items())}


def run_options(arguments):
    """An optimizer's arguments (its locals() on entry) without NOT_OPTIONS."""
    return {k: v for k, v in arguments.items() if k not in NOT_OPTIONS}


def fingerprint(description, method, options=None):
    """The fingerprint (module docstring) of `method` run with `options` on `description`."""
    out = {"flexmbs": __version__, "method": str(method),
           "options": canonical(dict(options or {})),
           "description": description_digest(description)}
    settings = simulation_settings_record(description)
    if settings is not None:
        out["settings"] = settings
    return out


def simulation_settings_record(description):
    """The simulation settings of a Description as they run, as plain JSON data keyed as
    SimulationSettings.to_dict() (module docstring: newton resolved from the deprecated
    reuse_jacobian, linear_solver as 'solver', validity as {mode, limits}; null: the
    default); None for anything else."""
    time, solver = getattr(description, "time", None), getattr(description, "solver", None)
    if not hasattr(solver, "model_dump") or time is None:
        return None
    so = solver.model_dump(mode="json")
    validity = {"mode": so.pop("validity")}
    validity.update({k: so.pop(k) for k in VALIDITY_LIMITS})
    so["solver"] = so.pop("linear_solver")
    return canonical({"rho_inf": time.rho_inf, "start": time.start,
                      "newton": time.newton_strategy, **so, "validity": validity})


def differences(stored, current):
    """What differs between two fingerprints, as short phrases ('the case description's
    time', 'option eps: 0.01 -> 0.02', 'flexmbs 0.1.0 -> 0.2.0'); ['no fingerprint'] when
    `stored` is not one (a file from before fingerprints, or from another program)."""
    if not isinstance(stored, dict) or not {"flexmbs", "method", "options",
                                            "description"} <= set(stored):
        return ["no fingerprint (written before fingerprints, or by another program)"]
    if not all(isinstance(stored[k], (dict, type(None))) for k in ("options", "description")):
        return ["a malformed fingerprint (its options or description is not a table)"]
    out = []
    if stored["flexmbs"] != current["flexmbs"]:
        out.append(f"flexmbs {stored['flexmbs']} -> {current['flexmbs']}")
    if stored["method"] != current["method"]:
        out.append(f"method {stored['method']} -> {current['method']}")
    out += _option_differences(stored["options"] or {}, current["options"] or {})
    sd, cd = stored["description"] or {}, current["description"] or {}
    changed = sorted(k for k in set(sd) | set(cd) if sd.get(k) != cd.get(k))
    if changed:
        out.append("the case description's " + ", ".join(changed))
    return out


def _option_differences(so, co, prefix=""):
    """'option a.b: old -> new' for each option that differs; an option table (a dict on both
    sides, e.g. an optimizer's options) is compared key by key."""
    out = []
    for k in sorted(set(so) | set(co)):
        a, b = so.get(k), co.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += _option_differences(a, b, f"{prefix}{k}.")
        else:
            out.append(f"option {prefix}{k}: {_short(a)} -> {_short(b)}")
    return out


def _short(v, n=60):
    s = json.dumps(v)
    return s if len(s) <= n else s[:n - 3] + "..."
