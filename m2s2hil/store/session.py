"""The session store: one folder per session under a data root.

Layout of ``<root>/<session_id>/``::

    journal.sqlite            the journal (see m2s2hil.store.journal); the source of truth
    sweep.json, rig.json      human-readable copies of the plan and the rig
    frames/<event>.raw.tiff   raw mosaic, uint16, metadata JSON in ImageDescription
    frames/<event>.cube.tiff  processed cube (bands, H, W), float32, only when stored (below)
    frames/<event>.preview.jpg  8-bit RGB quick-look (.png in legacy sessions)
    darks/<dark>.tiff         master darks, uint16 (float32 in legacy sessions)
    manifest.json             every file with its sha256, written at completion

``<event>`` is the event id with ``/`` replaced by ``_`` (``weak_E0_az010_f0``).

Ownership: a session is open either for reading (``SessionStore.open``, the default:
the journal opened read-only, nothing in the folder changed, writes refused) or for
writing (``mode="write"``, and :meth:`SessionStore.create`): the writer holds the
session's owner lock (m2s2hil.store.owner_lock) for as long as it is open, checks the
journal (``PRAGMA quick_check``) before anything is written, and only then removes the
temporary files a crashed writer left. ``check_stored`` (resume) verifies every stored
file and moves a missing or damaged frame aside so it is captured again.

Integrity: every file goes to a temporary name in its folder, is fsynced, renamed, and
the folder fsynced (m2s2hil.store.atomic); its sha256 goes into the journal. The frame's
journal row is committed LAST, so a crash leaves at worst files without a row (a resumed
run overwrites them) and never a row without its files. An event id is written once:
writing it again raises :class:`DuplicateEvent`.

Storage format: the rig's ``[storage]`` (m2s2hil.store.frame_files): by default raw
mosaics and darks are deflate-compressed uint16 TIFF and cubes are not stored but computed
when read (:meth:`SessionStore.read_cube`, m2s2hil.store.cubes); legacy sessions
(uncompressed raw, float32 darks, stored cubes) read the same way.

Frame metadata (``write_frame(..., meta=)``): the caller's measurements plus what the
store owns (event, session, software version, rig digest, processing method, storage
format, cube recipe), built in one place and encoded once (m2s2hil.store.frame_meta); a
caller key the store owns is refused. Recommended keys, used by export: ``exposure_s``,
``gain``, ``temperature_c``,
``pose`` = {``turntable_deg``, ``tilt_deg``} (read-back), ``lamps_on`` (channels),
``timestamp`` (wall seconds), ``device_timestamp_s``, ``block_id``.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import secrets
import shutil
import sqlite3
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from m2s2hil.config import RigConfig, parse_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import ConfigError, M2S2Error, UsageError
from m2s2hil.plan import CaptureEvent, PlanError, Sweep, parse_sweep
from m2s2hil.store.atomic import (
    DEFAULT_RESERVE_BYTES,
    TMP_MARK,
    DiskFull,
    check_free_space,
    fsync_dir,
    is_no_space,
    remove_temp_files,
    sha256_file,
    write_files_atomic,
    write_text_atomic,
)
from m2s2hil.store.cubes import CubeComputer, cube_is_stored
from m2s2hil.store.frame_files import (
    EncodedJSON,
    InvalidImage,
    decode_tiff,
    dumps,
    encode_cube,
    encode_dark,
    encode_png,
    encode_raw,
    encode_tiff,
    normalise_cube,
    preview_file,
)
from m2s2hil.store.frame_meta import build_meta
from m2s2hil.store.journal import DuplicateEvent, Journal, JournalDamaged, JournalError
from m2s2hil.store.owner_lock import OwnerLock, SessionLocked, writer_active

__all__ = [
    "DarkRecord", "DiskFull", "DuplicateEvent", "FileRecord", "FrameRecord", "InvalidImage",
    "OutputNotWritable", "Problem", "ReadOnlySession", "SessionCorrupt", "SessionDamaged",
    "SessionExists", "SessionInfo", "SessionLocked", "SessionNotFound", "SessionStore", "SkipRecord",
    "StoreError",
    "check_free_space", "default_data_root", "estimate_frame_bytes", "estimate_session_bytes",
    "list_sessions", "software_version",
]

JOURNAL = "journal.sqlite"
SESSION_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,127}$")
STATES_DONE = ("completed", "failed", "aborted")


class StoreError(M2S2Error):
    """A session store problem that is not the user's input."""


