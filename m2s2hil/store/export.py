"""Export a session in the published M2S2 layout, as a Hugging Face dataset (Parquet with the exact
raw values, m2s2hil.store.export_hf) or as a Zarr store (m2s2hil.store.zarr_export).

``layout="m2s2"`` writes, under ``out``:

- ``HIL/<Satellite>/b<N>/e<N>/<all|dir|solo>_<k>.png``: the raw mosaic as an 8-bit PNG
  with three identical channels, exactly like the release. 10 → 8 bits is
  ``raw >> (bit_depth - 8)`` (for the TOUCAN: ``>> 2``, i.e. floor(DN / 4); nothing is
  rounded up, so 1023 → 255 and the mapping never overflows).
- ``HIL16/<same path>``: the same mosaic losslessly, a 16-bit single-channel PNG holding
  the sensor's DN unchanged (0..1023 for 10 bits; not rescaled).
- ``HILbracket/<Satellite>/b<N>/e<N>/<light>_<k>_x<factor>.png``: a bracketed sweep's extra
  exposures of pose ``k`` (``Sweep.bracket``), 16-bit like ``HIL16``. They stay out of ``HIL/``,
  whose names the release fixes to one image per pose; the CSV has a row for each, with its
  ``exposure_factor`` (1 for the pose's own frame) and exposure.
- ``metadata/<session_id>.csv``: one row per image (pose commanded and read back,
  exposure, gain, lighting, temperature, dark id, sha256 of the raw TIFF, ...).
- ``metadata/<session_id>.json``: what the release lacks: band centres, FWHM, the 4×4
  mosaic layout (band index per position, 0-based), bit depth, the 8-bit mapping, the
  sweep, rig digest, software version, and the master darks (``metadata/<session_id>/``).
- ``HILmasks/<same path>``: the simulator's truth label map of a frame captured on the
  simulated rig (8-bit PNG, label i = ``class_names[i]`` of the JSON, 0 = background), and
  ``HILlabels/<same path>``: the twin's projected labels (role ``projected_labels``) where
  the frame has them; the CSV names them (``mask_file``, ``labels_file``).
- A synthetic session (``m2s2hil synth``) goes beside it, by the same satellite/build/
  elevation/``k`` path: ``Synthetic/<Satellite>/b<N>/e<N>/rgb_<k>.png`` (the RGB render),
  ``band<BB>_<k>.png`` (the render lit with band BB's colour, 01..10 as the paper numbers
  bands) and ``mask_<k>.png`` (the material mask), ``e3`` for the synthetic-only elevation.
- ``metadata/pairs.csv``: every synthetic view with the HIL frames of the same pose
  (satellite, build, elevation, nominal azimuth), one row per (view, HIL frame), rebuilt
  from every session CSV under ``out`` after each export, so the order of exports does not
  matter.

``k`` is the capture index within its folder: the azimuth index (0..35 for 10° steps,
azimuth = start + k·step), plus ``n_azimuths · f`` for the f-th extra frame at a pose
(so with one frame per pose k is exactly the azimuth index). The paper does not define
the index (its 3,024 HIL images do not factor into 36 azimuths × 81 folders), so the
CSV carries the azimuth explicitly.

``layout="hf"`` writes a ``datasets`` dataset (Parquet) whose ``raw`` column holds the
exact 10-bit values as a uint16 array, with bands, FWHM and mosaic layout in every row
(m2s2hil.store.export_hf); ``datasets.load_dataset(out, split="train")`` loads it;
exporting more sessions into the same folder merges them.

``layout="zarr"`` writes (or appends to) a Zarr store ``out`` that xarray opens lazily: raw
frames chunked per frame with labelled coordinates (m2s2hil.store.zarr_export).

Existing files are never overwritten unless ``overwrite=True`` (checked before anything
is written). Every file is written atomically. Exporting only reads the session: nothing
is recorded in it, so an archived read-only session exports.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from m2s2hil.atomic import write_bytes_atomic, write_text_atomic
from m2s2hil.catalog import load_catalog
from m2s2hil.errors import UsageError
from m2s2hil.store.frame_files import encode_png
from m2s2hil.store.records import FrameRecord
from m2s2hil.store.session import SessionStore

Layout = Literal["m2s2", "hf", "zarr"]
LAYOUTS = ("m2s2", "hf", "zarr")

CSV_COLUMNS = (
    "session_id", "event_id", "satellite", "build", "elevation", "lighting", "lighting_dataset", "k",
    "azimuth_index", "frame", "nominal_azimuth_deg", "azimuth_deg", "turntable_readback_deg", "tilt_deg",
    "tilt_readback_deg", "exposure_s", "gain", "temperature_c", "dark_id", "timestamp", "bit_depth",
    "processing_method", "raw_sha256", "domain", "mask_file", "labels_file", "exposure_factor",
)
SYNTH_COLUMNS = (
    "file", "mask_file", "band_files", "session_id", "event_id", "domain", "satellite", "build", "elevation",
    "k", "azimuth_index", "nominal_azimuth_deg", "azimuth_deg", "tilt_deg", "light", "exposure", "mockup",
)
PAIR_COLUMNS = (
    "satellite", "build", "elevation", "nominal_azimuth_deg", "synthetic_file", "synthetic_mask_file",
    "hil_file", "hil_mask_file", "hil_labels_file", "lighting", "synthetic_session_id", "hil_session_id",
)
MASK_ROLE, LABELS_ROLE = "truth_labels", "projected_labels"  # a frame's label files (extra roles)
LABEL_FOLDERS = ((MASK_ROLE, "HILmasks", "mask_file"), (LABELS_ROLE, "HILlabels", "labels_file"))


#: ``progress(done, total)``: frames written so far of the export's frames.
ProgressFn = Callable[[int, int], None]


class Progress:
    """Counts an export's frames and passes ``(done, total)`` on to ``fn`` at most every
    ``every_s`` seconds (a follower polls at about 1 Hz: more calls would only cost time), and
    always for the first and the last frame."""

    def __init__(self, fn: ProgressFn | None, total: int, every_s: float = 0.5) -> None:
        self.fn, self.total, self.every_s = fn, total, every_s
        self.done = 0
        self._last = -float("inf")

    def step(self, n: int = 1) -> None:
        self.done = min(self.total, self.done + n)
        if self.fn is None:
            return
        now = time.monotonic()
        if self.done in (1, self.total) or now - self._last >= self.every_s:
            self._last = now
            self.fn(self.done, self.total)


class ExportError(UsageError):
    """An export that cannot be done (unknown layout, a file in the way, ...)."""


@dataclass
class ExportResult:
    layout: str
    out: Path
    images: int = 0
    files: list[Path] = field(default_factory=list)


def to_8bit(raw: np.ndarray, bit_depth: int) -> np.ndarray:
    """The release's mapping: drop the low bits (``>> (bit_depth - 8)``)."""
    shift = bit_depth - 8
    if shift < 0:
        raise ExportError(f"cannot map {bit_depth}-bit data to 8 bits by a shift")
    return (raw >> shift).astype(np.uint8) if shift else raw.astype(np.uint8)


