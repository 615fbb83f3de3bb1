"""Fingerprints of stored results: what a history, a stored start or a stored job answers.

A result kept on disk (an optimization history that a run resumes from, a multi-start's
stored start, a study's stored job) is reused only for the question it answers. Its
fingerprint is a JSON dict of

    flexmbs      the flexmbs version that computed it
    method       what was run (e.g. 'weakly', 'fully', 'start', a job function's name)
    options      the method's options (JSON values; the start design among them)
    description  {top-level key of the case description: SHA-256 of its JSON}, of the
                 description as resolved (case file read, overrides applied, validated)
    settings     the simulation settings of the case, whole (readable; its [time]'s
                 rho_inf, start, newton and its [solver] table, every key (null: the
                 default of SimulationSettings or ValidityLimits):
                 flexmbs.analysis.settings.SimulationSettings); compared through the
                 description's digests, which cover them

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
        # the [optimize] table is the run's options, fingerprinted as such (a resumed run
        # may raise its limits)
        data.pop("optimize", None)
    elif isinstance(description, dict):
        data = description
    else:
        return {"object": type(description).__qualname__}
    data = canonical(data)
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
    """The simulation settings of a Description as plain JSON data: [time]'s rho_inf, start
    and newton and every key of [solver] (defaults included); None for anything else."""
    time, solver = getattr(description, "time", None), getattr(description, "solver", None)
    if not hasattr(solver, "model_dump") or time is None:
        return None
    return canonical({"rho_inf": time.rho_inf, "start": time.start, "newton": time.newton,
                      **solver.model_dump(mode="json")})


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
