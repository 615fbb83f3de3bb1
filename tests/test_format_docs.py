"""The file-format references and the pydantic schemas that validate the files cannot drift
apart: docs/case-format.md against flexmbs.description (case files) and docs/study-format.md
against flexmbs.study (study files). Every key a schema accepts is documented, every key the
reference's tables list is accepted, and every allowed word of a key (a `Literal` value such as
a joint type or a law type) is named in the reference."""
from __future__ import annotations

import pathlib
import re
import typing

from pydantic import BaseModel

import pytest

import flexmbs.model.description as description
import flexmbs.paper.study as study

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
FORMATS = [pytest.param("case-format.md", description.Description, id="case"),
           pytest.param("study-format.md", study.StudyFile, id="study")]


def _schema(root):
    """(keys, words, tables): every field name (its alias where it has one) of every model
    reachable from the root model, with the models that have it; every Literal value; the
    top-level tables."""
    keys, words, seen = {}, set(), set()

    def walk(tp):
        if typing.get_origin(tp) is typing.Literal:
            words.update(str(a) for a in typing.get_args(tp))
            return
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if tp in seen:
                return
            seen.add(tp)
            for name, field in tp.model_fields.items():
                keys.setdefault(field.alias or name, set()).add(tp.__name__)
                walk(field.annotation)
            return
        for arg in typing.get_args(tp):
            walk(arg)

    walk(root)
    return keys, words, set(root.model_fields)


def _first_cells(text):
    """The backticked entries of the first column of every table row of the reference."""
    found = set()
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            found.update(re.findall(r"`([^`]+)`", line.split("|")[1]))
    return found


@pytest.mark.parametrize("doc, root", FORMATS)
def test_every_schema_key_is_documented(doc, root):
    """Each key of the schema appears in backticks in its reference."""
    keys, _, _ = _schema(root)
    text = (DOCS / doc).read_text(encoding="utf-8")
    missing = sorted(k for k in keys
                     if not re.search(rf"`[^`\n]*\b{re.escape(k)}\b[^`\n]*`", text))
    assert not missing, (f"keys accepted by {root.__module__} but not documented in "
                         f"docs/{doc}: {missing}")


@pytest.mark.parametrize("doc, root", FORMATS)
def test_every_documented_key_is_accepted(doc, root):
    """Each backticked key in the first column of a table of the reference is a key, an
    allowed word or a top-level table ([name], [[name]], [name.NAME]) of the schema."""
    keys, words, tables = _schema(root)
    unknown = []
    for cell in sorted(_first_cells((DOCS / doc).read_text(encoding="utf-8"))):
        table = re.fullmatch(r"\[\[?([a-z_]+)(?:\.[A-Z]+)?\]\]?", cell)
        if table:
            ok = table.group(1) in tables
        else:
            ok = cell in keys or cell in words
        if not ok:
            unknown.append(cell)
    assert not unknown, (f"docs/{doc} lists keys the schema does not accept: {unknown}")


@pytest.mark.parametrize("doc, root", FORMATS)
def test_every_allowed_word_is_documented(doc, root):
    """Each non-numeric Literal value of the schema (joint types, law types, shapes, units,
    Newton strategies, methods ...) is named in its reference, in backticks or quotes."""
    _, words, _ = _schema(root)
    text = (DOCS / doc).read_text(encoding="utf-8")
    missing = sorted(w for w in words if not w.isdigit()
                     and f"`{w}`" not in text and f'"{w}"' not in text)
    assert not missing, f"allowed values not named in docs/{doc}: {missing}"
