"""Plain files: what may be read (a regular file, never a FIFO, device or folder) and what
JSON can hold. The lowest layer of the package's file handling: case files, studies,
histories and stored results all go through it."""
from __future__ import annotations

import math
import os
import stat

import numpy as np

from flexmbs.errors import ModelError

__all__ = ["check_regular_file", "file_kind", "jsonable"]


def file_kind(mode):
    """What a non-regular file is, in words."""
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular_file(path, what, error=ModelError):
    """Refuse, before opening it, a file that exists and is not a regular file: a FIFO (which
    would block the read or the write), a device such as /dev/zero (read without end), a
    folder. `error` (ModelError, or CaseError for case and study files) naming `what` (e.g.
    "--history"), the path and its kind; True when the file exists, False when it does not."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise error(f"{what} {os.fspath(path)!r} cannot be read: "
                    f"{exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise error(f"{what} {os.fspath(path)!r} is {file_kind(mode)}, not a regular file; "
                    "give the path of a file")
    return True


def jsonable(obj):
    """A copy of obj made of JSON types (numpy arrays/scalars -> lists/floats, NaN -> None)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "iub" or (obj.dtype.kind == "f" and np.all(np.isfinite(obj))):
            return obj.tolist()                 # plain ints / bools / finite floats: fast
        return jsonable(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj
