"""A numba cache directory of its own for each concurrently running test process.

numba's ``cache=True`` keeps an index per function and numbers its data files; two
processes compiling different signatures of the same kernel at once can both pick the
same free number, and one then loads the other's machine code. Each test process
therefore claims a cache slot (``<tmp>/m2s2hil-numba-<tree>/slot-N``) with an exclusive
lock held for its lifetime: one run after another reuses slot 0 (a warm cache), runs side
by side get different slots, and so do the workers of one ``pytest -n 3`` run (each claims
its own in its ``pytest_configure``; the controller, which runs no test, claims none).
Subprocesses a test starts inherit their parent's slot.

A claimed slot is first seeded from the package's own cache (``__pycache__`` beside each kernel's
source, filled by any run of m2s2hil without ``NUMBA_CACHE_DIR`` and by ``m2s2hil
compile-kernels``, which ``.ci/run`` calls as part of installing): a kernel whose index there is
newer than the slot's is copied in, so a fresh checkout's workers load machine code instead of
each compiling it again (75 s of CPU per process for every method and dtype).

Must run before numba is imported (numba reads ``NUMBA_CACHE_DIR`` once, at import).
"""

from __future__ import annotations

import fcntl
import glob
import hashlib
import os
import shutil
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
        seed_slot(slot)
        os.environ["NUMBA_CACHE_DIR"] = str(slot)
        return slot
    raise RuntimeError(f"all {max_slots} numba cache slots under {base} are in use")


TREE = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = ("m2s2hil", "simulators", "drivers", "protocols")  # the package-dir mapping's folders


def seed_slot(slot: Path, tree: Path = TREE) -> int:
    """Copy into ``slot`` each kernel cache of ``tree``'s ``__pycache__`` dirs that is newer than the
    slot's (an index with its data files); returns how many kernels were copied. The slot's layout
    is numba's for a user-given cache dir: ``<source dir name>_<sha1 of its absolute path>``."""
    copied = 0
    for top in PACKAGE_DIRS:
        for index in (tree / top).glob("**/__pycache__/*.nbi"):
            src_dir = index.parent.parent.resolve()
            dest = slot / f"{src_dir.name}_{hashlib.sha1(str(src_dir).encode()).hexdigest()}"
            mine = dest / index.name
            try:
                if mine.exists() and mine.stat().st_mtime >= index.stat().st_mtime:
                    continue
                dest.mkdir(parents=True, exist_ok=True)
                stem = index.name[: -len(".nbi")]
                for data in index.parent.glob(f"{glob.escape(stem)}.*.nbc"):
                    shutil.copy2(data, dest / data.name)
                shutil.copy2(index, mine)  # last: an index never points at data not yet copied
            except OSError:
                continue  # a cache file being rewritten meanwhile: this kernel compiles instead
            copied += 1
    return copied


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
