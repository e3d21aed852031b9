"""A session folder made and opened: built under a hidden name and renamed into place, its
journal opened and checked before anything is trusted or written.

:class:`~m2s2hil.store.session.SessionStore` ``create``/``open`` are built on these; a
failure to write (read-only mount, no permission, full disk) is the typed
:class:`OutputNotWritable` or ``DiskFull``, never a bare OSError, and leaves no staging folder.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

from m2s2hil.atomic import DiskFull, check_free_space, fsync_dir, is_no_space, write_text_atomic
from m2s2hil.config import RigConfig, parse_rig
from m2s2hil.errors import ConfigError
from m2s2hil.plan import PlanError, Sweep, parse_sweep
from m2s2hil.store.errors import OutputNotWritable, SessionCorrupt, SessionDamaged
from m2s2hil.store.frame_files import dumps
from m2s2hil.store.journal import Journal, JournalDamaged, JournalError
from m2s2hil.store.layout import JOURNAL


def software_version() -> str:
    """The installed m2s2hil's version, recorded in every session's journal."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("m2s2hil")
    except PackageNotFoundError:
        return "unknown"


def check_writable(folder: str | Path) -> None:
    """:class:`OutputNotWritable` unless ``folder`` (or its nearest existing parent) can be
    written: checked before free space, so a read-only mount is not mistaken for a full one."""
    p = Path(folder)
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        ro = bool(os.statvfs(p).f_flag & os.ST_RDONLY)
    except OSError:
        ro = False
    if ro:
        raise OutputNotWritable(Path(folder), "read-only file system")
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputNotWritable(Path(folder), "permission denied")


def not_writable(exc: OSError) -> bool:
    """Whether ``exc`` says the folder cannot be written (rather than anything else)."""
    return exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM)


def _mkdir(folder: Path, root: Path, **kw: bool) -> None:
    try:
        folder.mkdir(**kw)
    except OSError as exc:
        if not_writable(exc):
            raise OutputNotWritable(root, exc.strerror or str(exc)) from None
        raise


def create_folder(root: Path, session_id: str, sweep: Sweep, rig: RigConfig, *, now: float) -> Path:
    """``root/session_id`` with its journal (state ``created``) and the plan's and rig's
    JSON copies; built as ``.<id>.creating`` and renamed, so a crash leaves no half session."""
    final = root / session_id
    check_writable(root)
    _mkdir(root, root, parents=True, exist_ok=True)
    # Only the session's own small files must fit here: a short disk is the engine's to
    # report (it pauses, resumable), and a small mount is not "full" for a megabyte.
    check_free_space(root, 1024 * 1024, reserve_bytes=0)
    staging = root / f".{session_id}.creating"
    shutil.rmtree(staging, ignore_errors=True)
    _mkdir(staging, root)
    try:
        (staging / "frames").mkdir()
        (staging / "darks").mkdir()
        rig_json = dumps(rig.model_dump(mode="json"))
        j = Journal(staging / JOURNAL, create=True)
        try:
            j.init_session(
                session_id=session_id, satellite=sweep.satellite, build=sweep.build,
                sweep_json=sweep.model_dump_json(), rig_json=rig_json, rig_digest=rig.digest,
                software_version=software_version(), state="created", now=now,
            )
        finally:
            j.close()
        write_text_atomic(staging / "sweep.json", sweep.to_json() + "\n")
        write_text_atomic(staging / "rig.json",
                          json.dumps(rig.model_dump(mode="json"), indent=2, sort_keys=True) + "\n")
        os.replace(staging, final)
        fsync_dir(root)
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if is_no_space(exc):
            raise DiskFull(root, detail=str(exc)) from exc
        if not_writable(exc):
            raise OutputNotWritable(root, exc.strerror or str(exc)) from None
        raise
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return final


def open_journal(path: Path, session_id: str, *, read_only: bool) -> tuple[Journal, Sweep, RigConfig]:
    """The session's journal, checked (``quick_check``), with the plan and rig it holds.
    :class:`SessionDamaged` (``sessions repair`` can rebuild it) or :class:`SessionCorrupt`;
    the journal is closed on every failure."""
    try:
        j = Journal(path / JOURNAL, read_only=read_only)
    except JournalDamaged as exc:
        raise SessionDamaged(path, exc.detail) from None
    except JournalError as exc:
        raise SessionCorrupt(str(exc)) from None
    damage = j.check()
    if damage is not None:
        j.close()
        raise SessionDamaged(path, damage)
    try:
        row = j.session()
        sweep = parse_sweep(json.loads(row["sweep_json"]), f"{path}: sweep")
        rig = parse_rig(json.loads(row["rig_json"]), f"{path}: rig")
    except JournalDamaged as exc:
        j.close()
        raise SessionDamaged(path, str(exc)) from None
    except (JournalError, PlanError, ConfigError, json.JSONDecodeError) as exc:
        j.close()
        raise SessionCorrupt(f"{path}: journal content unusable: {exc}") from None
    if row["session_id"] != session_id:
        j.close()
        raise SessionCorrupt(f"{path}: journal belongs to session {row['session_id']!r}")
    return j, sweep, rig
