"""A griffe extension for the API reference (mkdocs.yml): a doctest block (lines from '>>> ' to
the next blank line) outside a numpydoc Examples section is fenced as code, so that Markdown
shows it as written instead of reading its '>>>' as nested quotes and its '[1][0]' as links.
Blocks inside an Examples section are left to griffe's numpydoc parser, which does the same."""
import re

import griffe

_UNDERLINE = re.compile(r"^-{3,}\s*$")


def fence_doctests(text):
    """`text` (a dedented docstring) with each doctest block outside Examples fenced as pycon."""
    lines = text.split("\n")
    out, section, i = [], None, 0
    while i < len(lines):
        line = lines[i]
        if i + 1 < len(lines) and line.strip() and _UNDERLINE.match(lines[i + 1]):
            section = line.strip().lower()
        if line.startswith(">>>") and section != "examples":
            j = i
            while j < len(lines) and lines[j].strip():
                j += 1
            out += ["```pycon", *lines[i:j], "```"]
            i = j
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


class DoctestBlocks(griffe.Extension):
    """Fences the doctest blocks of every docstring as it is loaded."""

    def on_instance(self, *, obj, **kwargs):
        if obj.docstring is not None and ">>>" in obj.docstring.value:
            obj.docstring.value = fence_doctests(obj.docstring.value)
