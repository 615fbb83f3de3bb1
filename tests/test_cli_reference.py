"""docs/cli.md's "Every command and option" is the parser's own: the part between its markers
is what tools/cli_reference.py writes from `flexmbs.cli.main.build_parser` (each command's
description, each option's invocation and help), so an option added, removed or reworded
shows in the reference or fails here."""
import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
try:
    import cli_reference
finally:
    sys.path.remove(str(ROOT / "tools"))


def test_generated_part_is_current():
    """The text between the markers of docs/cli.md equals `cli_reference.reference()`."""
    text = cli_reference.PAGE.read_text(encoding="utf-8")
    start = text.index(cli_reference.BEGIN)
    end = text.index(cli_reference.END) + len(cli_reference.END)
    assert text[start:end] + "\n" == cli_reference.reference(), (
        "docs/cli.md's command reference is not the parser's: run "
        "`.venv/bin/python tools/cli_reference.py`")


def test_every_option_is_named():
    """Each option string of every subcommand of the parser (but -h/--help) appears in
    backticks in docs/cli.md: the shared options, listed once, count for every command."""
    from flexmbs.cli.main import build_parser

    text = cli_reference.PAGE.read_text(encoding="utf-8")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = [f"{name} {opt}" for name, p in sub.choices.items() for a in p._actions
               if not isinstance(a, argparse._HelpAction) and a.help is not argparse.SUPPRESS
               for opt in a.option_strings if f"`{opt}" not in text and f", {opt}" not in text]
    assert not missing, f"options not in docs/cli.md: {missing}"
