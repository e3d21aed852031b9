"""The session store: one folder per session under a data root.

Layout of ``<root>/<session_id>/``::

    journal.sqlite            the journal (see m2s2hil.store.journal); the source of truth
    sweep.json, rig.json      human-readable copies of the plan and the rig
    frames/<event>.raw.tiff   raw mosaic, uint16, metadata JSON in ImageDescription
    frames/<event>.cube.tiff  processed cube (bands, H, W), float32 or uint16
    frames/<event>.preview.png
    darks/<dark>.tiff         master darks, float32
    manifest.json             every file with its sha256, written at completion

``<event>`` is the event id with ``/`` replaced by ``_`` (``weak_E0_az010_f0``).

Integrity: every file goes to a temporary name in its folder, is fsynced, renamed, and
the folder fsynced (m2s2hil.store.atomic); its sha256 goes into the journal. The frame's
journal row is committed LAST, so a crash leaves at worst files without a row (a resumed
run overwrites them) and never a row without its files. An event id is written once:
writing it again raises :class:`DuplicateEvent`.

Frame metadata (``write_frame(..., meta=)``): a free dict merged over what the store
knows (event, session, software version, rig digest, dark id, processing method).
Recommended keys, used by export: ``exposure_s``, ``gain``, ``temperature_c``,
``pose`` = {``turntable_deg``, ``tilt_deg``} (read-back), ``lamps_on`` (channels),
``timestamp`` (wall seconds), ``device_timestamp_s``, ``block_id``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from m2s2hil.config import RigConfig, parse_rig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import ConfigError, M2S2Error, UsageError
from m2s2hil.plan import CaptureEvent, PlanError, Sweep, parse_sweep
from m2s2hil.store.atomic import (
    DEFAULT_RESERVE_BYTES,
    DiskFull,
    check_free_space,
    fsync_dir,
    is_no_space,
    remove_temp_files,
    sha256_file,
    write_files_atomic,
    write_text_atomic,
)
from m2s2hil.store.frame_files import (
    InvalidImage,
    decode_tiff,
    dumps,
    encode_cube,
    encode_dark,
    encode_png,
    encode_raw,
    encode_tiff,
)
from m2s2hil.store.journal import DuplicateEvent, Journal, JournalError

__all__ = [
    "DarkRecord", "DiskFull", "DuplicateEvent", "FileRecord", "FrameRecord", "InvalidImage", "Problem",
    "SessionCorrupt",
    "SessionExists", "SessionInfo", "SessionNotFound", "SessionStore", "SkipRecord", "StoreError",
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
    state: str
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


def estimate_frame_bytes(rig: RigConfig, processing: str = "superpixel") -> int:
    """Upper estimate of one frame's files: raw uint16 + float32 cube (super-pixel size, or
    full size for the full-resolution methods) + uncompressed RGB preview + headers."""
    m = rig.camera.model
    small = (m.width // m.period) * (m.height // m.period)
    cube_px = small if processing == "superpixel" else m.width * m.height
    return m.width * m.height * 2 + m.n_bands * cube_px * 4 + small * 3 + 64 * 1024


def estimate_session_bytes(sweep: Sweep, rig: RigConfig) -> int:
    events = sweep.expand(rig)
    m = rig.camera.model
    frames = sum(e.kind == "frame" for e in events)
    darks = sum(e.kind == "dark" for e in events)
    return frames * estimate_frame_bytes(rig, sweep.processing) + darks * (m.width * m.height * 4 + 65536)


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
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.path = Path(path)
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
        root.mkdir(parents=True, exist_ok=True)
        check_free_space(root, 1024 * 1024)
        staging = root / f".{sid}.creating"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
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
            raise
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return cls.open(root, sid, clock=clock)

    @classmethod
    def open(cls, root: str | Path, session_id: str, *, clock: Clock = SYSTEM_CLOCK) -> SessionStore:
        """Reopen a session (e.g. to resume it). Leftover temporary files are removed."""
        root = Path(root)
        path = root / _check_id(session_id)
        if not path.is_dir():
            raise SessionNotFound(root, session_id)
        if not (path / JOURNAL).is_file():
            raise SessionCorrupt(f"{path}: no {JOURNAL}; not a session folder or a damaged one")
        try:
            j = Journal(path / JOURNAL)
        except JournalError as exc:
            raise SessionCorrupt(str(exc)) from None
        try:
            row = j.session()
            sweep = parse_sweep(json.loads(row["sweep_json"]), f"{path}: sweep")
            rig = parse_rig(json.loads(row["rig_json"]), f"{path}: rig")
        except (JournalError, PlanError, ConfigError, json.JSONDecodeError) as exc:
            j.close()
            raise SessionCorrupt(f"{path}: journal content unusable: {exc}") from None
        if row["session_id"] != session_id:
            j.close()
            raise SessionCorrupt(f"{path}: journal belongs to session {row['session_id']!r}")
        remove_temp_files(path)
        return cls(path, j, sweep, rig, clock=clock)

    @classmethod
    def open_path(cls, path: str | Path, *, clock: Clock = SYSTEM_CLOCK) -> SessionStore:
        p = Path(path)
        return cls.open(p.parent, p.name, clock=clock)

    def close(self) -> None:
        self.journal.close()

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
        self.journal.set_state(state, self.clock.wall())

    def record_event(self, kind: str, payload: dict | None = None) -> int:
        """Append to the session's event log; returns its sequence number."""
        if not kind:
            raise UsageError("event kind must not be empty")
        return self.journal.add_event(kind, payload or {}, self.clock.wall())

    def events(self, since: int = 0) -> list[dict]:
        return self.journal.events(since)

    def record_skip(self, event: CaptureEvent, reason: str, fault_class: str) -> None:
        self.journal.add_skip(event_id=event.event_id, idx=event.index, reason=reason,
                              fault_class=fault_class, now=self.clock.wall())

    # ------------------------------------------------------------ writes
    def _claim(self, event_id: str) -> None:
        with self.journal._lock:
            if event_id in self._inflight or self.journal.is_completed(event_id):
                raise DuplicateEvent(event_id)
            self._inflight.add(event_id)

    def _release(self, event_id: str) -> None:
        with self.journal._lock:
            self._inflight.discard(event_id)

    def _meta(self, event: CaptureEvent, meta: dict | None, **extra: Any) -> dict[str, Any]:
        """What the store knows, overlaid by the caller's ``meta`` (actual exposure, dark
        used, ...); provenance keys the store owns cannot be overridden."""
        defaults = {
            "exposure_s": event.exposure_s,
            "gain": event.gain,
            "dark_id": event.dark_id,
            "processing_method": self.sweep.processing,
            "bit_depth": self.rig.camera.model.bit_depth,
            **extra,
        }
        owned = {
            "session_id": self.session_id,
            "satellite": self.sweep.satellite,
            "build": self.sweep.build,
            "event": event.model_dump(mode="json"),
            "software_version": self.software_version,
            "rig_digest": self.rig_digest,
        }
        return {**defaults, **(meta or {}), **owned}

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

        ``extra``: more 2-D arrays stored with the frame under their role name (e.g.
        ``{"truth_labels": labels}`` → ``frames/<event>.truth_labels.png``), checksummed and
        committed with it: integer arrays that fit 8 or 16 bits as PNG, others as TIFF."""
        if event.kind != "frame":
            raise UsageError(f"write_frame got a {event.kind} event ({event.event_id}); use write_dark")
        m = self.rig.camera.model
        self._claim(event.event_id)
        try:
            full = self._meta(event, meta)
            name = _safe(event.event_id)
            files: dict[str, tuple[str, bytes]] = {
                "raw": (f"frames/{name}.raw.tiff", encode_raw(raw, full, (m.height, m.width))),
            }
            if cube is not None:
                files["cube"] = (f"frames/{name}.cube.tiff",
                                 encode_cube(cube, {**full, "bands_nm": list(m.bands_nm),
                                                    "dims": "band,y,x"}, m.n_bands))
            if preview_rgb is not None:
                files["preview"] = (f"frames/{name}.preview.png", encode_png(preview_rgb))
            for role, arr in (extra or {}).items():
                files[role] = _extra_file(name, role, arr, full)
            recs = self._write(files)
            now = self.clock.wall()
            self.journal.add_frame(
                event_id=event.event_id, idx=event.index, dark_id=full.get("dark_id"),
                files={k: v.model_dump() for k, v in recs.items()}, meta=full, now=now,
            )
        finally:
            self._release(event.event_id)
        return FrameRecord(event_id=event.event_id, index=event.index, time=now,
                           dark_id=full.get("dark_id"), files=recs, meta=json.loads(dumps(full)))

    def write_dark(self, event: CaptureEvent, master: np.ndarray, meta: dict | None = None) -> DarkRecord:
        """Store a master dark under ``event.event_id`` (its dark id). For a second dark at
        the same setting (e.g. after a temperature drift) pass an event with a new id."""
        if event.kind != "dark":
            raise UsageError(f"write_dark got a {event.kind} event ({event.event_id})")
        m = self.rig.camera.model
        self._claim(event.event_id)
        try:
            full = self._meta(event, meta, n_frames=event.n_frames, reduce=self.sweep.dark.reduce)
            full["dark_id"] = event.event_id
            data = encode_dark(master, full, (m.height, m.width))
            recs = self._write({"master": (f"darks/{_safe(event.event_id)}.tiff", data)})
            now = self.clock.wall()
            self.journal.add_dark(
                dark_id=event.event_id, exposure_s=event.exposure_s, gain=event.gain,
                n_frames=int(full["n_frames"]), reduce=str(full["reduce"]),
                files={k: v.model_dump() for k, v in recs.items()}, meta=full, now=now,
            )
        finally:
            self._release(event.event_id)
        return DarkRecord(dark_id=event.event_id, exposure_s=event.exposure_s, gain=event.gain,
                          n_frames=int(full["n_frames"]), reduce=str(full["reduce"]), time=now,
                          files=recs, meta=json.loads(dumps(full)))

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
        arr, desc = decode_tiff(self.read_file(self.frame(event_id).files["raw"]))
        return arr, desc

    def load_dark(self, dark_id: str) -> np.ndarray:
        for d in self.darks():
            if d.dark_id == dark_id:
                return decode_tiff(self.read_file(d.files["master"]))[0]
        raise UsageError(f"session {self.session_id} has no dark {dark_id!r}")

    # ------------------------------------------------------------ integrity
    def verify(self) -> list[Problem]:
        """Recompute every file's sha256 against the journal; also report files the
        journal does not know (orphans of an interrupted write) and journal damage."""
        problems: list[Problem] = []
        ok = self.journal.pragma("integrity_check")
        if ok != "ok":
            problems.append(Problem(JOURNAL, "journal", str(ok)))
        known: set[str] = set()
        recs = [f for fr in self.frames() for f in fr.files.values()]
        recs += [f for d in self.darks() for f in d.files.values()]
        for rec in recs:
            known.add(rec.path)
            p = self.path / rec.path
            if not p.is_file():
                problems.append(Problem(rec.path, "missing", "file listed in the journal is missing"))
                continue
            size = p.stat().st_size
            if size != rec.bytes:
                problems.append(Problem(rec.path, "size", f"{size} bytes, journal says {rec.bytes}"))
                continue
            digest = sha256_file(p)
            if digest != rec.sha256:
                problems.append(Problem(rec.path, "checksum", f"sha256 {digest[:12]}…, journal says "
                                                               f"{rec.sha256[:12]}…"))
        for folder in ("frames", "darks"):
            for p in sorted((self.path / folder).glob("*")):
                rel = p.relative_to(self.path).as_posix()
                if p.is_file() and rel not in known:
                    problems.append(Problem(rel, "orphan", "file not in the journal (interrupted write)"))
        return problems

    def manifest(self, state: str | None = None) -> dict:
        """Write manifest.json (every file with its sha256) and return it. ``state``: the
        state to record in it (default: the current one)."""
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
        """End of run: write the manifest, then mark the session (the very last step)."""
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
            "skipped": len(self.skipped_event_ids()),
            "missing": len(planned_frames - done),
            "bytes": total_bytes,
            "rig_digest": self.rig_digest,
            "software_version": self.software_version,
        }


def list_sessions(root: str | Path) -> list[SessionInfo]:
    """Every session folder under ``root`` (newest first); unreadable ones carry ``error``."""
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
            j = Journal(p / JOURNAL)
            try:
                row = j.session()
                n = j.query("SELECT COUNT(*) AS n FROM frames")[0]["n"]
                out.append(SessionInfo(session_id=p.name, path=str(p), state=row["state"],
                                       satellite=row["satellite"], build=row["build"],
                                       created=row["created"], updated=row["updated"], frames=n))
            finally:
                j.close()
        except (JournalError, KeyError) as exc:
            out.append(SessionInfo(session_id=p.name, path=str(p), state="corrupt", error=str(exc)))
    out.sort(key=lambda s: (s.created or 0.0, s.session_id), reverse=True)
    return out

