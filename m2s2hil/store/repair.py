"""Rebuild a damaged session journal from what the session folder itself holds.

Every raw frame TIFF carries the frame's whole metadata in its ImageDescription (the
session, the event with its index, the dark used, exposure, pose, provenance), every
master dark its own; ``sweep.json`` and ``rig.json`` are the plan and the rig the
session was created with, and ``manifest.json`` (when the session got that far) holds
every file's sha256 and the recorded skips. That is everything the journal's ``frames``,
``darks``, ``skips`` and ``session`` tables hold, so they can be rebuilt; the event log
before the damage cannot (the damaged journal is kept beside the new one).

A file is taken only when it decodes and, when the manifest lists it, its sha256
matches; anything else goes to ``quarantine/`` and its capture is left to a resume. The
new journal is built under a temporary name and renamed over the old one only when it
is complete, holding the session's owner lock throughout.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import tifffile

from m2s2hil.atomic import TMP_MARK, fsync_dir, remove_temp_files
from m2s2hil.config import parse_rig
from m2s2hil.errors import ConfigError, UsageError
from m2s2hil.plan import PlanError, parse_sweep
from m2s2hil.store.errors import SessionCorrupt, SessionNotFound
from m2s2hil.store.folder import software_version
from m2s2hil.store.frame_files import dumps
from m2s2hil.store.journal import Journal, JournalError
from m2s2hil.store.layout import JOURNAL, check_session_id
from m2s2hil.store.owner_lock import OwnerLock

_ROLE_RE = re.compile(r"^(?P<name>.+)\.(?P<role>[a-z][a-z0-9_]{0,31})\.(?:tiff|png|jpg)$")
# a file rewritten after capture (store/relabel: ``<frame>.<role>.<tag>.<ext>``, tag ``r<event>``)
_TAGGED_RE = re.compile(
    r"^(?P<name>.+)\.(?P<role>[a-z][a-z0-9_]{0,31})\.(?P<tag>[a-z0-9]{1,16})\.(?:tiff|png|jpg)$")
#: meta["qc"][role] of a frame whose rewritten file the repair kept: what the journal said is lost
RECOVERED = "recovered_by_repair"


def _tag_order(tag: str) -> tuple[int, str]:
    """Newest last: ``r<event>`` by its journal sequence number, other tags after them by name."""
    m = re.fullmatch(r"r(\d{1,15})", tag)
    return (int(m[1]), "") if m else (1 << 62, tag)


@dataclass
class RepairReport:
    session_id: str
    frames: int = 0
    darks: int = 0
    skips: int = 0
    quarantined: list[str] = field(default_factory=list)
    kept_journal: str = ""
    state: str = "paused"

    @staticmethod
    def kept_journal_name(stamp: str) -> str:
        return f"{JOURNAL}.damaged-{stamp}"

    def line(self) -> str:
        q = f", {len(self.quarantined)} damaged file(s) moved to quarantine/" if self.quarantined else ""
        return (f"session {self.session_id}: journal rebuilt from the files: {self.frames} frame(s), "
                f"{self.darks} dark(s), {self.skips} skip(s){q}; old journal kept as {self.kept_journal}; "
                f"state {self.state}")


def _recovered(meta: dict[str, Any], role: str, tag: str, kept_journal: str) -> dict[str, Any]:
    """``meta`` with ``qc[role]`` saying the file is a later rewrite (``tag``) whose provenance
    was in the journal (kept as ``kept_journal``); the capture-time record moves to
    ``qc[role + "_superseded"]``, as a rewrite leaves it (store/relabel)."""
    out = dict(meta)
    qc = dict(out.get("qc") or {})
    if isinstance(qc.get(role), dict):
        qc[f"{role}_superseded"] = qc[role]
    m = re.fullmatch(r"r(\d{1,15})", tag)
    qc[role] = {RECOVERED: True, "tag": tag, "registration": {"event": int(m[1]) if m else None},
                "provenance": f"in the damaged journal kept as {kept_journal}"}
    out["qc"] = qc
    return out


def _description(data: bytes) -> dict[str, Any] | None:
    """The JSON metadata of a TIFF that decodes completely; None if it does not."""
    try:
        with tifffile.TiffFile(io.BytesIO(data), is_shaped=False) as tf:
            arr = tf.asarray()
            desc = tf.pages[0].description
        meta = json.loads(desc)
    except Exception:  # a truncated or overwritten file: anything tifffile or json raise
        return None
    if not isinstance(meta, dict):
        return None
    if meta.get("shape") == list(arr.shape):
        del meta["shape"]
    return meta


def _image_ok(data: bytes) -> bool:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()
    except Exception:
        return False
    return True


def repair_session(root: str | Path, session_id: str, *, force: bool = False) -> RepairReport:
    """Rebuild ``<root>/<session_id>/journal.sqlite`` (see the module docstring). A sound
    journal is left alone (its event log is worth more) unless ``force``."""
    root = Path(root)
    path = root / check_session_id(session_id)
    if not path.is_dir():
        raise SessionNotFound(root, session_id)
    lock = OwnerLock.acquire(path)
    try:
        if not force and _sound(path / JOURNAL):
            raise UsageError(f"session {session_id}: the journal is sound, nothing to repair "
                             "(--force rebuilds it from the files anyway)")
        return _rebuild(path, session_id)
    finally:
        lock.release()


def _sound(journal: Path) -> bool:
    try:
        j = Journal(journal, read_only=True)
    except JournalError:
        return False
    try:
        return j.check() is None and bool(j.query("SELECT 1 FROM session WHERE id = 1"))
    except JournalError:
        return False
    finally:
        j.close()


def _rebuild(path: Path, session_id: str) -> RepairReport:
    try:
        sweep_doc = json.loads((path / "sweep.json").read_text())
        rig_doc = json.loads((path / "rig.json").read_text())
        sweep = parse_sweep(sweep_doc, f"{path}/sweep.json")
        rig = parse_rig(rig_doc, f"{path}/rig.json")
    except (OSError, json.JSONDecodeError, PlanError, ConfigError) as exc:
        raise SessionCorrupt(f"{path}: cannot rebuild the journal without sweep.json and rig.json: {exc}") \
            from None
    manifest: dict[str, Any] = {}
    with contextlib.suppress(OSError, json.JSONDecodeError):
        manifest = json.loads((path / "manifest.json").read_text())
    listed = {f["path"]: f["sha256"] for f in manifest.get("files", []) if "path" in f and "sha256" in f}
    remove_temp_files(path)  # we hold the lock: leftovers are a dead writer's
    report = RepairReport(session_id)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")

    def accept(p: Path, data: bytes) -> dict[str, Any] | None:
        rel = p.relative_to(path).as_posix()
        digest = hashlib.sha256(data).hexdigest()
        if rel in listed and listed[rel] != digest:
            return None
        return {"path": rel, "sha256": digest, "bytes": len(data)}

    def quarantine(p: Path) -> None:
        aside = path / "quarantine" / f"repair-{stamp}"
        aside.mkdir(parents=True, exist_ok=True)
        os.replace(p, aside / p.name)
        report.quarantined.append((aside / p.name).relative_to(path).as_posix())

    # Frames: group the files by name; the raw TIFF's metadata says which event it is. A label
    # map rewritten after capture (``sessions register``) carries a tag; the newest one stands
    # for its role (the rewrite removed the older after its journal switched to it).
    listing = [p for p in sorted((path / "frames").glob("*")) if p.is_file() and TMP_MARK not in p.name]
    raws = {p.name[: -len(".raw.tiff")] for p in listing if p.name.endswith(".raw.tiff")}
    groups: dict[str, dict[str, Path]] = {}
    rewritten: dict[str, dict[str, list[tuple[str, Path]]]] = {}
    for p in listing:
        m = _ROLE_RE.match(p.name)
        t = _TAGGED_RE.match(p.name)
        if m and m["name"] not in raws and t and t["name"] in raws:
            rewritten.setdefault(t["name"], {}).setdefault(t["role"], []).append((t["tag"], p))
        elif m:
            groups.setdefault(m["name"], {})[m["role"]] = p
    tags: dict[str, dict[str, str]] = {}  # frame name -> role -> tag of the rewritten file kept
    for name, roles in rewritten.items():
        for role, versions in roles.items():
            versions.sort(key=lambda v: _tag_order(v[0]))
            for _, older in versions[:-1]:
                groups.setdefault(f"{name}.{role}.older", {})["stale"] = older  # no raw: quarantined
            if role in groups.get(name, {}):  # the capture-time file an interrupted rewrite left
                groups.setdefault(f"{name}.{role}.capture", {})["stale"] = groups[name].pop(role)
            groups.setdefault(name, {})[role] = versions[-1][1]
            tags.setdefault(name, {})[role] = versions[-1][0]
    frames: list[tuple[int, str, float, str | None, dict, dict]] = []
    for _name, files in groups.items():
        raw = files.get("raw")
        meta = None
        recs: dict[str, dict] = {}
        if raw is not None:
            data = raw.read_bytes()
            meta = _description(data)
            rec = accept(raw, data) if meta is not None else None
            if rec is None or not isinstance(meta.get("event"), dict) or meta.get("session_id") != session_id:
                meta = None
            else:
                recs["raw"] = rec
        if meta is None:  # without a sound raw the frame is not stored: recapture it
            for p in files.values():
                quarantine(p)
            continue
        for role, p in files.items():
            if role == "raw":
                continue
            data = p.read_bytes()
            sound = _description(data) is not None if p.suffix == ".tiff" else _image_ok(data)
            rec = accept(p, data) if sound else None
            if rec is None:
                quarantine(p)
            else:
                recs[role] = rec
        for role, tag in tags.get(_name, {}).items():
            if role in recs:  # the raw's metadata describes the capture-time file: say what stands
                meta = _recovered(meta, role, tag, report.kept_journal_name(stamp))
        ev = meta["event"]
        when = float(meta.get("timestamp") or raw.stat().st_mtime)
        frames.append((int(ev["index"]), str(ev["event_id"]), when, meta.get("dark_id"), recs, meta))
    darks: list[tuple[float, str, dict, dict]] = []
    for p in sorted((path / "darks").glob("*.tiff")):
        if TMP_MARK in p.name:
            continue
        data = p.read_bytes()
        meta = _description(data)
        rec = accept(p, data) if meta is not None else None
        if rec is None or "dark_id" not in meta:
            quarantine(p)
            continue
        darks.append((p.stat().st_mtime, str(meta["dark_id"]), {"master": rec}, meta))

    # The new journal, complete under a temporary name, then renamed into place.
    tmp = path / f".{JOURNAL}{TMP_MARK}repair"
    for suffix in ("", "-wal", "-shm"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(f"{tmp}{suffix}")
    created = manifest.get("created")
    if created is None:
        created = min([t for _, _, t, *_ in frames] + [t for t, *_ in darks] + [path.stat().st_mtime])
    planned_frames = {e.event_id for e in sweep.expand(rig) if e.kind == "frame"}
    stored = {eid for _, eid, *_ in frames}
    complete = manifest.get("state") in ("completed", "completed_with_gaps") and planned_frames <= stored
    report.state = str(manifest["state"]) if complete else "paused"
    now = datetime.now(UTC).timestamp()
    j = Journal(tmp, create=True)
    try:
        j.init_session(session_id=session_id, satellite=sweep.satellite, build=sweep.build,
                       sweep_json=sweep.model_dump_json(), rig_json=dumps(rig.model_dump(mode="json")),
                       rig_digest=manifest.get("rig_digest") or rig.digest,
                       software_version=manifest.get("software_version") or software_version(),
                       state=report.state, now=float(created))
        for t, dark_id, files, meta in sorted(darks):
            j.add_dark(dark_id=dark_id, exposure_s=float(meta.get("exposure_s", 0.0)),
                       gain=float(meta.get("gain", 0.0)), n_frames=int(meta.get("n_frames", 0)),
                       reduce=str(meta.get("reduce", "")), files=files, meta=meta, now=t)
            report.darks += 1
        for idx, event_id, t, dark_id, files, meta in sorted(frames):
            j.add_frame(event_id=event_id, idx=idx, dark_id=dark_id, files=files, meta=meta, now=t)
            report.frames += 1
        for s in manifest.get("skips", []):
            if s.get("event_id") not in stored:
                j.add_skip(event_id=s["event_id"], idx=int(s["index"]), reason=str(s["reason"]),
                           fault_class=str(s["fault_class"]), now=float(s["time"]))
                report.skips += 1
        report.kept_journal = report.kept_journal_name(stamp)
        j.add_event("repaired", {"frames": report.frames, "darks": report.darks, "skips": report.skips,
                                 "quarantined": report.quarantined, "old_journal": report.kept_journal,
                                 "from_manifest": bool(manifest)}, now)
        if j.check() is not None:
            raise SessionCorrupt(f"{path}: the rebuilt journal fails its own check")
    finally:
        j.close()
    # Keep the damaged journal (and its WAL) beside the new one; nothing is deleted.
    for suffix in ("-wal", "-shm", ""):
        src = path / f"{JOURNAL}{suffix}"
        if src.exists():
            os.replace(src, path / f"{report.kept_journal}{suffix}")
    os.replace(tmp, path / JOURNAL)
    fsync_dir(path)
    return report
