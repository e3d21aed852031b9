"""The metadata sidecars of an exported folder, read back on import.

``m2s2hil export --layout m2s2`` writes ``metadata/<session>.csv`` (one row per image, keyed
by its ``file``, ``HIL/...``), ``metadata/<session>.json`` (camera model, sweep, darks) and
the master darks under ``metadata/<session>/``. Released data without them imports as
before (nominal poses, unknown exposure).
"""

from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from m2s2hil.errors import UsageError


class SidecarError(UsageError):
    """A metadata sidecar that cannot be read; ``path`` names the file."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


@dataclass(frozen=True)
class Sidecar:
    """What the export recorded about one image."""

    row: dict[str, str]  # its CSV row
    session: dict[str, Any]  # its session's JSON ({} if missing)
    folder: Path  # the metadata folder (dark files are relative to it)


def read_sidecars(root: Path) -> dict[str, Sidecar]:
    """Sidecar of every image the CSVs under ``root/metadata`` name, by ``HIL/...`` path."""
    meta_dir = root / "metadata"
    out: dict[str, Sidecar] = {}
    if not meta_dir.is_dir():
        return out
    for csv_path in sorted(meta_dir.glob("*.csv")):
        json_path = csv_path.with_suffix(".json")
        try:
            info = json.loads(json_path.read_text(encoding="utf-8")) if json_path.is_file() else {}
            with csv_path.open(newline="", encoding="utf-8") as f:
                rows = list(csv.DictReader(f))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, csv.Error) as exc:
            raise SidecarError(csv_path, f"unreadable metadata sidecar: {exc}") from None
        if not isinstance(info, dict):
            raise SidecarError(json_path, "expected a JSON object")
        for r in rows:
            if r.get("file"):
                out[r["file"]] = Sidecar(r, info, meta_dir)
    return out


def _num(v: str | None) -> float | None:
    if v is None or v == "":
        return None
    try:
        return float(v)
    except ValueError:
        return None


def frame_meta(side: Sidecar) -> dict[str, Any]:
    """The frame's capture metadata as exported (exposure, gain, temperature, dark, pose
    read-backs, timestamp) plus where it came from."""
    r = side.row
    pose = {"turntable_deg": _num(r.get("turntable_readback_deg")),
            "tilt_deg": _num(r.get("tilt_readback_deg"))}
    meta: dict[str, Any] = {
        "exposure_s": _num(r.get("exposure_s")),
        "gain": _num(r.get("gain")),
        "temperature_c": _num(r.get("temperature_c")),
        "dark_id": r.get("dark_id") or None,
        "timestamp": _num(r.get("timestamp")),
        "exposure_known": _num(r.get("exposure_s")) is not None,
        "source_session": r.get("session_id"),
        "source_event_id": r.get("event_id"),
    }
    if any(v is not None for v in pose.values()):
        meta["pose"] = pose
        meta["pose_source"] = "read-back, from the export's metadata"
    return meta


def bit_depth(side: Sidecar | None) -> int | None:
    if side is None:
        return None
    v = _num(side.row.get("bit_depth")) or _num(str(side.session.get("bit_depth", "")))
    return int(v) if v else None


def camera_fields(side: Sidecar) -> dict[str, Any]:
    """Camera-model fields the session JSON holds (bands, FWHM, layout, name, pixel pitch)."""
    s = side.session
    out: dict[str, Any] = {}
    for key, field in (("camera", "name"), ("bands_nm", "bands_nm"), ("fwhm_nm", "fwhm_nm"),
                       ("mosaic_layout", "layout"), ("pixel_pitch_um", "pixel_pitch_um")):
        if key in s:
            out[field] = s[key]
    return out


def darks(side: Sidecar) -> list[tuple[dict[str, Any], Path]]:
    """(dark entry of the session JSON, its file) for every master dark the export copied;
    the file's sha256 must be the one recorded."""
    out = []
    for d in side.session.get("darks", []) or []:
        path = side.folder / str(d.get("file", ""))
        if not d.get("file") or not path.is_file():
            continue
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if d.get("sha256") and digest != d["sha256"]:
            raise SidecarError(path, "sha256 does not match the session's metadata")
        out.append((d, path))
    return out
