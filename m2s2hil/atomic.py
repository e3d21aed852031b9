"""Crash-safe file writes: temporary name in the same folder, fsync, rename, fsync the folder.

A reader (or a resumed session) therefore sees either the old file or the complete new
one under the final name, never a partial file. A full disk (ENOSPC, EDQUOT) becomes the
typed :class:`DiskFull` so the engine can suspend instead of crashing; the temporary
files are removed on every failure path.

A leaf of the application (it imports only m2s2hil.errors), so that the session store,
processing (darks, calibrations), the rig and the analysis all write through it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import secrets
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from m2s2hil.errors import M2S2Error

TMP_MARK = ".tmp-"
# Keep this much free beyond what a write needs: SQLite's WAL and the OS need room too.
DEFAULT_RESERVE_BYTES = 64 * 1024 * 1024
_NO_SPACE = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


class DiskFull(M2S2Error):
    """Not enough free space to write a file (or the write failed with ENOSPC)."""

    fault_class = "disk_full"

    def __init__(self, path: str | Path, *, needed: int | None = None, free: int | None = None,
                 detail: str = "") -> None:
        self.path = str(path)
        self.needed = needed
        self.free = free
        parts = [f"disk full at {self.path}"]
        if needed is not None and free is not None:
            parts.append(f"need {_mb(needed)} MB, {_mb(free)} MB free")
        if detail:
            parts.append(detail)
        super().__init__(": ".join(parts) + "; free some space and resume the session")


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f}"


@dataclass(frozen=True)
class Written:
    path: Path
    sha256: str
    bytes: int


def is_no_space(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in _NO_SPACE


def check_free_space(root: str | Path, needed_bytes: int, *,
                     reserve_bytes: int = DEFAULT_RESERVE_BYTES) -> int:
    """Raise :class:`DiskFull` unless ``needed_bytes`` + reserve fit on ``root``'s filesystem.
    Returns the free bytes."""
    p = Path(root)
    while not p.exists() and p != p.parent:
        p = p.parent
    free = shutil.disk_usage(p).free
    if free < needed_bytes + reserve_bytes:
        raise DiskFull(root, needed=needed_bytes + reserve_bytes, free=free)
    return free


def _write_fd(fd: int, data: bytes | memoryview) -> None:
    """Write everything (os.write may write less than asked)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def fsync_dir(path: str | Path) -> None:
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temp_name(final: Path) -> Path:
    return final.with_name(f".{final.name}{TMP_MARK}{os.getpid()}-{secrets.token_hex(4)}")


def _write_temp(final: Path, data: bytes) -> Path:
    tmp = _temp_name(final)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        _write_fd(fd, data)
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    os.close(fd)
    return tmp


def write_files_atomic(files: Mapping[str | Path, bytes]) -> dict[Path, Written]:
    """Write several files so that none appears under its final name unless all were
    written and synced: phase 1 writes and fsyncs every temporary file, phase 2 renames
    them and fsyncs each folder once. Returns size and sha256 per final path."""
    temps: list[tuple[Path, Path]] = []
    out: dict[Path, Written] = {}
    try:
        for final, data in files.items():
            final = Path(final)
            final.parent.mkdir(parents=True, exist_ok=True)
            temps.append((_write_temp(final, data), final))
            out[final] = Written(final, hashlib.sha256(data).hexdigest(), len(data))
        for tmp, final in temps:
            os.replace(tmp, final)
        for folder in {final.parent for _, final in temps}:
            fsync_dir(folder)
    except OSError as exc:
        for tmp, _ in temps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if is_no_space(exc):
            first = next(iter(files), "")
            raise DiskFull(Path(first).parent, detail=str(exc)) from exc
        raise
    except BaseException:
        for tmp, _ in temps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise
    return out


def write_bytes_atomic(path: str | Path, data: bytes) -> Written:
    return write_files_atomic({Path(path): data})[Path(path)]


def write_text_atomic(path: str | Path, text: str) -> Written:
    return write_bytes_atomic(path, text.encode("utf-8"))


def remove_temp_files(folder: str | Path) -> list[Path]:
    """Delete temporary files a crashed writer left behind (recursively). Only a session's
    owner, holding its lock (m2s2hil.store.owner_lock), may call this: anyone else could
    delete a live writer's file between its write and its rename."""
    removed = []
    base = Path(folder)
    if not base.is_dir():
        return removed
    for p in base.rglob(f".*{TMP_MARK}*"):
        if p.is_file():
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
