"""The API reference (`make docs`: mkdocs + mkdocstrings, mkdocs.yml, docs/api/) builds in
strict mode with no warning, and covers the package: every module and every public name."""
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

import flexmbs

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "python" / "flexmbs"
PAGES = ROOT / "docs" / "api"


def _documented_modules():
    """The modules named by a `::: flexmbs...` directive on any page of docs/api/."""
    found = set()
    for page in PAGES.glob("*.md"):
        found.update(re.findall(r"^::: (flexmbs[\w.]*)\s*$", page.read_text(), re.M))
    return found


def test_every_module_has_a_page():
    """Each module of python/flexmbs (but __main__) is rendered by some page of docs/api/:
    a module added to a layer without its line there would be missing from the reference."""
    modules = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] == "__main__":
            continue
        modules.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    missing = sorted(modules - _documented_modules())
    assert not missing, f"modules on no page of docs/api/: {missing}"


def test_strict_build_has_no_warning(tmp_path):
    """`mkdocs build --strict` (as `make docs`) exits 0 with no WARNING line, and its index page
    has an entry (anchor id="flexmbs.NAME") for every name of flexmbs.__all__: the docstrings
    parse (numpydoc sections, Markdown prose) and the public API is all there."""
    missing = [m for m in ("mkdocs", "mkdocstrings") if importlib.util.find_spec(m) is None]
    if missing:     # a failure, not a skip: `make test` installs the docs extra
        pytest.fail(f"the docs extra is not installed (no {', '.join(missing)}): run "
                    f"`make setup` or `pip install -e .[docs]`")
    site = tmp_path / "site"
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                          "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    log = run.stdout + run.stderr
    warnings = [line for line in log.splitlines() if "WARNING" in line or "ERROR" in line]
    assert run.returncode == 0 and not warnings, "\n".join(warnings) or log[-3000:]
    index = (site / "index.html").read_text()
    names = [n for n in flexmbs.__all__ if n != "__version__"]
    absent = [n for n in names if f'id="flexmbs.{n}"' not in index]
    assert not absent, f"public names missing from the reference's index: {absent}"


def test_doctest_blocks_fenced_outside_examples():
    """tools/doctest_blocks.py fences a '>>>' block (to its blank line) as pycon code outside a
    numpydoc Examples section and leaves one inside it to griffe's parser: the two cases of its
    docstring, on a docstring written for them."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from doctest_blocks import fence_doctests
    finally:
        sys.path.remove(str(ROOT / "tools"))
    text = "Intro.\n\n>>> a = [[1]]\n>>> a[0][0]\n1\n\nAfter.\n\nExamples\n--------\n>>> 2\n2"
    assert fence_doctests(text) == ("Intro.\n\n```pycon\n>>> a = [[1]]\n>>> a[0][0]\n1\n```\n\n"
                                    "After.\n\nExamples\n--------\n>>> 2\n2")