class SessionNotFound(UsageError):
    def __init__(self, root: Path, session_id: str) -> None:
        super().__init__(f"no session {session_id!r} under {root}")


class SessionExists(UsageError):
    def __init__(self, path: Path) -> None:
        super().__init__(f"session folder {path} already exists")


class SessionCorrupt(StoreError):
    """A session folder whose journal is missing, unreadable or inconsistent."""


class SessionDamaged(SessionCorrupt):
    """The journal's database is damaged; ``sessions repair`` rebuilds it from the files."""

    def __init__(self, path: Path, detail: str) -> None:
        self.path = path
        self.detail = detail
        super().__init__(f"session {path.name}: journal damaged ({detail}); nothing was changed; "
                         f"rebuild it from the frame files with: m2s2hil sessions repair {path.name}"
                         f" --root {path.parent}")


class ReadOnlySession(UsageError):
    """A write through a session opened for reading."""

    def __init__(self, session_id: str, what: str) -> None:
        super().__init__(f"session {session_id} is open for reading; {what} needs "
                         "SessionStore.open(..., mode='write')")


class OutputNotWritable(UsageError):
    """The data root (or a session folder) cannot be written: read-only or no permission."""

    def __init__(self, path: Path, detail: str) -> None:
        self.path = path
        super().__init__(f"output folder {path} is not writable ({detail}); choose another with --out")


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


def _not_writable(exc: OSError) -> bool:
    return exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM)


def default_data_root() -> Path:
    """``$M2S2HIL_DATA`` if set, else ``./sessions``."""
    return Path(os.environ.get("M2S2HIL_DATA") or "sessions")


def software_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("m2s2hil")
    except PackageNotFoundError:
        return "unknown"


class _Rec(BaseModel):
    model_config = ConfigDict(frozen=True)


class FileRecord(_Rec):
    path: str  # relative to the session folder, POSIX separators
    sha256: str
    bytes: int


class FrameRecord(_Rec):
    event_id: str
    index: int
    time: float
    dark_id: str | None
    files: dict[str, FileRecord]  # role -> file: "raw", "cube", "preview"
    meta: dict[str, Any]


class DarkRecord(_Rec):
    dark_id: str
    exposure_s: float
    gain: float
    n_frames: int
    reduce: str
    time: float
    files: dict[str, FileRecord]  # "master"
    meta: dict[str, Any]


class SkipRecord(_Rec):
    event_id: str
    index: int
    time: float
    reason: str
    fault_class: str


@dataclass(frozen=True)
class Problem:
    path: str
    kind: str  # missing | size | checksum | orphan | journal
    detail: str

    def __str__(self) -> str:
        return f"{self.path}: {self.kind}: {self.detail}"


class SessionInfo(_Rec):
    session_id: str
    path: str
    state: str  # the journal's state; "damaged" when the journal cannot be trusted
    satellite: str | None = None
    build: str | None = None
    created: float | None = None
    updated: float | None = None
    frames: int = 0
    error: str | None = None


def _safe(event_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]", "_", event_id)


_RESERVED_ROLES = ("raw", "cube", "preview")


def _extra_file(name: str, role: str, arr: np.ndarray, meta: dict) -> tuple[str, bytes]:
    if role in _RESERVED_ROLES or not re.fullmatch(r"[a-z][a-z0-9_]{0,31}", role):
        raise UsageError(f"invalid extra file role {role!r}: lower-case letters, digits, '_'; "
                         f"not {', '.join(_RESERVED_ROLES)}")
    if not isinstance(arr, np.ndarray) or arr.ndim != 2:
        raise InvalidImage(f"extra {role!r} must be a 2-D array")
    if arr.dtype.kind in "ui" or arr.dtype == np.bool_:
        lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
        for dt in (np.uint8, np.uint16):
            if lo >= 0 and hi <= np.iinfo(dt).max:
                return f"frames/{name}.{role}.png", encode_png(arr.astype(dt))
    desc = {"role": role, "event_id": meta["event"]["event_id"]}
    return f"frames/{name}.{role}.tiff", encode_tiff(arr, desc)


