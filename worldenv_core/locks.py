"""One run at a time per stage target: a lock file held (flock) for the run's lifetime.

Two `collect`s into one episode folder, or two trainings into one work dir, would redo the same
work and race on its files. The lock file names the holder (pid, host, start time); the kernel
drops a lock whose process died, and the next run takes it over with a warning naming the run
that left it. A second run while the first is alive fails at once with a message naming it.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
from contextlib import contextmanager
import logging
import os
import platform
from pathlib import Path

from worldenv_core.errors import ArtefactError

log = logging.getLogger(__name__)
LOCK_NAME = ".lock"


class RunLockedError(ArtefactError):
    """Another live run holds the lock."""


class RunLock:
    def __init__(self, target: str | os.PathLike, what: str):
        """target: the folder the run writes (its lock is `<target>/.lock`); what: the run, for messages."""
        self.path = Path(target) / LOCK_NAME
        self.what = what
        self._file = None

    def acquire(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        f = open(self.path, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "a run that has not written its name yet"
            f.close()
            raise RunLockedError(f"{self.what} is already running ({holder}; lock {self.path}): wait for it to "
                                 "finish, or stop it and run again") from None
        f.seek(0)
        left = f.read().strip()
        if left:  # written by a holder that never released it: it died (the kernel dropped its lock)
            log.warning("taking over the lock of %s left by a run that is gone (%s)", self.what, left)
        f.seek(0)
        f.truncate()
        started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        f.write(f"pid {os.getpid()} on {platform.node()} since {started}\n")
        f.flush()
        self._file = f
        return self

    def release(self) -> None:
        if self._file is None:
            return
        self._file.seek(0)
        self._file.truncate()  # empty: released cleanly
        self._file.flush()
        fcntl.flock(self._file, fcntl.LOCK_UN)
        self._file.close()
        self._file = None

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


@contextmanager
def waiting_lock(path: str | os.PathLike):
    """An exclusive lock on `path` (a lock file, created), waited for: around a short write of a
    file several runs rebuild (the experiment's report), so that the one holding it reads and
    writes the newest state and no write lands on another's."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