def mosaic_png8(raw: np.ndarray, bit_depth: int) -> np.ndarray:
    g = to_8bit(raw, bit_depth)
    return np.dstack([g, g, g])


def _k(ev: dict, n_az: int) -> int:
    return int(ev["azimuth_index"]) + n_az * int(ev["frame"])


def _pose(meta: dict, key: str) -> Any:
    pose = meta.get("pose")
    return pose.get(key, "") if isinstance(pose, dict) else ""


def _row(store: SessionStore, fr: FrameRecord, n_az: int) -> dict[str, Any]:
    cat = load_catalog()
    ev = fr.meta["event"]
    m = fr.meta
    return {
        "session_id": store.session_id,
        "event_id": fr.event_id,
        "satellite": cat.satellites[store.sweep.satellite].name,
        "build": store.sweep.build,
        "elevation": ev["elevation"],
        "lighting": ev["lighting"],
        "lighting_dataset": cat.lighting[ev["lighting"]].dataset,
        "k": _k(ev, n_az),
        "azimuth_index": ev["azimuth_index"],
        "frame": ev["frame"],
        "nominal_azimuth_deg": ev["nominal_azimuth_deg"],
        "azimuth_deg": ev["azimuth_deg"],
        "turntable_readback_deg": _pose(m, "turntable_deg"),
        "tilt_deg": ev["tilt_deg"],
        "tilt_readback_deg": _pose(m, "tilt_deg"),
        "exposure_s": m.get("exposure_s", ev["exposure_s"]),
        "gain": m.get("gain", ev["gain"]),
        "temperature_c": m.get("temperature_c", ""),
        "dark_id": fr.dark_id or "",
        "timestamp": m.get("timestamp", fr.time),
        "bit_depth": m.get("bit_depth", store.rig.camera.model.bit_depth),
        "processing_method": m.get("processing_method", store.sweep.processing),
        "raw_sha256": fr.files["raw"].sha256,
        "domain": "hil",
        "exposure_factor": float(ev.get("exposure_factor", 1.0)),  # absent before brackets: 1
    }


