"""The documentation site (`make docs`: mkdocs + mkdocstrings, mkdocs.yml, docs/) builds in
strict mode with no warning, has every page of docs/ in its navigation, and its API reference
(docs/api/) covers the package: every module and every public name."""
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

import flexmbs

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "python" / "flexmbs"
DOCS = ROOT / "docs"
PAGES = DOCS / "api"


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


def _nav_pages(entries):
    """Every page (a path relative to docs/) named in mkdocs.yml's nav, at any depth."""
    found = set()
    for entry in entries:
        items = entry.values() if isinstance(entry, dict) else [entry]
        for item in items:
            found.update(_nav_pages(item) if isinstance(item, list) else {item})
    return found


def test_every_page_is_in_the_navigation():
    """Each Markdown page under docs/ (but the reproduction's stored jobs, which mkdocs.yml
    excludes) is named in mkdocs.yml's nav, and each nav entry is a page that exists: a page
    is reachable from the site's home page. docs_dir is docs/ itself, so the guide's pages
    and the API reference build into one site."""
    import yaml
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    assert config["docs_dir"] == "docs"
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")
             if "jobs" not in p.relative_to(DOCS).parts}
    nav = _nav_pages(config["nav"])
    assert not sorted(pages - nav), f"pages of docs/ not in mkdocs.yml's nav: {sorted(pages - nav)}"
    assert not sorted(nav - pages), f"nav entries with no page: {sorted(nav - pages)}"


def test_home_page_links_every_guide_page():
    """docs/index.md, the site's home, links each page of docs/ (the API reference through its
    own index, api/index.md, whose pages link one another)."""
    home = (DOCS / "index.md").read_text(encoding="utf-8")
    linked = set(re.findall(r"\]\(([^)#\s]+\.md)\)", home))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")
             if "jobs" not in p.relative_to(DOCS).parts and p.parent != PAGES
             and p.name != "index.md"} | {"api/index.md"}
    assert not sorted(pages - linked), f"pages not linked from docs/index.md: {sorted(pages - linked)}"


def test_strict_build_has_no_warning(tmp_path):
    """`mkdocs build --strict` (as `make docs`) exits 0 with no WARNING line, and the API
    reference's index page (api/index.html) has an entry (anchor id="flexmbs.NAME") for every
    name of flexmbs.__all__: the docstrings parse (numpydoc sections, Markdown prose), the
    guide's links resolve, and the public API is all there."""
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
    index = (site / "api" / "index.html").read_text()
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
