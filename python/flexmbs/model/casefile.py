"""Case files in the general format (TOML) -> Description, with errors that name the file,
the key, the value and what is allowed. The format: docs/case-format.md.

Shipped cases (the repository's ``cases/`` folder, or the copy installed with the package in
``flexmbs/cases_data``) are found by name: `case_path("NAME")`. Any key can be replaced
before validation with `overrides`, by a dotted path: ``{"time.t_end": 0.66}``; an item of a
table array is addressed by its ``name`` or its index: ``{"bodies.arm1.elements": 8}``.
"""
from __future__ import annotations

import contextlib
import copy
import os
import sys
import tomllib
import types
import typing
from importlib import resources
from pathlib import Path

from pydantic import BaseModel, ValidationError

from flexmbs.errors import CaseError
from flexmbs.files import check_regular_file
from flexmbs.model.description import Body, Description, Response

__all__ = ["read_description", "description_from_dict", "is_general_format", "apply_overrides",
           "parse_override", "case_path", "case_folders", "available_cases", "nesting_guard"]


def _loc(loc):
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _step(tp, part):
    """The types a location part leads to from type `tp` (a model, list, dict, union)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Annotated:
        return _step(args[0], part)
    if origin in (typing.Union, types.UnionType):
        return [t for a in args for t in _step(a, part)]
    if origin in (list, tuple):
        return list(args[:1]) if isinstance(part, int) else []
    if origin is dict:
        return list(args[1:2]) if isinstance(part, str) else []
    if not (isinstance(tp, type) and issubclass(tp, BaseModel)) or not isinstance(part, str):
        return []
    for name, f in tp.model_fields.items():
        if part in (name, f.alias):
            return [f.annotation]
    if part.startswith("function-"):             # a validator's step: the same model
        return [tp]
    for f in tp.model_fields.values():           # the tag of a union member ('beam')
        if typing.get_origin(f.annotation) is typing.Literal and part in typing.get_args(f.annotation):
            return [tp]
    return []


def _models(tp):
    """The models a type stands for (through Annotated, unions and None)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Annotated:
        return _models(args[0])
    if origin in (typing.Union, types.UnionType):
        return [m for a in args for m in _models(a)]
    return [tp] if isinstance(tp, type) and issubclass(tp, BaseModel) else []


def allowed_keys(model, loc):
    """The keys allowed in the table that holds the last key of `loc` (a pydantic error's
    location under `model`), as a file spells them; None when no single table is found."""
    types = [model]
    for part in loc[:-1]:
        types = [t for tp in types for t in _step(tp, part)]
    models = {m for tp in types for m in _models(tp)}
    if len(models) != 1:
        return None
    (m,) = models
    return [f.alias or name for name, f in m.model_fields.items()]


def friendly_error(err, model=None, doc="docs/case-format.md", tags=None):
    """One line of a pydantic error: the key, what is wrong, the value given (for an unknown
    key of `model`'s data, default a case's Description, the keys allowed in its table).
    tags: the tags of `model`'s tagged unions (default: a case's)."""
    tags = _TAGS if tags is None else tags
    # pydantic adds the tag of a union member ('beam', after the item's index) or of a
    # validator to the location; a key of the same name elsewhere (a point mass's 'mass')
    # stays
    raw = list(err["loc"])
    loc = [p for k, p in enumerate(raw) if not (isinstance(p, str) and (
        p.startswith("function-") or (p in tags and k > 0 and isinstance(raw[k - 1], int))))]
    msg = err["msg"].removeprefix("Value error, ")
    allowed = ""
    if err["type"] == "extra_forbidden":
        msg = f"is not a known key (see {doc})"
        keys = allowed_keys(model or Description, err["loc"])
        if keys:
            where = f"[{_loc(loc[:-1])}]" if loc[:-1] else "the top level"
            allowed = f"; allowed in {where}: {', '.join(keys)}"
    elif err["type"] == "missing":
        msg = "is missing"
    if not loc:                      # a check across keys: its message names them
        return msg
    inp = err.get("input")
    shown = "" if err["type"] == "missing" or isinstance(inp, (dict, list)) else f", got {inp!r}"
    return f"key '{_loc(loc)}' {msg}{shown}{allowed}"



