"""Local worker processes of `run_batch` exit when the process that started the batch is killed
with SIGKILL (which gives it no chance to end them): flexmbs.batch._watch_parent."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def sleeping_job(folder, name):
    """A job that records its worker's pid in `folder`/`name`.pid, then sleeps a minute."""
    path = Path(folder) / f"{name}.pid"
    path.with_suffix(".tmp").write_text(str(os.getpid()))
    path.with_suffix(".tmp").rename(path)
    time.sleep(60)
    return {}


def _running(pid):
    """Whether process `pid` exists and is not a zombie (/proc state 'Z')."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL and fork server: POSIX only")
@pytest.mark.parametrize("start_method", ["spawn", "forkserver"])
def test_workers_exit_when_the_caller_is_killed(tmp_path, start_method):
    """After `kill -9` of a process running run_batch with 2 local workers (jobs sleeping 60 s),
    both worker pids are gone within 10 s (the workers check their caller every second); before
    `_watch_parent` they slept on and then waited forever for more jobs."""
    code = ("import sys; sys.path.insert(0, {here!r}); "
            "from test_batch_orphans import sleeping_job; "
            "from flexmbs.batch import run_batch; "
            "run_batch(sleeping_job, {{n: dict(folder={folder!r}, name=n) for n in ('a', 'b')}}, "
            "workers=2, start_method={method!r}, progress=False)"
            ).format(here=str(HERE), folder=str(tmp_path), method=start_method)
    caller = subprocess.Popen([sys.executable, "-c", code])
    pids = []
    try:
        deadline = time.monotonic() + 60
        while len(list(tmp_path.glob("*.pid"))) < 2:
            assert caller.poll() is None, "the batch ended before its jobs started"
            assert time.monotonic() < deadline, "the workers did not start within 60 s"
            time.sleep(0.1)
        pids = [int(p.read_text()) for p in tmp_path.glob("*.pid")]
        assert all(_running(pid) for pid in pids)
        caller.send_signal(signal.SIGKILL)
        caller.wait()
        deadline = time.monotonic() + 10
        while any(_running(pid) for pid in pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = [pid for pid in pids if _running(pid)]
        assert not left, f"worker(s) {left} still running 10 s after their caller was killed"
    finally:
        if caller.poll() is None:
            caller.kill()
            caller.wait()
        for pid in pids:                 # only the workers this test started
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
