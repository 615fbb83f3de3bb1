"""Fuzzing of the case files: only documented errors come out of a damaged case file.

For every shipped case file (cases/*.toml) hypothesis draws a few mutations -- a key or a
whole table or an item of an array of tables ([[bodies]], [[design]], ...) deleted, a value's
type changed (number -> string, list, bool, table), a value replaced by a negative, zero, NaN,
infinite or huge number, an unknown key added -- writes the result to a temporary TOML file and
reads it with `flexmbs.model.casefile.read_description(path)`. When reading succeeds the Problem
(mechanism, rigid reference) is built and, if small (up to CHEAP_DOFS coordinates), evaluated
at its start design (gradient=False). The unmutated file's horizon is cut to three time steps
first (time.t_end = 3 h), so that an evaluation is three steps unless a mutation changes it.

What is checked (the contract of flexmbs.errors and of docs/case-format.md): reading either
succeeds or raises CaseError whose message names the file; building the Problem and the short
evaluation either succeed or raise a FlexmbsError subclass. Never KeyError, TypeError, AttributeError,
IndexError, ZeroDivisionError, OverflowError or a raw ValueError/MemoryError, and no hang (each
example has a deadline). The examples are derandomized so that CI is reproducible; set
FLEXMBS_FUZZ_EXAMPLES to run more (random) examples locally.
"""
from __future__ import annotations

import copy
import datetime
import math
import os
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flexmbs.errors import CaseError, FlexmbsError
from flexmbs.model.casefile import read_description
from flexmbs.problem import Problem

CASES_DIR = Path(__file__).resolve().parents[1] / "cases"
CASE_FILES = sorted(CASES_DIR.glob("*.toml"))
_EXTRA = int(os.environ.get("FLEXMBS_FUZZ_EXAMPLES", "0"))
EXAMPLES = _EXTRA or 100
#: simulate (three steps) only models up to this size: the fuzzer tests the case files, and a
#: large but valid element count only makes an example slow
CHEAP_DOFS = 3000

# --------------------------------------------------------------------------- a small TOML writer


