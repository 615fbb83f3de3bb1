"""What the command line prints: `flexmbs --version`, the citation file, the verdicts of
`optimize` (one meaning each, docs/json-output.md "What `optimize` reports"), the verified step
and the command that re-checks it, and the units of the printed numbers."""
import json
from pathlib import Path

import pytest

import flexmbs
from flexmbs.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- version, citation
def test_version_prints_the_package_version(capsys):
    """`flexmbs --version` prints "flexmbs X.Y.Z" with flexmbs.__version__
    (python/flexmbs/version.py) and exits with status 0."""
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"flexmbs {flexmbs.__version__}"


def test_citation_file_has_the_required_cff_keys():
    """CITATION.cff parses as YAML and has the keys Citation File Format 1.2.0 requires
    (cff-version, message, title, authors), the package's version, and the paper as
    preferred-citation: its title and authors as the paper states them (Tromme, Brüls,
    Duysinx) and its DOI."""
    yaml = pytest.importorskip("yaml")
    d = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert d["cff-version"] == "1.2.0"
    for key in ("message", "title", "authors"):
        assert d[key]
    assert str(d["version"]) == flexmbs.__version__
    paper = d["preferred-citation"]
    assert paper["type"] == "article"
    assert paper["title"] == ("Weakly and fully coupled methods for structural optimization "
                              "of flexible mechanisms")
    assert [a["family-names"] for a in paper["authors"]] == ["Tromme", "Brüls", "Duysinx"]
    assert paper["doi"].startswith("10.1007/s11044-")
    assert (paper["journal"], paper["volume"], paper["year"]) == (
        "Multibody System Dynamics", 38, 2016)
