"""A numba cache directory of its own for each concurrently running test process.

numba's ``cache=True`` keeps an index per function and numbers its data files; two
processes compiling different signatures of the same kernel at once can both pick the
same free number, and one then loads the other's machine code. Each test process
therefore claims a cache slot (``<tmp>/m2s2hil-numba-<tree>/slot-N``) with an exclusive
lock held for its lifetime: one run after another reuses slot 0 (a warm cache), runs side
by side get different slots, and so do the workers of one ``pytest -n 2`` run (each claims
its own in its ``pytest_configure``; the controller, which runs no test, claims none).
Subprocesses a test starts inherit their parent's slot.

Must run before numba is imported (numba reads ``NUMBA_CACHE_DIR`` once, at import).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import sys
import tempfile
import warnings
from pathlib import Path

_held: list[int] = []  # lock file descriptors, open for the life of the process


def claim_slot(base: Path | None = None, *, max_slots: int = 64) -> Path:
    """Lock the first free slot under ``base`` and point ``NUMBA_CACHE_DIR`` at it."""
    if base is None:
        tree = hashlib.sha256(str(Path(__file__).resolve().parents[1]).encode()).hexdigest()[:12]
        base = Path(tempfile.gettempdir()) / f"m2s2hil-numba-{tree}"
    for n in range(max_slots):
        slot = base / f"slot-{n}"
        slot.mkdir(parents=True, exist_ok=True)
        fd = os.open(slot / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        _held.append(fd)
        os.environ["NUMBA_CACHE_DIR"] = str(slot)
        return slot
    raise RuntimeError(f"all {max_slots} numba cache slots under {base} are in use")


def use_private_numba_cache(*, worker: bool = False) -> None:
    """Claim a slot unless this process already has a cache dir (a test's subprocess, or CI's).

    An xdist ``worker`` always claims one: its siblings see the same environment, so a cache
    dir given from outside becomes the base of their slots instead of one shared dir."""
    if "numba" in sys.modules:
        warnings.warn("numba was imported before the test cache slot was claimed", stacklevel=2)
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given is None:
        claim_slot()
    elif worker:
        claim_slot(Path(given))