def _synthetic_row(store: SessionStore, fr: FrameRecord, n_az: int) -> dict[str, Any]:
    cat = load_catalog()
    ev, m = fr.meta["event"], fr.meta
    syn = m.get("synthetic", {})
    return {
        "session_id": store.session_id, "event_id": fr.event_id, "domain": "synthetic",
        "satellite": cat.satellites[store.sweep.satellite].name, "build": store.sweep.build,
        "elevation": ev["elevation"], "k": _k(ev, n_az), "azimuth_index": ev["azimuth_index"],
        "nominal_azimuth_deg": ev["nominal_azimuth_deg"], "azimuth_deg": ev["azimuth_deg"],
        "tilt_deg": ev["tilt_deg"], "light": syn.get("light", ""), "exposure": syn.get("exposure", ""),
        "mockup": syn.get("mockup", ""),
    }


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def write_pairs(out: Path) -> Path | None:
    """``metadata/pairs.csv`` from every session CSV under ``out`` (module docstring); None
    when ``out`` holds no synthetic view."""
    syn: dict[tuple, list[dict]] = {}
    hil: dict[tuple, list[dict]] = {}
    for p in sorted((out / "metadata").glob("*.csv")):
        if p.name == "pairs.csv":
            continue
        for r in _read_csv(p):
            try:
                az = round(float(r["nominal_azimuth_deg"])) % 360
                key = (r["satellite"], r["build"], r["elevation"], az)
            except (KeyError, ValueError):
                continue
            if r.get("domain") != "synthetic" and float(r.get("exposure_factor") or 1.0) != 1.0:
                continue  # a bracket's extra exposure pairs through its pose's own frame
            (syn if r.get("domain") == "synthetic" else hil).setdefault(key, []).append(r)
    if not syn:
        return None
    rows = []
    for key in sorted(syn):
        for s in syn[key]:
            for h in hil.get(key, [{}]):  # a view without its HIL frame keeps a row (empty HIL side)
                rows.append({
                    "satellite": key[0], "build": key[1], "elevation": key[2], "nominal_azimuth_deg": key[3],
                    "synthetic_file": s["file"], "synthetic_mask_file": s["mask_file"],
                    "hil_file": h.get("file", ""), "hil_mask_file": h.get("mask_file", ""),
                    "hil_labels_file": h.get("labels_file", ""), "lighting": h.get("lighting", ""),
                    "synthetic_session_id": s["session_id"], "hil_session_id": h.get("session_id", ""),
                })
    target = out / "metadata" / "pairs.csv"
    write_text_atomic(target, _csv(rows, PAIR_COLUMNS))
    return target


def _csv(rows: list[dict], columns: tuple[str, ...]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: r.get(c, "") for c in columns})
    return buf.getvalue()


def camera_metadata(store: SessionStore) -> dict[str, Any]:
    m = store.rig.camera.model
    return {
        "camera": m.name,
        "width": m.width,
        "height": m.height,
        "bit_depth": m.bit_depth,
        "pixel_pitch_um": m.pixel_pitch_um,
        "bands_nm": list(m.bands_nm),
        "fwhm_nm": list(m.fwhm_nm),
        "mosaic_layout": [list(r) for r in m.layout],
        "mosaic_layout_note": "band index (0-based into bands_nm) at each position of the repeating "
                              f"{m.period}x{m.period} cell, row-major from the top-left pixel",
        "png8_mapping": f"value8 = raw >> {m.bit_depth - 8} (floor); three identical channels",
        "png16_mapping": "value16 = raw DN unchanged",
    }


