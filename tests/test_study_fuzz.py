"""Fuzzing of the study files and of the stored results of a batch: only documented errors.

Study files (flexmbs.paper.study.load_study): hypothesis mutates the shipped study
cases/studies/paper.toml -- a key, a table or an item of an array of tables deleted, a value
replaced by one of another type (test_casefile_fuzz.ODD_VALUES) or by a deeply nested array, an
unknown key added -- writes it to a temporary folder (its published numbers are then the ones shipped with flexmbs)
and loads it: the result is
a Study or a CaseError naming the file (docs/study-format.md), never another exception.

Stored results (flexmbs.batch.run_batch's `store`): hypothesis writes random JSON (any shape,
deeply nested arrays, bytes that are not JSON or not UTF-8) under a job's name; run_batch either
reuses it (only when it is a result of the job's schema with the job's fingerprint) or runs the
job again (with a warning), never raises. The examples are derandomized (reproducible in CI).
"""
from __future__ import annotations

import copy
import json
import tomllib
import warnings
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flexmbs.batch import invalid_result, run_batch, StoredResult
from flexmbs.errors import CaseError
from flexmbs.files import read_stored
from flexmbs.paper.study import Study, load_study
from test_casefile_fuzz import ODD_VALUES, mutate
from test_casefile_fuzz import _value as scalar_value

STUDY = Path(__file__).resolve().parents[1] / "cases" / "studies" / "paper.toml"


class Deep:
    """A value written as `depth` nested arrays (built as text: no recursion in the writer)."""

    def __init__(self, depth):
        self.depth = depth


def _value(v):
    """TOML text of a value; strings and keys quoted as JSON (newlines, any key)."""
    if isinstance(v, Deep):
        return "[" * v.depth + "]" * v.depth
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)     # JSON's escapes are TOML's
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_value(x)}" for k, x in v.items()) + "}"
    return scalar_value(v)          # booleans and numbers (nan, inf)


def to_toml(data):
    """TOML text of a dict: every top-level key with an inline value (keys quoted)."""
    return "".join(f"{json.dumps(k)} = {_value(v)}\n" for k, v in data.items())


def test_writer_round_trips_the_study():
    """The writer reproduces the shipped study's data exactly, so a mutation is the only
    difference between the fuzzed file and the original."""
    data = tomllib.loads(STUDY.read_text(encoding="utf-8"))
    assert tomllib.loads(to_toml(data)) == data


STUDY_MUTATION = st.tuples(
    st.sampled_from(["delete", "replace", "replace", "scale", "add"]),
    st.integers(min_value=0, max_value=10**6),
    st.one_of(ODD_VALUES, st.builds(Deep, st.sampled_from([2, 50, 3000, 100000]))))


def test_damaged_study_gives_a_study_or_a_case_error(tmp_path_factory):
    """Mutated study files: load_study returns a Study or raises CaseError whose message names
    the file (flexmbs.paper.study's contract), nothing else."""
    original = tomllib.loads(STUDY.read_text(encoding="utf-8"))
    folder = tmp_path_factory.mktemp("study")
    counter = {"n": 0}

    @settings(max_examples=40, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(st.lists(STUDY_MUTATION, min_size=1, max_size=3))
    def check(mutations):
        counter["n"] += 1
        path = folder / f"fuzz_{counter['n']}.toml"
        path.write_text(to_toml(mutate(copy.deepcopy(original), mutations)), encoding="utf-8")
        try:
            study = load_study(path)
        except CaseError as exc:
            assert str(path.resolve()) in str(exc) or str(path) in str(exc), \
                f"CaseError does not name the file: {exc}"
            return
        assert isinstance(study, Study)

    check()
    assert counter["n"] >= 10


class _Result(StoredResult):
    value: float
    name: str


def cheap_job(x):
    """A job whose result has a schema (`_Result`)."""
    return {"value": 2.0 * x, "name": "cheap"}


cheap_job.result_schema = _Result

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False)
    | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
        st.sampled_from(["value", "name", "fingerprint", "flexmbs", "method", "options",
                         "description", "x"]) | st.text(max_size=3), inner, max_size=4),
    max_leaves=12)
STORED = st.one_of(
    JSON.map(lambda v: json.dumps(v).encode()),
    st.builds(lambda v, fp: json.dumps({"value": v, "name": "cheap", "fingerprint": fp}).encode(),
              st.floats(allow_nan=False), JSON),
    st.sampled_from([b"", b"[" * 5000, b'{"a":' * 5000, b"[" * 900 + b"]" * 900, b"\xff\xfe", b"NaN", b"{",
                     b'{"value": 6.0, "name": "cheap"}']),
    st.binary(max_size=20))


@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(STORED, st.booleans())
def test_damaged_stored_result_is_reused_or_run_again(tmp_path_factory, content, fingerprints):
    """A stored result file of any content: read_stored gives JSON or None, invalid_result a
    reason or None, and run_batch returns the job's result -- the stored one only when it fits
    the schema (and, with fingerprints, carries the job's fingerprint), else the recomputed
    {'value': 6.0, 'name': 'cheap'} -- never an exception."""
    store = tmp_path_factory.mktemp("store")
    (store / "j.json").write_bytes(content)
    value = read_stored(store / "j.json")
    why = invalid_result(value, _Result) if value is not None else "unreadable"
    assert why is None or isinstance(why, str)
    fp = {"j": {"flexmbs": "0", "method": "cheap_job", "options": {"x": 3.0},
                "description": None}} if fingerprints else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = run_batch(cheap_job, {"j": {"x": 3.0}}, workers=1, store=store, progress=False,
                        fingerprints=fp)
    result = out["j"]
    _Result.model_validate(result)
    if why is not None or (fingerprints and result.get("fingerprint") != fp["j"]):
        assert result["value"] == 6.0
    assert read_stored(store / "j.json") == result
