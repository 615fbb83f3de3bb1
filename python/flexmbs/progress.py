"""Progress of long runs on a terminal, through tqdm (one bar per run, on stderr by default).

Library code never shows progress unless asked: every function taking a ``progress`` option
turns it into a reporter with `reporter`:

    None or False     nothing
    True              a tqdm bar on sys.stderr
    a text stream     a tqdm bar on that stream (anything with ``write``, e.g. io.StringIO)
    a callable        called with each record (a history record of a cycle / iteration, or
                      a finished job's result), nothing printed

The command line (``flexmbs optimize``) passes True when stderr is a terminal
(``--progress/--no-progress`` overrides). `Bar.__call__` takes one record; what the bar shows
beside the count is made from that record by a `describe` function of the caller (simulations,
mass, constraint violation, ...). A reporter has ``close()`` (a no-op for a plain callable).
"""
from __future__ import annotations

import os
import sys

from flexmbs.errors import ModelError

__all__ = ["reporter", "Bar", "check_progress", "fmt", "describe_iteration", "describe_cycle",
           "describe_start"]


def check_progress(progress):
    """`progress` checked: None/False, True, a text stream or a callable (ModelError otherwise,
    naming the value)."""
    if progress is None or progress is False or progress is True:
        return progress
    if hasattr(progress, "write") or callable(progress):
        return progress
    raise ModelError(f"progress must be a callable taking one history record, or None/False, "
                     f"got {progress!r} (or True: a bar on stderr, or a text stream)")


class Bar:
    """A tqdm bar counting records: `bar(record)` advances it to `position(record)` (default
    one more) and shows `describe(record)` beside the count; `close()` ends the line.

    Parameters
    ----------
    total : int or None
        The largest count (e.g. the iteration limit); None: no percentage.
    label : str
        Text before the bar ('iterations', 'cycles', 'starts', ...).
    stream : text stream, optional
        Default sys.stderr (looked up when the bar is made).
    describe : callable(record) -> str, optional
    position : callable(record) -> int, optional
        The count after this record (e.g. the iteration number); default: records seen.
    """

    def __init__(self, total=None, label="", stream=None, describe=None, position=None,
                 initial=0):
        from tqdm import tqdm

        self.describe = describe
        self.position = position
        stream = stream or sys.stderr
        try:
            cols = os.get_terminal_size(stream.fileno()).columns
        except (AttributeError, OSError, ValueError):
            cols = 0
        # a terminal of unknown width (0 columns, e.g. a pseudo-terminal without a size)
        # would get no bar from tqdm: 100 columns and 20 rows then
        width = dict(dynamic_ncols=True) if cols > 0 else dict(ncols=100, nrows=20)
        self._bar = tqdm(total=total, desc=label, file=stream, initial=initial, leave=True,
                         disable=False, mininterval=0.0, smoothing=0.1, **width)

    def __call__(self, record=None):
        bar = self._bar
        n = bar.n + 1 if self.position is None or record is None else self.position(record)
        if self.describe is not None and record is not None:
            bar.set_postfix_str(self.describe(record), refresh=False)
        if int(n) > bar.n:
            bar.update(int(n) - bar.n)
        else:
            bar.refresh()

    def close(self):
        self._bar.close()

    def write(self, text, file=None):
        """Print a line (on `file`, default the bar's stream) with the bar cleared first and
        drawn again after it (tqdm.write), so that lines and bar do not mix."""
        self._bar.write(text, file=file or self._bar.fp)


class _Callback:
    """A user's callable as a reporter (close() does nothing)."""

    def __init__(self, func):
        self.func = func

    def __call__(self, record=None):
        self.func(record)

    def close(self):
        pass


def reporter(progress, *, total=None, label="", describe=None, position=None, initial=0):
    """The reporter of a `progress` option (module docstring): None, a `Bar` or a callable
    wrapper; both have close()."""
    progress = check_progress(progress)
    if progress is None or progress is False:
        return None
    if progress is True:
        return Bar(total, label, None, describe, position, initial)
    if hasattr(progress, "write"):
        return Bar(total, label, progress, describe, position, initial)
    return _Callback(progress)


def fmt(value, spec, unit=""):
    """value formatted with spec, '-' when None."""
    return "-" if value is None else f"{value:{spec}}{unit}"


def _mass_or_objective(rec):
    m = rec.get("mass_kg")
    return f"mass {m:.5g} kg" if m is not None else f"objective {fmt(rec.get('objective'), '.5g')}"


def describe_iteration(rec):
    """A fully coupled iteration record in a few words: simulations, mass, violation."""
    return (f"{rec.get('simulations', '-')} sims, {_mass_or_objective(rec)}, "
            f"max violation {fmt(rec.get('max_violation'), '.1e')}")


def describe_cycle(rec):
    """A weakly coupled cycle record in a few words: mass, violation, ESL change."""
    return (f"{_mass_or_objective(rec)}, max g {fmt(rec.get('max_violation'), '+.1e')}, "
            f"ESL change {fmt(rec.get('esl_change'), '.2e')}")


def describe_start(best):
    """Multi-start: the best feasible objective found so far (None: none yet)."""
    return "no feasible design yet" if best is None else f"best feasible {best:.6g}"