def _session_json(store: SessionStore) -> dict[str, Any]:
    cat = load_catalog()
    return {
        "session_id": store.session_id,
        "satellite": cat.satellites[store.sweep.satellite].name,
        "build": store.sweep.build,
        "state": store.state,
        "software_version": store.software_version,
        "rig_digest": store.rig_digest,
        **camera_metadata(store),
        "lighting": {k: {"dataset": v.dataset, "description": v.description,
                         "lamps": list(store.rig.lighting.get(k, ()))}
                     for k, v in cat.lighting.items()},
        "elevations_deg": dict(store.rig.elevations),
        "sweep": store.sweep.model_dump(mode="json"),
        "darks": [{"dark_id": d.dark_id, "exposure_s": d.exposure_s, "gain": d.gain,
                   "n_frames": d.n_frames, "reduce": d.reduce, "sha256": d.files["master"].sha256,
                   "file": f"{store.session_id}/{Path(d.files['master'].path).name}"}
                  for d in store.darks()],
        "skips": [s.model_dump() for s in store.skips()],
    }


def _refuse_clash(planned: list[Path], overwrite: bool) -> None:
    """Checked before anything is written: no existing file is replaced unless ``overwrite``."""
    clash = [] if overwrite else [p for p in planned if p.exists()]
    if clash:
        raise ExportError(f"{clash[0]} already exists ({len(clash)} file(s) in the way); "
                          "use overwrite to replace them")


def export_session(store: SessionStore, out: str | Path, layout: str = "m2s2", *,
                   overwrite: bool = False, progress: ProgressFn | None = None) -> ExportResult:
    """Export every committed frame of ``store`` (see the module docstring); ``progress(done,
    total)`` is told of the frames written (:class:`Progress`: at most every 0.5 s)."""
    if layout not in LAYOUTS:
        raise ExportError(f"unknown export layout {layout!r}; known: {', '.join(LAYOUTS)}")
    out = Path(out)
    frames = store.frames()
    if not frames:
        raise ExportError(f"session {store.session_id} has no frames to export")
    prog = Progress(progress, len(frames))
    if store.kind == "synthetic":
        n_az = len(store.sweep.azimuths())
        if layout != "m2s2":
            from m2s2hil.store.export_synthetic import export_synthetic

            return export_synthetic(store, out, layout, frames, overwrite=overwrite, progress=prog)
        return _export_synthetic_m2s2(store, out, frames, n_az, overwrite=overwrite, progress=prog)
    if layout == "zarr":
        from m2s2hil.store.zarr_export import ZarrExportError, export_zarr

        try:
            n = export_zarr(store, out, progress=prog)
        except ZarrExportError as exc:
            raise ExportError(str(exc)) from None
        return ExportResult(layout=layout, out=out, images=n, files=[out])
    cat = load_catalog()
    sat_name = cat.satellites[store.sweep.satellite].name
    b = f"b{int(store.sweep.build[1:])}"
    n_az = len(store.sweep.azimuths())
    bits = store.rig.camera.model.bit_depth
    rows = [_row(store, fr, n_az) for fr in frames]

    def rel_name(r: dict) -> str:
        factor = r["exposure_factor"]
        tail = "" if factor == 1.0 else f"_x{factor:g}"
        return f"{r['lighting_dataset']}_{r['k']}{tail}.png"

    meta_json = out / "metadata" / f"{store.session_id}.json"
    dark_dir = out / "metadata" / store.session_id
    darks = [(d, dark_dir / Path(d.files["master"].path).name) for d in store.darks()]
    result = ExportResult(layout=layout, out=out)
    if layout == "hf":
        _refuse_clash([meta_json, *(t for _, t in darks)], overwrite)
        from m2s2hil.store.export_hf import HfExportError, export_hf

        try:
            result.files += export_hf(store, out, frames, rows, overwrite=overwrite, progress=prog)
        except HfExportError as exc:
            raise ExportError(str(exc)) from None
        result.images = len(frames)
    else:
        targets: list[tuple[Path | None, Path]] = []  # (8-bit, 16-bit PNG); a bracket member: 16-bit only
        labels: list[tuple[FrameRecord, str, Path]] = []  # (frame, role, target): masks, projected labels
        for fr, r in zip(frames, rows, strict=True):
            sub = Path(sat_name) / b / f"e{int(r['elevation'][1:])}" / rel_name(r)
            if r["exposure_factor"] != 1.0:  # a bracket member: 16-bit only, beside the release's folders
                targets.append((None, out / "HILbracket" / sub))
                r["file"] = r["file16"] = f"HILbracket/{sub.as_posix()}"
            else:
                targets.append((out / "HIL" / sub, out / "HIL16" / sub))
                r["file"] = f"HIL/{sub.as_posix()}"
                r["file16"] = f"HIL16/{sub.as_posix()}"
            for role, folder, col in LABEL_FOLDERS:
                if role in fr.files:
                    labels.append((fr, role, out / folder / sub))
                    r[col] = f"{folder}/{sub.as_posix()}"
        meta_csv = out / "metadata" / f"{store.session_id}.csv"
        planned = [p for t in targets for p in t if p is not None]
        _refuse_clash(planned + [t for _, _, t in labels] + [meta_csv, meta_json] + [t for _, t in darks],
                      overwrite)
        for fr, (p8, p16) in zip(frames, targets, strict=True):
            raw, _ = store.read_raw(fr.event_id)
            if p8 is not None:
                write_bytes_atomic(p8, encode_png(mosaic_png8(raw, bits)))
                result.files.append(p8)
            write_bytes_atomic(p16, encode_png(raw.astype(np.uint16)))
            result.files.append(p16)
            result.images += 1
            prog.step()
        for fr, role, target in labels:  # stored as 8-bit PNG already: copied as they are, checked
            write_bytes_atomic(target, store.read_file(fr.files[role]))
            result.files.append(target)
        write_text_atomic(meta_csv, _csv(rows, ("file", "file16", *CSV_COLUMNS)))
        result.files.append(meta_csv)
        pairs = write_pairs(out)
        if pairs is not None:
            result.files.append(pairs)

    info = _session_json(store)
    for d, dst in darks:
        write_bytes_atomic(dst, store.read_file(d.files["master"]))
        result.files.append(dst)
    write_text_atomic(meta_json, json.dumps(info, indent=2, sort_keys=True) + "\n")
    result.files.append(meta_json)
    return result


