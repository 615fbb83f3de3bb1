"""Plain files: what may be read (a regular file, never a FIFO, device or folder) and what
JSON can hold, and how a file is written whole or not at all (`atomic_open`, `atomic_path`).
The lowest layer of the package's file handling: case files, studies, histories, stored results,
figures and films all go through it."""
from __future__ import annotations

import contextlib
import math
import json
import os
import shutil
import stat
import tempfile
from pathlib import Path

import numpy as np

from flexmbs.errors import ModelError, ResourceError

__all__ = ["check_regular_file", "file_kind", "jsonable", "atomic_path", "atomic_open",
           "write_atomic", "save_figure", "read_stored", "check_writable", "check_store",
           "check_disk_space", "write_failure"]


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


# ----------------------------------------------------------------------------- safe files
@contextlib.contextmanager
def atomic_path(path, suffix=".tmp"):
    """A temporary file name beside `path` (ending with `suffix`, for writers that choose the
    format by it) to write to; on success it is renamed to `path` (os.replace, atomic on
    POSIX) with the permissions `path` had (or a new file's); on any error it is deleted and
    whatever was at `path` is left untouched."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, _file_mode(path))     # mkstemp makes 0600 files
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_open(path, mode="w", encoding="utf-8"):
    """Open a temporary file beside `path` for writing; on success, flush it to disk (fsync)
    and rename it to `path` (`atomic_path`); on any error, delete it and leave whatever was at
    `path` untouched. So a reader never sees a half-written file under `path`.

    mode is 'w' (text) or 'wb' (binary).
    """
    if mode not in ("w", "wb"):
        raise ModelError(f"atomic_open mode must be 'w' or 'wb', got {mode!r}")
    with atomic_path(path) as tmp:
        with open(tmp, mode, **({} if "b" in mode else {"encoding": encoding})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def _file_mode(path):
    """The permissions of the file at `path`, else those a new file gets (0666 - umask)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask


def write_atomic(path, data):
    """Write text or bytes to `path` through `atomic_open`."""
    with atomic_open(path, "wb" if isinstance(data, (bytes, bytearray)) else "w") as fh:
        fh.write(data)
    return path


def save_figure(fig, path, **savefig_kw):
    """Save a matplotlib figure through a temporary file (`atomic_open`): a figure is either
    whole or absent. The format comes from the extension (png without one)."""
    fmt = os.path.splitext(os.fspath(path))[1][1:].lower() or "png"
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format=fmt, **savefig_kw)
    return path


def read_stored(path):
    """The JSON content of a stored result file, or None when it is missing or unreadable
    (truncated, not JSON, nested too deeply for Python's json, not a regular file): such a
    file does not count as a result."""
    try:
        if not check_regular_file(path, "stored result"):
            return None
    except ModelError:
        return None
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (ValueError, UnicodeDecodeError, RecursionError):    # JSONDecodeError: a ValueError
        return None


def check_writable(folder, what, create=False):
    """Check, before a run, that files can be created in `folder` (creating it when `create`):
    by creating and deleting a temporary file there, which also catches read-only file systems
    (permission bits say nothing when running as root).

    Raises ModelError naming `what` (e.g. "--out result.npz"), the folder and the reason.
    """
    folder = Path(folder) if str(folder) else Path(".")
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        elif folder.exists() and not folder.is_dir():
            raise ModelError(f"{what}: {str(folder)!r} is a file, not a folder")
        elif not folder.is_dir():
            raise ModelError(f"{what}: folder {str(folder)!r} does not exist "
                             "(create it first)")
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".flexmbs-write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ModelError(f"{what}: cannot write in folder {str(folder)!r}: "
                         f"{exc.strerror or exc}") from None
    return folder


def check_store(store, what="store"):
    """Create the folder `store` of run_batch's results (with its parents) or check the one
    there; ModelError naming `what` and the path when it is a file (or cannot be created)."""
    path = Path(store)
    if path.exists() and not path.is_dir():
        mode = path.stat().st_mode
        kind = "a file" if stat.S_ISREG(mode) else file_kind(mode)
        raise ModelError(f"{what} {os.fspath(store)!r} is {kind}, not a folder: give a folder "
                         "for the results (one file per job)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ModelError(f"{what} {os.fspath(store)!r}: cannot create the folder: "
                         f"{exc.strerror or exc}") from None
    return path


def check_disk_space(folder, required, what):
    """Raise ResourceError when the file system of `folder` has less than `required` bytes
    free (a rough estimate of what a run will write)."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < required:
        raise ResourceError(f"{what}: about {required / 1e6:.1f} MB will be written in "
                            f"{str(folder)!r} but only {free / 1e6:.1f} MB are free",
                            required=required, available=free)


def write_failure(path, what, reason):
    """The ResourceError of a file that could not be written whole (`what`, e.g. "the film", at
    `path`; `reason`: what the writer reported): with the free space of its folder and the
    process's file size limit (RLIMIT_FSIZE, `ulimit -f`) when one is set, the two usual
    causes."""
    import resource

    folder = Path(path).parent
    notes = []
    free = None
    try:
        free = shutil.disk_usage(folder).free
        notes.append(f"{free / 1e6:.1f} MB free in {str(folder)!r}")
    except OSError:
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY:
        notes.append(f"file size limit (ulimit -f) {soft} bytes")
    reason = " ".join(str(reason).split())
    return ResourceError(f"{what} {os.fspath(path)!r} could not be written whole: {reason:.200}"
                         + (f" ({'; '.join(notes)})" if notes else "")
                         + "; nothing was left under that name", available=free)
