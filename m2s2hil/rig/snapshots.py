"""Test frames taken outside sessions: ``<data root>/snapshots/<id>/``.

A snapshot is what an operator takes while setting a rig up (is the mockup centred, is any
material saturated, is the focus right): the raw mosaic as a 16-bit TIFF that plain tifffile
reads, its metadata (exposure, gain, sensor temperature, the axes' read-back, lamps on, the rig
file's digest) in the TIFF and beside it as JSON, and a white-balanced false-colour PNG. Files
are written atomically; a snapshot never touches a session.
"""

from __future__ import annotations

import json
import re
import secrets
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from m2s2hil.atomic import write_files_atomic
from m2s2hil.drivers.interfaces import Frame
from m2s2hil.errors import UsageError
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.display import false_colour
from m2s2hil.rig.opened import AXIS_ROLES, Rig
from m2s2hil.store.frame_files import dumps, encode_png, encode_raw

SNAPSHOT_ID = re.compile(r"^[0-9]{8}T[0-9]{6}-[0-9a-f]{6}$")
FILES = {"raw.tiff": "image/tiff", "preview.png": "image/png", "meta.json": "application/json"}


class SnapshotNotFound(UsageError):
    pass


def snapshot_root(data_root: Path) -> Path:
    return Path(data_root) / "snapshots"


def frame_metadata(rig: Rig, frame: Frame, note: str = "") -> dict[str, Any]:
    cfg = rig.config
    meta: dict[str, Any] = {
        "kind": "snapshot",
        "taken_at": datetime.now(UTC).isoformat(timespec="milliseconds"),
        "exposure_s": float(frame.exposure_s), "gain": float(frame.gain),
        "temperature_c": float(frame.temperature_c), "block_id": int(frame.block_id),
        "pixel_format": frame.pixel_format, "camera": cfg.camera.model.name,
        "bands_nm": list(cfg.camera.model.bands_nm), "rig": cfg.rig.name, "rig_digest": cfg.digest,
        "note": note,
    }
    for role in AXIS_ROLES:
        try:
            meta[f"{role}_deg"] = float(rig.axis(role).position())
        except Exception as exc:  # the frame is still worth keeping
            meta[f"{role}_deg"] = None
            meta[f"{role}_error"] = f"{type(exc).__name__}: {exc}"
    try:
        on = rig.lights.state()
        meta["lamps_on"] = sorted(n for n, lc in cfg.lamps.items() if lc.channel in on)
    except Exception as exc:
        meta["lamps_on"] = None
        meta["lamps_error"] = f"{type(exc).__name__}: {exc}"
    return meta


def save_snapshot(data_root: Path, rig: Rig, frame: Frame, note: str = "") -> dict[str, Any]:
    """Write the snapshot's three files; returns its metadata with its ``id``."""
    meta = frame_metadata(rig, frame, note)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    sid = f"{stamp}-{secrets.token_hex(3)}"
    meta["id"] = sid
    folder = snapshot_root(data_root) / sid
    folder.mkdir(parents=True, exist_ok=False)
    model = rig.config.camera.model
    cube = get_demosaicer("superpixel", model, frame.data.shape).process(frame.data)
    write_files_atomic({
        folder / "raw.tiff": encode_raw(frame.data, meta),
        folder / "preview.png": encode_png(false_colour(cube, model.bands_nm)),
        folder / "meta.json": dumps(meta).encode(),
    })
    return meta


def _folder(data_root: Path, sid: str) -> Path:
    if not SNAPSHOT_ID.match(sid):
        raise SnapshotNotFound(f"no snapshot {sid!r}")
    folder = snapshot_root(data_root) / sid
    if not (folder / "meta.json").is_file():
        raise SnapshotNotFound(f"no snapshot {sid!r}")
    return folder


def snapshot_meta(data_root: Path, sid: str) -> dict[str, Any]:
    return json.loads((_folder(data_root, sid) / "meta.json").read_text())


def snapshot_file(data_root: Path, sid: str, name: str) -> Path:
    if name not in FILES:
        raise SnapshotNotFound(f"a snapshot has no file {name!r}; files: {', '.join(FILES)}")
    return _folder(data_root, sid) / name


def list_snapshots(data_root: Path, limit: int = 50) -> list[dict[str, Any]]:
    root = snapshot_root(data_root)
    if not root.is_dir():
        return []
    out = []
    for d in sorted((p for p in root.iterdir() if SNAPSHOT_ID.match(p.name)), reverse=True)[:limit]:
        try:
            out.append(json.loads((d / "meta.json").read_text()))
        except (OSError, ValueError):
            continue  # a damaged snapshot is skipped, never fatal to the listing
    return out