def _export_synthetic_m2s2(store: SessionStore, out: Path, frames: list[FrameRecord], n_az: int, *,
                           overwrite: bool, progress: Progress | None = None) -> ExportResult:
    """A synthetic session's views beside the HIL folders (module docstring)."""
    cat = load_catalog()
    base = Path("Synthetic") / cat.satellites[store.sweep.satellite].name / f"b{int(store.sweep.build[1:])}"
    rows = [_synthetic_row(store, fr, n_az) for fr in frames]
    copies: list[tuple[FrameRecord, str, Path]] = []
    for fr, r in zip(frames, rows, strict=True):
        folder = base / f"e{int(r['elevation'][1:])}"
        bands = sorted(role for role in fr.files if role.startswith("band_"))
        if "rgb" not in fr.files or MASK_ROLE not in fr.files or not bands:
            raise ExportError(f"synthetic frame {fr.event_id} of {store.session_id} lacks its rgb, bands "
                              "or mask")
        names = [("rgb", f"rgb_{r['k']}.png"), (MASK_ROLE, f"mask_{r['k']}.png")]
        names += [(role, f"band{int(role[5:]) + 1:02d}_{r['k']}.png") for role in bands]
        for role, name in names:
            copies.append((fr, role, out / folder / name))
        r["file"] = (folder / names[0][1]).as_posix()
        r["mask_file"] = (folder / names[1][1]).as_posix()
        r["band_files"] = " ".join((folder / n).as_posix() for _, n in names[2:])
    meta_csv = out / "metadata" / f"{store.session_id}.csv"
    meta_json = out / "metadata" / f"{store.session_id}.json"
    _refuse_clash([t for _, _, t in copies] + [meta_csv, meta_json], overwrite)
    result = ExportResult(layout="m2s2", out=out, images=len(frames))
    for fr, role, target in copies:  # PNGs as stored (checksums checked on read)
        write_bytes_atomic(target, store.read_file(fr.files[role]))
        result.files.append(target)
        if role == "rgb" and progress is not None:  # one rgb per view: a view done
            progress.step()
    write_text_atomic(meta_csv, _csv(rows, SYNTH_COLUMNS))
    info = {**_session_json(store), "domain": "synthetic",
            "class_names": frames[0].meta.get("class_names", []),
            "synthetic": {k: v for k, v in frames[0].meta.get("synthetic", {}).items() if k != "exposure"},
            "elevations_deg": {r["elevation"]: r["tilt_deg"] for r in rows}}
    write_text_atomic(meta_json, json.dumps(info, indent=2, sort_keys=True) + "\n")
    result.files += [meta_csv, meta_json]
    pairs = write_pairs(out)
    if pairs is not None:
        result.files.append(pairs)
    return result