def _union_tags(*unions):
    """The `type` words of the members of discriminated unions of the description."""
    tags = []
    for u in unions:
        for member in typing.get_args(typing.get_args(u)[0]):
            for word in typing.get_args(member.model_fields["type"].annotation):
                if word not in tags:
                    tags.append(word)
    return tuple(tags)


#: the tags pydantic puts in an error's location for a union member (every body and
#: response type of the description)
_TAGS = _union_tags(Body, Response)


@contextlib.contextmanager
def nesting_guard(source):
    """Turn a RecursionError of reading or validating a file (TOML or JSON nested thousands
    of levels deep: tomllib, json and the validation recurse per level) into a CaseError
    naming `source`."""
    try:
        yield
    except RecursionError:
        raise CaseError(f"{source}: nested too deeply (arrays or tables within each other "
                        f"beyond Python's recursion limit, {sys.getrecursionlimit()} levels); "
                        "a case or study nests a few levels") from None


def description_from_dict(data, source="<dict>", overrides=None):
    """Validate a parsed case (a dict) into a Description; CaseError naming source and keys.

    overrides : dict, optional
        Keys to replace first (`apply_overrides`); `data` itself is not changed.
    """
    if not isinstance(data, dict):
        raise CaseError(f"{source}: a case must be a table, got {type(data).__name__}")
    if overrides:
        with nesting_guard(source):         # a deep copy of the data
            data = apply_overrides(data, overrides, source)
    try:
        with nesting_guard(source):
            return Description.model_validate(data)
    except ValidationError as exc:
        lines = [friendly_error(e) for e in exc.errors()]
        more = f" (and {len(lines) - 5} more)" if len(lines) > 5 else ""
        raise CaseError(f"{source}: " + "; ".join(lines[:5]) + more) from None


def is_general_format(data):
    """True for a case in the general format (it lists [[bodies]])."""
    return isinstance(data, dict) and "bodies" in data


def read_description(path, overrides=None):
    """Read and validate a case file (a path, or the name of a shipped case, `case_path`);
    `overrides` as in `description_from_dict`."""
    p = case_path(path)
    check_regular_file(p, "case file", CaseError)
    try:
        text = p.read_text(encoding="utf-8-sig")     # a leading BOM is dropped
    except OSError as exc:
        raise CaseError(f"case file {str(path)!r} cannot be read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise CaseError(f"{p}: not a UTF-8 text file ({exc.reason})") from None
    try:
        with nesting_guard(p):
            data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CaseError(f"{p}: not valid TOML: {exc}") from None
    if not is_general_format(data):
        raise CaseError(f"{p}: not a flexmbs case: it lists no [[bodies]] (docs/case-format.md)")
    return description_from_dict(data, str(p), overrides)


# ----------------------------------------------------------------------------- overrides
def _override_target(node, parts, key, source):
    """The container and leaf that a dotted override path names."""
    for k, part in enumerate(parts[:-1]):
        where = ".".join(parts[:k + 1])
        if isinstance(node, dict):
            if part not in node:
                node[part] = {}
            node = node[part]
        elif isinstance(node, list):
            hits = [it for it in node if isinstance(it, dict) and it.get("name") == part]
            if not hits and part.lstrip("-").isdigit() and -len(node) <= int(part) < len(node):
                hits = [node[int(part)]]
            if len(hits) != 1:
                names = [it.get("name") for it in node if isinstance(it, dict) and it.get("name")]
                raise CaseError(f"{source}: override '{key}': no single item '{part}' in "
                                f"'{'.'.join(parts[:k])}' (names: {', '.join(names) or 'none'}; "
                                f"or an index 0..{len(node) - 1})")
            node = hits[0]
        else:
            raise CaseError(f"{source}: override '{key}': '{where}' is not a table or an array "
                            f"of tables (it is {node!r})")
    if not isinstance(node, dict):
        raise CaseError(f"{source}: override '{key}': '{'.'.join(parts[:-1])}' is not a table")
    return node, parts[-1]


def apply_overrides(data, overrides, source="<dict>"):
    """A deep copy of the raw case `data` with `overrides` {dotted key: value} set.

    The result is validated as a whole afterwards (an unknown leaf key or a bad value is then
    named by `description_from_dict`)."""
    if not isinstance(overrides, dict):
        raise CaseError(f"{source}: overrides must be a dict {{dotted key: value}}, "
                        f"got {type(overrides).__name__}")
    out = copy.deepcopy(data)
    for key, value in overrides.items():
        if not isinstance(key, str) or not key or any(not p for p in key.split(".")):
            raise CaseError(f"{source}: override keys are dotted paths such as 'time.t_end', "
                            f"got {key!r}")
        node, leaf = _override_target(out, key.split("."), key, source)
        if hasattr(value, "tolist"):                     # numpy scalars and arrays
            value = value.tolist()
        if key == "time.h" and value == "auto" and isinstance(node.get("h"), (int, float)) \
                and "output" not in node and "time.output" not in overrides:
            node["output"] = node["h"]      # error-controlled steps, outputs on the case's grid
        node[leaf] = value
    return out


def parse_override(text):
    """'time.t_end=0.66' -> ('time.t_end', 0.66): the value is read as a TOML value (number,
    string in quotes, array, inline table, true/false); a bare word is a string."""
    key, sep, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not sep or not key or not raw:
        raise CaseError(f"an override is KEY=VALUE, e.g. time.t_end=0.66, got {text!r}")
    try:
        return key, tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return key, raw


# ----------------------------------------------------------------------------- shipped cases
def _repository_cases():
    """The repository's cases/ folder when flexmbs runs from a source tree, else None."""
    root = Path(__file__).resolve().parents[3]
    folder = root / "cases"
    if folder.is_dir() and (root / "python" / "flexmbs").is_dir():
        return folder
    return None


def _installed_cases():
    """The case files installed with the package (flexmbs/cases_data), or None."""
    try:
        folder = resources.files("flexmbs") / "cases_data"
        return folder if folder.is_dir() else None
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError):
        return None


