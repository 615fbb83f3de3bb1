"""Fuzzing of the case files (issue 14): only documented errors come out of a damaged case file.

For every shipped case file (cases/*.toml) hypothesis draws a few mutations -- a key or a
whole table deleted, a value's type changed (number -> string, list, bool, table), a value
replaced by a negative, zero, NaN, infinite or huge number, an unknown key added -- writes the
result to a temporary TOML file and loads it with `load_case(path)`. When loading succeeds the
model is built for the start design and, if small (up to CHEAP_DOFS coordinates), simulated for
three time steps.

What is checked (the contract of flexmbs.errors and of `load_case`'s docstring): loading either
succeeds or raises CaseError whose message names the file; building and the short simulation
either succeed or raise a FlexmbsError subclass. Never KeyError, TypeError, AttributeError,
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

import flexmbs as fx
from flexmbs.errors import CaseError, FlexmbsError

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
    """TOML text of a nested dict: scalars first, then [tables] and [table.sub] tables."""
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
    """Paths (tuples of keys) of every value that is not a table, and of every table."""
    out = []
    for k, v in data.items():
        p = prefix + (k,)
        out.append(p)
        if isinstance(v, dict):
            out += leaf_paths(v, p)
    return out


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
    """Mutated case files: load_case raises only CaseError naming the file, and building and a
    three-step simulation of a loaded case raise only FlexmbsError subclasses (issue 14)."""
    original = tomllib.loads(case_file.read_text(encoding="utf-8"))
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
            case = fx.load_case(path)
        except CaseError as exc:
            assert str(path) in str(exc), f"CaseError does not name the file: {exc}"
            return
        counter["loaded"] += 1
        try:
            model = case.build_model(case.start_mm)
            if model.ndof <= CHEAP_DOFS:
                case.simulate(case.start_mm, t_end=3 * case.h)
        except FlexmbsError:
            pass

    check()
    if os.environ.get("FLEXMBS_FUZZ_VERBOSE"):
        print(case_file.stem, counter)
    assert counter["n"] >= min(EXAMPLES, 10)


OVERRIDE_KEYS = st.one_of(
    st.sampled_from(sorted({".".join(p) for f in CASE_FILES
                            for p in leaf_paths(tomllib.loads(f.read_text(encoding="utf-8")))}
                           | {p[-1] for f in CASE_FILES
                              for p in leaf_paths(tomllib.loads(f.read_text(encoding="utf-8")))})),
    st.text(max_size=8))


@settings(max_examples=EXAMPLES, deadline=datetime.timedelta(seconds=30),
          derandomize=not _EXTRA, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from([p.stem for p in CASE_FILES]),
       st.dictionaries(OVERRIDE_KEYS, ODD_VALUES, min_size=1, max_size=2))
def test_random_overrides_give_only_case_errors(name, overrides):
    """load_case(name, **overrides) with random keys (by leaf name, dotted path or nonsense) and
    values of any type either loads or raises CaseError (issue 14: `--set` and Python overrides)."""
    try:
        fx.load_case(name, **overrides)
    except CaseError:
        pass


def test_writer_round_trips_the_shipped_cases():
    """The fuzzer's TOML writer reproduces every shipped case file's data exactly, so a mutation
    is the only difference between the fuzzed file and the original."""
    for f in CASE_FILES:
        data = tomllib.loads(f.read_text(encoding="utf-8"))
        assert tomllib.loads(to_toml(data)) == data