def _value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(data):
    """TOML text of a nested dict: scalars first (arrays of tables as inline arrays of inline
    tables), then [tables] and [table.sub] tables."""
    lines = [f"{k} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict)]

    def table(prefix, tab):
        lines.append(f"[{prefix}]")
        subs = []
        for k, v in tab.items():
            if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
                subs.append((k, v))           # e.g. [optimizer] -> [optimizer.fully]
            elif isinstance(v, dict) and prefix == "optimizer":
                subs.append((k, v))
            else:
                lines.append(f"{k} = {_value(v)}")
        for k, v in subs:
            table(f"{prefix}.{k}", v)

    for k, v in data.items():
        if isinstance(v, dict):
            table(k, v)
    return "\n".join(lines) + "\n"


def leaf_paths(data, prefix=()):
    """Paths (tuples of keys, list indices for the items of an array of tables) of every value
    that is not a table, of every table and of every item of an array of tables."""
    out = []
    items = data.items() if isinstance(data, dict) else enumerate(data)
    for k, v in items:
        p = prefix + (k,)
        out.append(p)
        if isinstance(v, dict) or (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
            out += leaf_paths(v, p)
    return out


def override_keys(data):
    """Dotted override keys of every path of leaf_paths, items of arrays named by their name
    (as `Problem(name, overrides=...)` takes them) or else by their index."""
    keys = set()
    for path in leaf_paths(data):
        node, parts = data, []
        for k in path:
            item = node[k]
            parts.append(item["name"] if isinstance(k, int) and isinstance(item, dict)
                         and isinstance(item.get("name"), str) else str(k))
            node = item
        keys.add(".".join(parts))
    return keys


# --------------------------------------------------------------------------- mutations
ODD_VALUES = st.one_of(
    st.sampled_from([0, 0.0, -1, -1.0, -1e300, 1e300, 10**9, -(10**9), float("nan"),
                     float("inf"), float("-inf"), 1e-300, 5e-324, "", "x", "28", "1e3", True,
                     False, [], [1.0], [0.0, 0.0], ["a", "b"], [float("nan")] * 4, {},
                     {"a": 1}, 2, 3, 1, 0.5, 360.0, -90.0]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-10, max_value=60),
    st.text(max_size=6),
    st.lists(st.floats(min_value=-100, max_value=100), max_size=5),
)

MUTATION = st.tuples(st.sampled_from(["delete", "replace", "replace", "scale", "scale", "add"]),
                     st.integers(min_value=0, max_value=10**6),
                     st.one_of(ODD_VALUES, st.sampled_from([-1.0, 0.0, 0.5, 2.0, 10.0, 1e3, 1e6, 1e-3])))


def mutate(data, mutations):
    """Apply (kind, index, value) mutations; index picks the key among all current paths.

    delete: remove the key or table; replace: put `value` there (any type); scale: multiply a
    number or a list of floats by `value` (a plausible value of the right type); add: an
    unknown key in the table.
    """
    for kind, index, value in mutations:
        value = copy.deepcopy(value)      # sampled values (lists, dicts) are shared objects
        paths = leaf_paths(data)
        if not paths:
            return data
        path = paths[index % len(paths)]
        parent = data
        for k in path[:-1]:
            parent = parent[k]
        if kind == "delete":
            del parent[path[-1]]
        elif kind == "replace":
            parent[path[-1]] = value
        elif kind == "scale":
            # a plausible value of the right type: the original number(s) times a factor
            old = parent[path[-1]]
            f = value if isinstance(value, (int, float)) and not isinstance(value, bool) else -1.0
            if isinstance(old, (int, float)) and not isinstance(old, bool):
                new = old * f
                if isinstance(old, int) and isinstance(new, float) and new.is_integer():
                    new = int(new)            # an integer key stays an integer where it can
                parent[path[-1]] = new
            elif isinstance(old, list) and old and all(isinstance(x, float) for x in old):
                parent[path[-1]] = [x * f for x in old]
        else:
            target = parent[path[-1]] if isinstance(parent[path[-1]], dict) else parent
            target["fuzz_unknown_key"] = value
    return data


# --------------------------------------------------------------------------- the test
@pytest.mark.parametrize("case_file", CASE_FILES, ids=[p.stem for p in CASE_FILES])
def test_damaged_case_file_gives_only_documented_errors(case_file, tmp_path_factory):
    """Mutated case files: read_description raises only CaseError naming the file, and
    building the Problem and a three-step evaluation raise only FlexmbsError subclasses."""
    original = tomllib.loads(case_file.read_text(encoding="utf-8"))
    original["time"]["t_end"] = 3 * original["time"]["h"]
    folder = tmp_path_factory.mktemp(case_file.stem)
    counter = {"n": 0, "loaded": 0}

    @settings(max_examples=EXAMPLES, deadline=datetime.timedelta(seconds=30),
              derandomize=not _EXTRA, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(st.lists(MUTATION, min_size=1, max_size=3))
    def check(mutations):
        data = mutate(copy.deepcopy(original), mutations)
        counter["n"] += 1
        path = folder / f"fuzz_{counter['n']}.toml"
        path.write_text(to_toml(data), encoding="utf-8")
        try:
            description = read_description(path)
        except CaseError as exc:
            assert str(path) in str(exc), f"CaseError does not name the file: {exc}"
            return
        counter["loaded"] += 1
        try:
            prob = Problem(description)
            if prob.mechanism.model.ndof <= CHEAP_DOFS:
                prob.evaluate(gradient=False)
        except FlexmbsError:
            pass

    check()
    if os.environ.get("FLEXMBS_FUZZ_VERBOSE"):
        print(case_file.stem, counter)
    assert counter["n"] >= min(EXAMPLES, 10)


def test_case_without_drives_gives_only_documented_errors():
    """The fuzzer's first finding, kept as a fixed example: the four-bar with its [[drives]]
    deleted (start = "rest", so the rest start's drive velocity field is computed) either
    evaluates three steps or raises a FlexmbsError subclass (flexmbs.errors' contract)."""
    data = tomllib.loads((CASES_DIR / "fourbar.toml").read_text(encoding="utf-8"))
    del data["drives"]
    data["time"]["t_end"] = 3 * data["time"]["h"]
    try:
        Problem(data).evaluate(gradient=False)
    except FlexmbsError:
        pass


OVERRIDE_KEYS = st.one_of(
    st.sampled_from(sorted(set().union(*(override_keys(tomllib.loads(f.read_text(encoding="utf-8")))
                                         for f in CASE_FILES))
                           | {p[-1] for f in CASE_FILES
                              for p in leaf_paths(tomllib.loads(f.read_text(encoding="utf-8")))
                              if isinstance(p[-1], str)})),
    st.text(max_size=8))


@settings(max_examples=EXAMPLES, deadline=datetime.timedelta(seconds=30),
          derandomize=not _EXTRA, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from([p.stem for p in CASE_FILES]),
       st.dictionaries(OVERRIDE_KEYS, ODD_VALUES, min_size=1, max_size=2))
def test_random_overrides_give_only_case_errors(name, overrides):
    """read_description(name, overrides) with random keys (dotted paths with items by name,
    leaf names, nonsense) and values of any type either reads or raises CaseError (as
    `--set` and Python overrides do); building the Problem of what was read raises only
    FlexmbsError subclasses."""
    try:
        description = read_description(name, overrides)
    except CaseError:
        return
    try:
        Problem(description)
    except FlexmbsError:
        pass


def test_writer_round_trips_the_shipped_cases():
    """The fuzzer's TOML writer reproduces every shipped case file's data exactly, so a mutation
    is the only difference between the fuzzed file and the original."""
    for f in CASE_FILES:
        data = tomllib.loads(f.read_text(encoding="utf-8"))
        assert tomllib.loads(to_toml(data)) == data
