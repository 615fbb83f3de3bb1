"""Case files in the general format (TOML) -> Description, with errors that name the file,
the key, the value and what is allowed. The format: docs/case-format.md.

A file is in the general format when it has a ``[[bodies]]`` table array; the paper's older
per-mechanism files (``[case] mechanism = ...``) are read by `flexmbs.cases.load_case`.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from pydantic import ValidationError

from flexmbs.description import Description
from flexmbs.errors import CaseError

__all__ = ["read_description", "description_from_dict", "is_general_format"]


def _loc(loc):
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _friendly(err):
    """One line of a pydantic error: the key, what is wrong, the value given."""
    # pydantic adds the tag of a union member ('beam') or of a validator to the location
    loc = [p for p in err["loc"] if not (isinstance(p, str) and
                                         (p in _TAGS or p.startswith("function-")))]
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = "is not a known key (see docs/case-format.md)"
    elif err["type"] == "missing":
        msg = "is missing"
    if not loc:                      # a check across keys: its message names them
        return msg
    inp = err.get("input")
    shown = "" if err["type"] == "missing" or isinstance(inp, (dict, list)) else f", got {inp!r}"
    return f"key '{_loc(loc)}' {msg}{shown}"


_TAGS = ("beam", "rigid", "mass", "deviation", "stress", "torque", "reaction")


def description_from_dict(data, source="<dict>"):
    """Validate a parsed case (a dict) into a Description; CaseError naming source and keys."""
    if not isinstance(data, dict):
        raise CaseError(f"{source}: a case must be a table, got {type(data).__name__}")
    try:
        return Description.model_validate(data)
    except ValidationError as exc:
        lines = [_friendly(e) for e in exc.errors()]
        more = f" (and {len(lines) - 5} more)" if len(lines) > 5 else ""
        raise CaseError(f"{source}: " + "; ".join(lines[:5]) + more) from None


def is_general_format(data):
    """True for a case in the general format (it lists [[bodies]])."""
    return isinstance(data, dict) and "bodies" in data


def read_description(path):
    """Read and validate a case file in the general format."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CaseError(f"case file {str(path)!r} cannot be read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise CaseError(f"{p}: not a UTF-8 text file ({exc.reason})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(f"{p}: not valid TOML: {exc}") from None
    if not is_general_format(data):
        raise CaseError(f"{p}: not a case in the general format (no [[bodies]]); the paper's "
                        "per-mechanism files are read by flexmbs.load_case")
    return description_from_dict(data, str(p))
