"""The session owner's lock: an exclusive ``flock`` on ``<session>/.owner.lock``.

One process at a time may write a session (capture, resume, repair, the daemon's job).
It holds the lock for as long as it has the session open for writing; the kernel drops
it when the process dies, so a crashed writer never leaves a stale lock behind. A reader
never takes it and never creates the file: it only asks whether somebody holds it (a
shared lock that cannot be had means a live writer), so it knows that temporary files
in the folder belong to a write in progress.

``flock`` locks belong to the open file description, so two opens in one process
exclude each other just as two processes do (the tests rely on that).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import time
from pathlib import Path

from m2s2hil.errors import UsageError

LOCK_NAME = ".owner.lock"


class SessionLocked(UsageError):
    """Another process (or another open handle) is writing this session."""

    exit_code = 1

    def __init__(self, path: Path, pid: int | None) -> None:
        self.path = path
        self.pid = pid
        who = f"process {pid}" if pid else "another process"
        super().__init__(f"session {path.name} is being written by {who} ({path / LOCK_NAME}); "
                         "wait for it to end or stop it first")


def _holder_pid(path: Path) -> int | None:
    with contextlib.suppress(OSError, ValueError):
        return int((path / LOCK_NAME).read_text().split()[0])
    return None


class OwnerLock:
    """The exclusive lock of one session folder; :meth:`release` (or process exit) drops it."""

    def __init__(self, folder: Path, fd: int) -> None:
        self.folder = folder
        self._fd: int | None = fd

    @classmethod
    def acquire(cls, folder: str | Path, *, wait_s: float = 0.5) -> OwnerLock:
        """Take the lock, waiting up to ``wait_s`` (a reader's probe holds a shared lock
        for an instant); :class:`SessionLocked` if a writer keeps it."""
        folder = Path(folder)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                if time.monotonic() >= deadline:
                    os.close(fd)
                    raise SessionLocked(folder, _holder_pid(folder)) from None
                time.sleep(0.02)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return cls(folder, fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def writer_active(folder: str | Path) -> bool:
    """Does a live process hold the session's owner lock? Creates nothing."""
    try:
        fd = os.open(Path(folder) / LOCK_NAME, os.O_RDONLY)
    except OSError:
        return False  # never locked (or unreadable): no live writer we could know of
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)
