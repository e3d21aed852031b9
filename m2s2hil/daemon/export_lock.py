"""One export at a time per output folder, and an export that is all or nothing.

Both front ends export through :func:`export_once`: ``m2s2hil export`` and the daemon's
``POST /sessions/{id}/export``. Under ``out``'s lock (an ``flock`` on a hidden file beside
``out``, so two threads of the daemon, two CLI runs and the CLI against the daemon all
exclude each other; the kernel drops it when its process dies, so a ``kill -9`` never leaves
it taken) the export is written into a hidden staging folder beside ``out``, which starts as
a hard-linked copy of ``out`` when the export adds to it (the m2s2 and hf layouts merge
sessions, zarr appends). Every writer replaces files by rename, never in place, so the links
leave ``out`` untouched. When the export is complete the staging folder takes ``out``'s place
in one ``renameat2(RENAME_EXCHANGE)`` (Linux; elsewhere two renames, with nothing under ``out``
for an instant), and the old tree is deleted.

A killed export therefore leaves ``out`` as it was (or absent) and a hidden folder
(``.<name>.export-*``), which the next export of ``out`` deletes under the lock. A second
export while one runs gets :class:`ExportBusy` (HTTP 409), at once: it does not wait.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import fcntl
import os
import secrets
import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

from m2s2hil.atomic import fsync_dir
from m2s2hil.errors import M2S2Error
from m2s2hil.store.export import ExportError, ExportResult, ProgressFn, export_session
from m2s2hil.store.session import SessionStore

STAGING_MARK = ".export-"
_RENAME_EXCHANGE = 2  # linux/fs.h


class ExportBusy(M2S2Error):
    """Another export (this process or another) is writing the same output folder."""

    def __init__(self, out: Path, holder: str) -> None:
        self.out = out
        who = f" (pid {holder})" if holder else ""
        super().__init__(f"another export is writing {out}{who}; try again when it has finished")


def lock_path(out: Path) -> Path:
    return out.parent / f".{out.name}.export-lock"


@contextlib.contextmanager
def export_lock(out: Path) -> Iterator[None]:
    """Hold ``out``'s export lock, or raise :class:`ExportBusy` at once."""
    out.parent.mkdir(parents=True, exist_ok=True)
    path = lock_path(out)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            raise ExportBusy(out, holder) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield
    finally:
        os.close(fd)  # releases the flock


def _staging_parents(out: Path) -> list[Path]:
    return [p for p in out.parent.glob(f".{out.name}{STAGING_MARK}*") if p != lock_path(out)]


def _remove_stale(out: Path) -> None:
    """Staging folders of exports that died (the caller holds the lock, so none is live)."""
    for p in _staging_parents(out):
        shutil.rmtree(p, ignore_errors=True)


def _link_tree(src: Path, dst: Path) -> None:
    """``dst`` as a copy of ``src`` whose files are hard links (copies where linking fails)."""

    def link(s: str, d: str) -> None:
        try:
            os.link(s, d)
        except OSError:
            shutil.copy2(s, d)

    shutil.copytree(src, dst, copy_function=link, symlinks=True)


def _fsync_tree(root: Path) -> None:
    """Every folder of ``root`` (the files were fsynced by their writers; links need their folders)."""
    for folder, _, _ in os.walk(root):
        fsync_dir(folder)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2``); False where the system cannot."""
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        return False
    libc = ctypes.CDLL(libc_name, use_errno=True)
    fn = getattr(libc, "renameat2", None)
    if fn is None:
        return False
    at_fdcwd = -100
    rc = fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _move_into_place(staged: Path, out: Path) -> None:
    if not out.exists():
        os.rename(staged, out)
    elif not _exchange(staged, out):
        os.rename(out, staged.with_name(staged.name + ".old"))  # deleted with the staging folder
        os.rename(staged, out)
    fsync_dir(out.parent)


def export_once(store: SessionStore, out: str | Path, layout: str = "m2s2", *, overwrite: bool = False,
                fresh: bool = False, progress: ProgressFn | None = None) -> ExportResult:
    """:func:`~m2s2hil.store.export.export_session` into ``out``, exclusively and atomically (see
    the module docstring). ``fresh``: start from an empty folder (what was in ``out`` goes);
    otherwise the export adds to ``out`` and ``overwrite`` says whether it may replace files."""
    out = Path(out).absolute()
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out} exists and is not a folder")
    with export_lock(out):
        _remove_stale(out)
        parent = out.parent / f".{out.name}{STAGING_MARK}{os.getpid()}-{secrets.token_hex(4)}"
        parent.mkdir()
        try:
            staged = parent / out.name  # the same name: a dataset card names its folder
            if out.is_dir() and not fresh:
                _link_tree(out, staged)
            result = export_session(store, staged, layout, overwrite=overwrite, progress=progress)
            _fsync_tree(staged)
            _move_into_place(staged, out)
        finally:
            shutil.rmtree(parent, ignore_errors=True)  # the old tree, or a failed export's files
    files = [out / p.relative_to(staged) if p.is_relative_to(staged) else p for p in result.files]
    return replace(result, out=out, files=files)
