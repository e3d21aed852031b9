"""The daemon's exclusive lock on its data root: two daemons must not write one root."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path
from typing import IO

from m2s2hil.errors import UsageError

LOCK_NAME = ".m2s2hil-daemon.lock"


class RootLocked(UsageError):
    """Another daemon serves this data root."""


def lock_data_root(root: str | Path) -> IO[str]:
    """An exclusive lock on the data root for the daemon's lifetime (released when the returned
    file is closed or the process ends): two daemons must not write one root."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    f = open(root / LOCK_NAME, "a+")  # noqa: SIM115  (held for the daemon's life)
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        raise RootLocked(f"another m2s2hil daemon is serving {root}") from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def unlock_data_root(f: IO[str]) -> None:
    """Release a lock taken by :func:`lock_data_root` and close its file."""
    with contextlib.suppress(OSError):
        fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    f.close()
