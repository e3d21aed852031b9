"""The session store: one folder per session under a data root (layout: m2s2hil.store.layout).

:class:`SessionStore` is an open session: made (:meth:`~SessionStore.create`) or opened
(:meth:`~SessionStore.open`), written frame by frame and dark by dark, read back. Around it:
the folder made and opened (m2s2hil.store.folder), the journal (m2s2hil.store.journal), the
records it returns (m2s2hil.store.records), its errors (m2s2hil.store.errors), the checks of
its files (m2s2hil.store.integrity), the sessions of a data root (m2s2hil.store.catalogue)
and the size estimates of a plan (m2s2hil.store.estimates).

Ownership: a session is open either for reading (``SessionStore.open``, the default:
the journal opened read-only, nothing in the folder changed, writes refused) or for
writing (``mode="write"``, and :meth:`SessionStore.create`): the writer holds the
session's owner lock (m2s2hil.store.owner_lock) for as long as it is open, checks the
journal (``PRAGMA quick_check``) before anything is written, and only then removes the
temporary files a crashed writer left. ``check_stored`` (resume) verifies every stored
file and moves a missing or damaged frame aside so it is captured again.

Integrity: every file goes to a temporary name in its folder, is fsynced, renamed, and
the folder fsynced (m2s2hil.atomic); its sha256 goes into the journal. The frame's
journal row is committed LAST, so a crash leaves at worst files without a row (a resumed
run overwrites them) and never a row without its files. An event id is written once:
writing it again raises ``DuplicateEvent``.

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

import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from m2s2hil.atomic import DEFAULT_RESERVE_BYTES, check_free_space, remove_temp_files, write_files_atomic
from m2s2hil.config import RigConfig
from m2s2hil.drivers.clock import SYSTEM_CLOCK, Clock
from m2s2hil.errors import UsageError
from m2s2hil.plan import CaptureEvent, Sweep
from m2s2hil.store import catalogue, integrity
from m2s2hil.store.cubes import CubeComputer, cube_is_stored
from m2s2hil.store.errors import (
    OutputNotWritable,
    ReadOnlySession,
    SessionCorrupt,
    SessionExists,
    SessionNotFound,
)
from m2s2hil.store.folder import create_folder, not_writable, open_journal
from m2s2hil.store.frame_files import (
    EncodedJSON,
    decode_tiff,
    encode_cube,
    encode_dark,
    encode_raw,
    extra_file,
    normalise_cube,
    preview_file,
)
from m2s2hil.store.frame_meta import build_meta
from m2s2hil.store.journal import DuplicateEvent, Journal
from m2s2hil.store.layout import JOURNAL, check_session_id, new_session_id, safe_name
from m2s2hil.store.owner_lock import OwnerLock
from m2s2hil.store.records import (
    DarkRecord,
    FileRecord,
    FrameRecord,
    Problem,
    SkipRecord,
    dark_record,
    frame_record,
    skip_record,
)

SessionKind = Literal["hil", "synthetic"]
KIND_EVENT = "session_kind"  # the event that marks a session's kind (absent: "hil")


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
               clock: Clock = SYSTEM_CLOCK, kind: SessionKind = "hil") -> SessionStore:
        """A new session folder (m2s2hil.store.folder.create_folder), open for writing.
        ``kind="synthetic"``: the twin's renders (m2s2hil.twin.synth), marked by the log's
        first event (``session_kind``), so every reader of the journal keeps working."""
        root = Path(root)
        now = clock.wall()
        sid = check_session_id(session_id) if session_id else new_session_id(sweep, now)
        if (root / sid).exists():
            raise SessionExists(root / sid)
        create_folder(root, sid, sweep, rig, now=now)
        store = cls.open(root, sid, clock=clock, mode="write")
        if kind != "hil":
            store.record_event(KIND_EVENT, {"kind": kind})
        return store

    @property
    def kind(self) -> SessionKind:
        """``"hil"`` (captured on the rig, simulated or real) or ``"synthetic"`` (rendered)."""
        rows = self.journal.query("SELECT payload FROM events WHERE kind = ? ORDER BY seq LIMIT 1",
                                  (KIND_EVENT,))
        return json.loads(rows[0]["payload"]).get("kind", "hil") if rows else "hil"

    @classmethod
    def open(cls, root: str | Path, session_id: str, *, clock: Clock = SYSTEM_CLOCK,
             mode: Literal["read", "write"] = "read") -> SessionStore:
        """Open a stored session.

        ``mode="read"`` (show, verify, list, export, reports): the journal read-only,
        nothing in the folder touched, every write refused (:class:`ReadOnlySession`).
        ``mode="write"`` (resume, repair, the daemon's job): take the owner lock
        (``SessionLocked`` if another writer has it), check the journal
        (``SessionDamaged``, before anything is written), then remove the temporary
        files a crashed writer left."""
        if mode not in ("read", "write"):
            raise UsageError(f"session open mode must be 'read' or 'write', not {mode!r}")
        root = Path(root)
        path = root / check_session_id(session_id)
        if not path.is_dir():
            raise SessionNotFound(root, session_id)
        if not (path / JOURNAL).is_file():
            raise SessionCorrupt(f"{path}: no {JOURNAL}; not a session folder or a damaged one")
        try:
            owner = OwnerLock.acquire(path) if mode == "write" else None
        except OSError as exc:  # the lock file cannot be made: an archived, read-only session
            if not_writable(exc):
                raise OutputNotWritable(path, exc.strerror or str(exc)) from None
            raise
        try:
            journal, sweep, rig = open_journal(path, session_id, read_only=owner is None)
            store = cls(path, journal, sweep, rig, clock=clock, owner=owner)
        except BaseException:
            if owner is not None:
                owner.release()
            raise
        if owner is not None:
            remove_temp_files(path)
        return store

    @classmethod
    def open_path(cls, path: str | Path, *, clock: Clock = SYSTEM_CLOCK,
                  mode: Literal["read", "write"] = "read") -> SessionStore:
        p = Path(path)
        return cls.open(p.parent, p.name, clock=clock, mode=mode)

    @property
    def writable(self) -> bool:
        """Open for writing, holding the owner lock."""
        return self._owner is not None and self._owner.held

    def require_writer(self, what: str) -> None:
        """:class:`ReadOnlySession` unless open for writing (``what``: the refused write)."""
        if not self.writable:
            raise ReadOnlySession(self.session_id, what)

    def release_ownership(self) -> None:
        """Give the owner lock back and stay open for reading (a daemon keeps serving a
        finished session's frames; another process may resume it from then on)."""
        if self._owner is None:
            return
        self.journal.reopen_read_only()
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
        self.require_writer("set_state")
        self.journal.set_state(state, self.clock.wall())

    def record_event(self, kind: str, payload: dict | None = None) -> int:
        """Append to the session's event log; returns its sequence number."""
        if not kind:
            raise UsageError("event kind must not be empty")
        self.require_writer("record_event")
        return self.journal.add_event(kind, payload or {}, self.clock.wall())

    def events(self, since: int = 0) -> list[dict]:
        return self.journal.events(since)

    def record_skip(self, event: CaptureEvent, reason: str, fault_class: str) -> None:
        self.require_writer("record_skip")
        self.journal.add_skip(event_id=event.event_id, idx=event.index, reason=reason,
                              fault_class=fault_class, now=self.clock.wall())

    # ------------------------------------------------------------ writes
    def _claim(self, event_id: str) -> None:
        self.require_writer(f"writing {event_id!r}")
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

    def write_frame(self, event: CaptureEvent, raw: np.ndarray | None, cube: np.ndarray | None = None,
                    preview_rgb: np.ndarray | None = None, meta: dict | None = None, *,
                    extra: Mapping[str, np.ndarray] | None = None) -> FrameRecord:
        """Write a frame's files, then commit its journal row. DuplicateEvent if the event is
        already committed; DiskFull if the disk is full (nothing is committed then).

        ``cube``: the processing stage's cube of ``raw`` (shape checked); stored only when the
        rig caches cubes, in the legacy format, or for a calibrated frame
        (m2s2hil.store.cubes.cube_is_stored); otherwise :meth:`read_cube` recomputes it.
        ``extra``: more 2-D arrays stored with the frame under their role name (e.g.
        ``{"truth_labels": labels}`` → ``frames/<event>.truth_labels.png``), checksummed and
        committed with it: integer arrays that fit 8 or 16 bits as PNG, others as TIFF.
        ``raw=None`` only in a synthetic session: a render has no mosaic, its images are extras."""
        if raw is None and self.kind != "synthetic":
            raise UsageError(f"frame {event.event_id}: a raw mosaic is required in a {self.kind} session")
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
            name = safe_name(event.event_id)
            files: dict[str, tuple[str, bytes]] = {} if raw is None else {
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
                files[role] = extra_file(name, role, arr, event.event_id)
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
            recs = self._write({"master": (f"darks/{safe_name(event.event_id)}.tiff", data)})
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

    def frames(self) -> list[FrameRecord]:
        return [frame_record(r) for r in self.journal.query("SELECT * FROM frames ORDER BY seq")]

    def frame(self, event_id: str) -> FrameRecord:
        rows = self.journal.query("SELECT * FROM frames WHERE event_id = ?", (event_id,))
        if not rows:
            raise UsageError(f"session {self.session_id} has no frame {event_id!r}")
        return frame_record(rows[0])

    def darks(self) -> list[DarkRecord]:
        return [dark_record(r) for r in self.journal.query("SELECT * FROM darks ORDER BY seq")]

    def dark_for(self, exposure_s: float, gain: float) -> DarkRecord | None:
        """The latest master dark at this (exposure, gain), for reuse."""
        hits = [d for d in self.darks() if abs(d.exposure_s - exposure_s) < 5e-7 and d.gain == gain]
        return hits[-1] if hits else None

    def skips(self) -> list[SkipRecord]:
        return [skip_record(r) for r in self.journal.query("SELECT * FROM skips ORDER BY seq")]

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

    # ------------------------------------------------------------ integrity (m2s2hil.store.integrity)
    def verify(self) -> list[Problem]:
        """Every file checked against the journal, orphans and journal damage reported."""
        return integrity.verify(self)

    def check_stored(self, *, checksum: bool = True) -> list[Problem]:
        """Before a resume: a capture whose files fail is moved aside, to be captured again."""
        return integrity.check_stored(self, checksum=checksum)

    def manifest(self, state: str | None = None) -> dict[str, Any]:
        """Write manifest.json (every file with its sha256) and return it."""
        return integrity.write_manifest(self, state)

    def complete(self, state: str = "completed") -> dict[str, Any]:
        """End of run: every file read back and checked, the manifest, then the state."""
        return integrity.complete(self, state)

    def summary(self) -> dict[str, Any]:
        """The session's counts against its plan (m2s2hil.store.catalogue.summary)."""
        return catalogue.summary(self)