def _raw_bytes(rig: RigConfig) -> int:
    """Upper estimate of a stored raw mosaic (or uint16 dark): uncompressed in the legacy
    format; deflate never needs much more than the sensor's bits per pixel (plus 5 %)."""
    m = rig.camera.model
    if rig.storage.format == "legacy":
        return m.width * m.height * 2
    return int(m.width * m.height * m.bit_depth / 8 * 1.05)


def estimate_frame_bytes(rig: RigConfig, processing: str = "superpixel") -> int:
    """Upper estimate of one frame's files: raw + float32 cube when stored (super-pixel size,
    or full size for the full-resolution methods) + uncompressed RGB preview + headers."""
    m = rig.camera.model
    small = (m.width // m.period) * (m.height // m.period)
    cube_px = small if processing == "superpixel" else m.width * m.height
    stored_cube = (rig.storage.format == "legacy" or rig.storage.cubes
                   or rig.camera.calibration_file is not None)
    return _raw_bytes(rig) + (m.n_bands * cube_px * 4 if stored_cube else 0) + small * 3 + 64 * 1024


def estimate_session_bytes(sweep: Sweep, rig: RigConfig) -> int:
    events = sweep.expand(rig)
    m = rig.camera.model
    frames = sum(e.kind == "frame" for e in events)
    darks = sum(e.kind == "dark" for e in events)
    dark_bytes = m.width * m.height * 4 if rig.storage.format == "legacy" else _raw_bytes(rig)
    return frames * estimate_frame_bytes(rig, sweep.processing) + darks * (dark_bytes + 65536)


def _new_session_id(sweep: Sweep, wall: float) -> str:
    ts = datetime.fromtimestamp(wall, UTC).strftime("%Y%m%dT%H%M%S")
    return f"{ts}-{sweep.satellite}-{sweep.build}-{'-'.join(sweep.lighting)}-{secrets.token_hex(2)}"


def _check_id(session_id: str) -> str:
    if not SESSION_ID_RE.match(session_id):
        raise UsageError(f"invalid session id {session_id!r}: letters, digits, '.', '_', '+', '-' only")
    return session_id


class SessionStore:
    """An open session. Create with :meth:`create`, reopen with :meth:`open`."""

    def __init__(self, path: Path, journal: Journal, sweep: Sweep, rig: RigConfig, *,
                 clock: Clock = SYSTEM_CLOCK, owner: OwnerLock | None = None) -> None:
        self.path = Path(path)
        self._owner = owner  # held while open for writing
        self.journal = journal
        self.sweep = sweep
        self.rig = rig
        self.clock = clock
        row = journal.session()
        self.session_id: str = row["session_id"]
        self.rig_digest: str = row["rig_digest"]
        self.software_version: str = row["software_version"]
        self.created: float = row["created"]
        self._inflight: set[str] = set()
        self._cubes: CubeComputer | None = None  # read_cube's processors

    # ------------------------------------------------------------ lifecycle
    @classmethod
    def create(cls, root: str | Path, sweep: Sweep, rig: RigConfig, *, session_id: str | None = None,
               clock: Clock = SYSTEM_CLOCK) -> SessionStore:
        """A new session folder, built under a hidden name and renamed into place."""
        root = Path(root)
        now = clock.wall()
        sid = _check_id(session_id) if session_id else _new_session_id(sweep, now)
        final = root / sid
        if final.exists():
            raise SessionExists(final)
        check_writable(root)
        try:
            root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            if _not_writable(exc):
                raise OutputNotWritable(root, exc.strerror or str(exc)) from None
            raise
        # Only the session's own small files must fit here: a short disk is the engine's to
        # report (it pauses, resumable), and a small mount is not "full" for a megabyte.
        check_free_space(root, 1024 * 1024, reserve_bytes=0)
        staging = root / f".{sid}.creating"
        shutil.rmtree(staging, ignore_errors=True)
        try:
            staging.mkdir()
        except OSError as exc:
            if _not_writable(exc):
                raise OutputNotWritable(root, exc.strerror or str(exc)) from None
            raise
        try:
            (staging / "frames").mkdir()
            (staging / "darks").mkdir()
            rig_json = dumps(rig.model_dump(mode="json"))
            j = Journal(staging / JOURNAL, create=True)
            try:
                j.init_session(
                    session_id=sid, satellite=sweep.satellite, build=sweep.build,
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
            if _not_writable(exc):
                raise OutputNotWritable(root, exc.strerror or str(exc)) from None
            raise
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return cls.open(root, sid, clock=clock, mode="write")

    @classmethod
    def open(cls, root: str | Path, session_id: str, *, clock: Clock = SYSTEM_CLOCK,
             mode: Literal["read", "write"] = "read") -> SessionStore:
        """Open a stored session.

        ``mode="read"`` (show, verify, list, export, reports): the journal read-only,
        nothing in the folder touched, every write refused (:class:`ReadOnlySession`).
        ``mode="write"`` (resume, repair, the daemon's job): take the owner lock
        (:class:`SessionLocked` if another writer has it), check the journal
        (:class:`SessionDamaged`, before anything is written), then remove the temporary
        files a crashed writer left."""
        if mode not in ("read", "write"):
            raise UsageError(f"session open mode must be 'read' or 'write', not {mode!r}")
        root = Path(root)
        path = root / _check_id(session_id)
        if not path.is_dir():
            raise SessionNotFound(root, session_id)
        if not (path / JOURNAL).is_file():
            raise SessionCorrupt(f"{path}: no {JOURNAL}; not a session folder or a damaged one")
        try:
            owner = OwnerLock.acquire(path) if mode == "write" else None
        except OSError as exc:  # the lock file cannot be made: an archived, read-only session
            if _not_writable(exc):
                raise OutputNotWritable(path, exc.strerror or str(exc)) from None
            raise
        try:
            store = cls._open_journal(path, session_id, clock, owner)
        except BaseException:
            if owner is not None:
                owner.release()
            raise
        if owner is not None:
            remove_temp_files(path)
        return store

    @classmethod
    def _open_journal(cls, path: Path, session_id: str, clock: Clock,
                      owner: OwnerLock | None) -> SessionStore:
        try:
            j = Journal(path / JOURNAL, read_only=owner is None)
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
        return cls(path, j, sweep, rig, clock=clock, owner=owner)

    @classmethod
    def open_path(cls, path: str | Path, *, clock: Clock = SYSTEM_CLOCK,
                  mode: Literal["read", "write"] = "read") -> SessionStore:
        p = Path(path)
        return cls.open(p.parent, p.name, clock=clock, mode=mode)

    @property
    def writable(self) -> bool:
        """Open for writing, holding the owner lock."""
        return self._owner is not None and self._owner.held

    def _require_writer(self, what: str) -> None:
        if not self.writable:
            raise ReadOnlySession(self.session_id, what)

    def release_ownership(self) -> None:
        """Give the owner lock back and stay open for reading (a daemon keeps serving a
        finished session's frames; another process may resume it from then on)."""
        if self._owner is None:
            return
        old, self.journal = self.journal, Journal(self.path / JOURNAL, read_only=True)
        old.close()
        self._owner.release()
        self._owner = None

    def close(self) -> None:
        self.journal.close()
        if self._owner is not None:
            self._owner.release()

    def __enter__(self) -> SessionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SessionStore({str(self.path)!r})"

    # ------------------------------------------------------------ state and log
    @property
    def state(self) -> str:
        return self.journal.session()["state"]

    def set_state(self, state: str) -> None:
        if not re.fullmatch(r"[a-z][a-z_-]{0,31}", state):
            raise UsageError(f"invalid session state {state!r}")
        self._require_writer("set_state")
        self.journal.set_state(state, self.clock.wall())

    def record_event(self, kind: str, payload: dict | None = None) -> int:
        """Append to the session's event log; returns its sequence number."""
        if not kind:
            raise UsageError("event kind must not be empty")
        self._require_writer("record_event")
        return self.journal.add_event(kind, payload or {}, self.clock.wall())

    def events(self, since: int = 0) -> list[dict]:
        return self.journal.events(since)

    def record_skip(self, event: CaptureEvent, reason: str, fault_class: str) -> None:
        self._require_writer("record_skip")
        self.journal.add_skip(event_id=event.event_id, idx=event.index, reason=reason,
                              fault_class=fault_class, now=self.clock.wall())

    # ------------------------------------------------------------ writes
    def _claim(self, event_id: str) -> None:
        self._require_writer(f"writing {event_id!r}")
        with self.journal._lock:
            if event_id in self._inflight or self.journal.is_completed(event_id):
                raise DuplicateEvent(event_id)
            self._inflight.add(event_id)

    def _release(self, event_id: str) -> None:
        with self.journal._lock:
            self._inflight.discard(event_id)

    def _meta(self, event: CaptureEvent, meta: dict | None, *, cube_stored: bool | None = None,
              **defaults: Any) -> tuple[dict[str, Any], EncodedJSON]:
        """The frame's (or dark's) metadata and its JSON text (m2s2hil.store.frame_meta)."""
        return build_meta(self, event, meta, cube_stored=cube_stored, **defaults)

    def _write(self, files: dict[str, tuple[str, bytes]]) -> dict[str, FileRecord]:
        total = sum(len(b) for _, b in files.values())
        check_free_space(self.path, total, reserve_bytes=DEFAULT_RESERVE_BYTES)
        written = write_files_atomic({self.path / rel: data for rel, data in files.values()})
        return {
            role: FileRecord(path=rel, sha256=written[self.path / rel].sha256,
                             bytes=written[self.path / rel].bytes)
            for role, (rel, _) in files.items()
        }

    def write_frame(self, event: CaptureEvent, raw: np.ndarray, cube: np.ndarray | None = None,
                    preview_rgb: np.ndarray | None = None, meta: dict | None = None, *,
                    extra: Mapping[str, np.ndarray] | None = None) -> FrameRecord:
        """Write a frame's files, then commit its journal row. DuplicateEvent if the event is
        already committed; DiskFull if the disk is full (nothing is committed then).

        ``cube``: the processing stage's cube of ``raw`` (shape checked); stored only when the
        rig caches cubes, in the legacy format, or for a calibrated frame
        (m2s2hil.store.cubes.cube_is_stored); otherwise :meth:`read_cube` recomputes it.
        ``extra``: more 2-D arrays stored with the frame under their role name (e.g.
        ``{"truth_labels": labels}`` → ``frames/<event>.truth_labels.png``), checksummed and
        committed with it: integer arrays that fit 8 or 16 bits as PNG, others as TIFF."""
        if event.kind != "frame":
            raise UsageError(f"write_frame got a {event.kind} event ({event.event_id}); use write_dark")
        m = self.rig.camera.model
        fmt = self.rig.storage.format
        if cube is not None:
            cube = normalise_cube(cube, m.n_bands)  # checked whether it is stored or not
        keep_cube = cube is not None and cube_is_stored(self.rig.storage, meta or {})
        self._claim(event.event_id)
        try:
            full, text = self._meta(event, meta, cube_stored=keep_cube)
            name = _safe(event.event_id)
            files: dict[str, tuple[str, bytes]] = {
                "raw": (f"frames/{name}.raw.tiff",
                        encode_raw(raw, text, (m.height, m.width), compress=fmt != "legacy")),
            }
            if keep_cube and cube is not None:
                desc = ({**full, "bands_nm": list(m.bands_nm), "dims": "band,y,x"} if fmt == "legacy" else
                        {"event_id": event.event_id, "cube": full["cube"], "bands_nm": list(m.bands_nm),
                         "dims": "band,y,x"})
                files["cube"] = (f"frames/{name}.cube.tiff",
                                 encode_cube(cube, desc, m.n_bands, compress=fmt != "legacy"))
            if preview_rgb is not None:
                files["preview"] = preview_file(name, preview_rgb, compress=fmt != "legacy")
            for role, arr in (extra or {}).items():
                files[role] = _extra_file(name, role, arr, full)
            recs = self._write(files)
            now = self.clock.wall()
            self.journal.add_frame(
                event_id=event.event_id, idx=event.index, dark_id=full.get("dark_id"),
                # the metadata's one encoding: the journal's dumps passes EncodedJSON through
                files={k: v.model_dump() for k, v in recs.items()}, meta=text, now=now,  # type: ignore[arg-type]
            )
        finally:
            self._release(event.event_id)
        return FrameRecord(event_id=event.event_id, index=event.index, time=now,
                           dark_id=full.get("dark_id"), files=recs, meta=full)

    def write_dark(self, event: CaptureEvent, master: np.ndarray, meta: dict | None = None) -> DarkRecord:
        """Store a master dark under ``event.event_id`` (its dark id). For a second dark at
        the same setting (e.g. after a temperature drift) pass an event with a new id."""
        if event.kind != "dark":
            raise UsageError(f"write_dark got a {event.kind} event ({event.event_id})")
        m = self.rig.camera.model
        self._claim(event.event_id)
        try:
            full, text = self._meta(event, {**(meta or {}), "dark_id": event.event_id},
                                    n_frames=event.n_frames, reduce=self.sweep.dark.reduce)
            data = encode_dark(master, full, (m.height, m.width),
                               compress=self.rig.storage.format != "legacy")
            recs = self._write({"master": (f"darks/{_safe(event.event_id)}.tiff", data)})
            now = self.clock.wall()
            self.journal.add_dark(
                dark_id=event.event_id, exposure_s=event.exposure_s, gain=event.gain,
                n_frames=int(full["n_frames"]), reduce=str(full["reduce"]),
                files={k: v.model_dump() for k, v in recs.items()}, meta=text, now=now,  # type: ignore[arg-type]
            )
        finally:
            self._release(event.event_id)
        return DarkRecord(dark_id=event.event_id, exposure_s=event.exposure_s, gain=event.gain,
                          n_frames=int(full["n_frames"]), reduce=str(full["reduce"]), time=now,
                          files=recs, meta=full)

    # ------------------------------------------------------------ reads
    def completed_event_ids(self) -> set[str]:
        """Ids of committed frames and darks: a resumed run skips these."""
        return self.journal.completed_ids()

    def skipped_event_ids(self) -> set[str]:
        """Events given up and not captured since."""
        done = self.completed_event_ids()
        return {r["event_id"] for r in self.journal.query("SELECT event_id FROM skips")} - done

    @staticmethod
    def _frame_record(r: Any) -> FrameRecord:
        return FrameRecord(event_id=r["event_id"], index=r["idx"], time=r["time"], dark_id=r["dark_id"],
                           files={k: FileRecord(**v) for k, v in json.loads(r["files"]).items()},
                           meta=json.loads(r["meta"]))

    def frames(self) -> list[FrameRecord]:
        return [self._frame_record(r) for r in self.journal.query("SELECT * FROM frames ORDER BY seq")]

    def frame(self, event_id: str) -> FrameRecord:
        rows = self.journal.query("SELECT * FROM frames WHERE event_id = ?", (event_id,))
        if not rows:
            raise UsageError(f"session {self.session_id} has no frame {event_id!r}")
        return self._frame_record(rows[0])

    def darks(self) -> list[DarkRecord]:
        return [
            DarkRecord(dark_id=r["dark_id"], exposure_s=r["exposure_s"], gain=r["gain"],
                       n_frames=r["n_frames"], reduce=r["reduce"], time=r["time"],
                       files={k: FileRecord(**v) for k, v in json.loads(r["files"]).items()},
                       meta=json.loads(r["meta"]))
            for r in self.journal.query("SELECT * FROM darks ORDER BY seq")
        ]

    def dark_for(self, exposure_s: float, gain: float) -> DarkRecord | None:
        """The latest master dark at this (exposure, gain), for reuse."""
        hits = [d for d in self.darks() if abs(d.exposure_s - exposure_s) < 5e-7 and d.gain == gain]
        return hits[-1] if hits else None

    def skips(self) -> list[SkipRecord]:
        return [SkipRecord(event_id=r["event_id"], index=r["idx"], time=r["time"], reason=r["reason"],
                           fault_class=r["fault_class"])
                for r in self.journal.query("SELECT * FROM skips ORDER BY seq")]

    def read_file(self, rec: FileRecord, *, check: bool = True) -> bytes:
        """A stored file's bytes; with ``check`` its sha256 must match the journal."""
        data = (self.path / rec.path).read_bytes()
        if check and hashlib.sha256(data).hexdigest() != rec.sha256:
            raise SessionCorrupt(f"{self.path / rec.path}: sha256 does not match the journal")
        return data

    def read_raw(self, event_id: str) -> tuple[np.ndarray, dict]:
        """The raw mosaic (uint16) and its metadata, in either storage format."""
        arr, desc = decode_tiff(self.read_file(self.frame(event_id).files["raw"]))
        return arr, desc

    def load_dark(self, dark_id: str) -> np.ndarray:
        """A master dark as stored: uint16 (compressed format) or float32 (legacy)."""
        for d in self.darks():
            if d.dark_id == dark_id:
                return decode_tiff(self.read_file(d.files["master"]))[0]
        raise UsageError(f"session {self.session_id} has no dark {dark_id!r}")

    def read_cube(self, event_id: str) -> np.ndarray:
        """The frame's cube (bands, H, W): the stored one, else computed from raw + dark with
        the recipe in its metadata (m2s2hil.store.cubes). Reading never writes."""
        if self._cubes is None:
            self._cubes = CubeComputer()
        return self._cubes.read(self, event_id)

    # ------------------------------------------------------------ integrity
    def _stored(self) -> list[tuple[str, dict[str, FileRecord]]]:
        """(event id, files) of every committed frame, then every dark."""
        frames = [(fr.event_id, fr.files) for fr in self.frames()]
        return frames + [(d.dark_id, d.files) for d in self.darks()]

    def _file_problem(self, rec: FileRecord, *, checksum: bool = True) -> Problem | None:
        p = self.path / rec.path
        if not p.is_file():
            return Problem(rec.path, "missing", "file listed in the journal is missing")
        size = p.stat().st_size
        if size != rec.bytes:
            return Problem(rec.path, "size", f"{size} bytes, journal says {rec.bytes}")
        if checksum:
            digest = sha256_file(p)
            if digest != rec.sha256:
                return Problem(rec.path, "checksum",
                               f"sha256 {digest[:12]}…, journal says {rec.sha256[:12]}…")
        return None

    def verify(self) -> list[Problem]:
        """Recompute every file's sha256 against the journal; also report files the
        journal does not know (orphans of an interrupted write) and journal damage.
        Temporary files of a live writer are its business and not reported."""
        problems: list[Problem] = []
        damage = self.journal.check()
        if damage is not None:
            problems.append(Problem(JOURNAL, "journal", damage))
        known: set[str] = set()
        for rec in (f for _, files in self._stored() for f in files.values()):
            known.add(rec.path)
            problem = self._file_problem(rec)
            if problem is not None:
                problems.append(problem)
        live = self.writable or writer_active(self.path)
        for folder in ("frames", "darks"):
            for p in sorted((self.path / folder).glob("*")):
                rel = p.relative_to(self.path).as_posix()
                if not p.is_file() or rel in known:
                    continue
                if TMP_MARK in p.name:
                    if not live:
                        problems.append(Problem(rel, "temporary", "left by an interrupted write; removed "
                                                                  "when the session is next resumed"))
                    continue
                problems.append(Problem(rel, "orphan", "file not in the journal (interrupted write)"))
        return problems

    def check_stored(self, *, checksum: bool = True) -> list[Problem]:
        """Before a resume trusts the journal: every committed frame's and dark's files
        must be there with their size and sha256. A capture whose files fail is moved
        aside (its files into ``quarantine/``, its journal row into a ``quarantined``
        event; nothing is deleted) so the run captures it again. Returns the problems."""
        self._require_writer("check_stored")
        out: list[Problem] = []
        for event_id, files in self._stored():
            probs = [pr for rec in files.values()
                     if (pr := self._file_problem(rec, checksum=checksum)) is not None]
            if not probs:
                continue
            stamp = datetime.fromtimestamp(self.clock.wall(), UTC).strftime("%Y%m%dT%H%M%S")
            aside = self.path / "quarantine" / f"{_safe(event_id)}-{stamp}-{secrets.token_hex(2)}"
            moved = []
            for rec in files.values():
                src = self.path / rec.path
                if src.is_file():
                    aside.mkdir(parents=True, exist_ok=True)
                    os.replace(src, aside / src.name)
                    moved.append((aside / src.name).relative_to(self.path).as_posix())
            if moved:
                fsync_dir(aside)
            self.journal.remove_record(event_id, now=self.clock.wall(),
                                       reason="; ".join(str(p) for p in probs) + (
                                           f"; kept in {aside.relative_to(self.path).as_posix()}"
                                           if moved else ""))
            out.extend(probs)
        return out

    def manifest(self, state: str | None = None) -> dict:
        """Write manifest.json (every file with its sha256) and return it. ``state``: the
        state to record in it (default: the current one)."""
        self._require_writer("manifest")
        row = self.journal.session()
        files = []
        for fr in self.frames():
            for role, rec in fr.files.items():
                files.append({"event_id": fr.event_id, "role": role, **rec.model_dump()})
        for d in self.darks():
            for role, rec in d.files.items():
                files.append({"event_id": d.dark_id, "role": f"dark-{role}", **rec.model_dump()})
        man = {
            "session_id": self.session_id,
            "satellite": self.sweep.satellite,
            "build": self.sweep.build,
            "state": state or row["state"],
            "created": row["created"],
            "written": self.clock.wall(),
            "software_version": self.software_version,
            "rig_digest": self.rig_digest,
            "sweep": self.sweep.model_dump(mode="json"),
            "files": files,
            "skips": [s.model_dump() for s in self.skips()],
        }
        write_text_atomic(self.path / "manifest.json", json.dumps(man, indent=2, sort_keys=True) + "\n")
        return man

    def complete(self, state: str = "completed") -> dict:
        """End of run: every committed file read back and checked against its sha256 (a file
        lost or damaged since it was written fails the run here, not in the dataset), the
        manifest, then the session's state (the very last step)."""
        self._require_writer("complete")
        lost = [pr for _, files in self._stored() for rec in files.values()
                if (pr := self._file_problem(rec)) is not None]
        if lost:
            raise StoreError(f"session {self.session_id}: {len(lost)} stored file(s) failed the final "
                             f"check ({lost[0]}); resume the session to capture them again")
        man = self.manifest(state)
        self.set_state(state)
        return man

    def summary(self) -> dict:
        row = self.journal.session()
        planned = self.sweep.expand(self.rig)
        planned_frames = {e.event_id for e in planned if e.kind == "frame"}
        planned_darks = {e.event_id for e in planned if e.kind == "dark"}
        done = self.completed_event_ids()
        frames = self.frames()
        total_bytes = sum(f.bytes for fr in frames for f in fr.files.values())
        total_bytes += sum(f.bytes for d in self.darks() for f in d.files.values())
        return {
            "session_id": self.session_id,
            "path": str(self.path),
            "satellite": self.sweep.satellite,
            "build": self.sweep.build,
            "state": row["state"],
            "created": row["created"],
            "updated": row["updated"],
            "planned_frames": len(planned_frames),
            "planned_darks": len(planned_darks),
            "frames": len(frames),
            "darks": len(done & planned_darks) + len({d.dark_id for d in self.darks()} - planned_darks),
            "frames_planned_stored": len(planned_frames & done),
            "skipped": len(self.skipped_event_ids()),
            "missing": len(planned_frames - done),
            "faults": self.journal.query("SELECT COUNT(*) AS n FROM events WHERE kind = 'fault'")[0]["n"],
            "bytes": total_bytes,
            "rig_digest": self.rig_digest,
            "software_version": self.software_version,
        }


def _created_from_id(session_id: str) -> float | None:
    """The creation time a generated id starts with (``20261124T214754-…``), for sorting."""
    try:
        return datetime.strptime(session_id[:15], "%Y%m%dT%H%M%S").replace(tzinfo=UTC).timestamp()
    except ValueError:
        return None


def list_sessions(root: str | Path) -> list[SessionInfo]:
    """Every session folder under ``root`` (newest first); a session whose journal cannot
    be read or fails ``quick_check`` is listed as ``damaged`` with the reason in ``error``,
    and the others are listed all the same. Read-only: nothing is changed."""
    root = Path(root)
    if not root.is_dir():
        return []
    out: list[SessionInfo] = []
    for p in root.iterdir():
        if not p.is_dir() or p.name.startswith(".") or not SESSION_ID_RE.match(p.name):
            continue
        if not (p / JOURNAL).is_file():
            continue
        try:
            j = Journal(p / JOURNAL, read_only=True)
            try:
                damage = j.check()
                if damage is not None:
                    raise JournalDamaged(damage)
                row = j.session()
                n = j.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
                out.append(SessionInfo(session_id=p.name, path=str(p), state=row["state"],
                                       satellite=row["satellite"], build=row["build"],
                                       created=row["created"], updated=row["updated"], frames=n))
            finally:
                j.close()
        except (JournalError, KeyError, sqlite3.Error) as exc:
            out.append(SessionInfo(session_id=p.name, path=str(p), state="damaged",
                                   created=_created_from_id(p.name), error=str(exc)))
    out.sort(key=lambda s: (s.created or 0.0, s.session_id), reverse=True)
    return out