def case_folders():
    """The folders that hold shipped case files: the repository's cases/ (source tree) and the
    copy installed with the package (flexmbs/cases_data)."""
    return [f for f in (_repository_cases(), _installed_cases()) if f is not None]


def available_cases():
    """Names of the shipped case files."""
    return shipped_names()


def shipped_names(subfolder=""):
    """Names (stems) of the shipped .toml files of the shipped folders (or their `subfolder`)."""
    names = set()
    for folder in case_folders():
        sub = folder / subfolder if subfolder else folder
        try:
            # iterdir, not glob: the package's folder may be an importlib Traversable
            names.update(p.name.removesuffix(".toml") for p in sub.iterdir()
                         if p.name.endswith(".toml") and p.is_file())
        except (OSError, AttributeError):        # no such folder
            continue
    return sorted(names)


def case_path(name):
    """An existing file path, or a shipped case by name (with or without .toml); CaseError
    naming the shipped cases if neither."""
    return shipped_path(name, "case")


def shipped_path(name, kind, subfolder=""):
    """An existing file path, or the shipped `kind` (a case; a study in subfolder 'studies')
    of that name (with or without .toml); CaseError listing the shipped ones if neither."""
    if not isinstance(name, (str, Path)):
        raise CaseError(f"a {kind} is a path to a .toml file or the name of a shipped {kind}, "
                        f"got {name!r} ({type(name).__name__})")
    p = Path(name)
    if p.is_file():
        return p
    if p.is_dir():
        raise CaseError(f"{kind} {str(name)!r} is a folder, not a file: give the path of a "
                        f"{kind} file (.toml) or the name of a shipped {kind}")
    if os.path.lexists(p):      # a device, FIFO or socket (or a link to one, or a broken link)
        if check_regular_file(p, f"{kind} file", CaseError):
            return p
        raise CaseError(f"{kind} file {str(name)!r} is a link to {os.readlink(p)!r}, which "
                        f"does not exist: give the path of a {kind} file (.toml)")
    if len(p.parts) == 1:
        for folder in case_folders():
            f = folder / subfolder / f"{p.name.removesuffix('.toml')}.toml"
            if f.is_file():
                return f
    raise CaseError(f"{kind} {str(name)!r} not found: give a path to a .toml file or one of the "
                    f"shipped {'studies' if kind == 'study' else kind + 's'}: "
                    f"{', '.join(shipped_names(subfolder)) or 'none found'}")
