"""The console's pictures (docs/console.md, "Pictures"): the spectrum at a point or region of a
stored frame or of the live view, a frame's ten band images side by side, a sweep's coverage
map, and calibration results as images.

They only read: a stored frame through the session's journal (files checked against their
sha256), the live view's newest frame as it is held in memory (no camera request), the dark
library and the calibration file. Coordinates are sensor pixels (0-based, x to the right, y
down); a region is widened to whole mosaic cells (m2s2hil/processing/spectrum.py).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from fastapi import APIRouter, Query, Response
from pydantic import BaseModel

from m2s2hil.daemon.errors import Conflict, UnknownSession
from m2s2hil.processing.calibration import load_calibration
from m2s2hil.processing.display import srgb_encode
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.spectrum import dark_subtracted, reflectance, snap_region
from m2s2hil.store.frame_files import decode_tiff
from m2s2hil.store.records import FrameRecord
from m2s2hil.store.session import SessionStore

from ..common import CONFLICT, NOT_FOUND, FrameN, Manager, SessionId
from .state import ConsoleDep

router = APIRouter(tags=["console pictures"])

Coord = Annotated[int, Query(ge=0, le=65535, description="Sensor pixel (0-based).")]
Size = Annotated[int, Query(ge=1, le=65536, description="Region size in sensor pixels (default: one cell).")]
PNG = {200: {"content": {"image/png": {}}, "description": "PNG image."}}


class SpectrumOut(BaseModel):
    source: str
    region: dict[str, int]
    sensor: list[int]
    bands_nm: list[float]
    dn: list[float]
    dark: str | None
    reflectance: list[float | None] | None
    white_reference: dict[str, Any] | None
    exposure_s: float
    gain: float
    lighting: str | None
    notes: list[str]


def _layout(model: Any, calib: Any) -> MosaicLayout:
    if calib is not None and calib.layout is not None:
        return MosaicLayout.from_pattern(calib.layout)
    return MosaicLayout.from_camera(model)


@functools.lru_cache(maxsize=2)
def _white(path: str, mtime_ns: int, model_json: str) -> tuple[Any, dict[str, Any]]:
    """The calibration file and its white reference's provenance, read once per version."""
    from m2s2hil.config import CameraModel

    model = CameraModel.model_validate_json(model_json)
    calib = load_calibration(path, model)
    doc = json.loads(Path(path).read_text())
    return calib, dict((doc.get("white_reference") or {}).get("provenance") or {})


def _calibration(console: Any) -> tuple[Any, dict[str, Any]] | tuple[None, None]:
    path = console.calibration_path
    if not path.is_file():
        return None, None
    try:
        model = console.manager.rig.config.camera.model
        return _white(str(path), path.stat().st_mtime_ns, model.model_dump_json())
    except Exception:  # a damaged file: the spectrum still has its DN (the calibration view says why)
        return None, None


def _spectrum(raw: np.ndarray, dark: np.ndarray | None, dark_label: str | None, *, source: str,
              x: int, y: int, w: int, h: int, exposure_s: float, gain: float, lighting: str | None,
              console: Any, notes: list[str]) -> dict[str, Any]:
    model = console.manager.rig.config.camera.model
    calib, prov = _calibration(console)
    layout = _layout(model, calib)
    sensor = (int(raw.shape[1]), int(raw.shape[0]))
    region = snap_region(x, y, w, h, sensor, layout.n)
    dn = dark_subtracted(raw, dark, layout, region)
    if dark is None:
        notes.append("no dark at this exposure and gain: DN include the dark level")
    refl = white = None
    if calib is not None and calib.white_mosaic is not None and calib.white_mosaic.shape == raw.shape:
        wdn = dark_subtracted(calib.white_mosaic, None, layout, region)
        rho = calib.white_reflectance if calib.white_reflectance is not None else np.ones(len(dn))
        w_exp, w_gain = float(prov.get("exposure_s") or 0.0), float(prov.get("gain") or 1.0)
        if w_exp > 0:
            r = reflectance(dn, exposure_s, gain, wdn, w_exp, w_gain, np.broadcast_to(rho, dn.shape))
            refl = [None if not math.isfinite(v) else round(float(v), 5) for v in r]
            white = {"captured_at": prov.get("captured_at"), "lighting": prov.get("lighting"),
                     "exposure_s": w_exp, "gain": w_gain,
                     "same_lighting": lighting is not None and prov.get("lighting") == lighting}
            if lighting is None:
                notes.append(f"reflectance assumes the white reference's lighting ({prov.get('lighting')})")
            elif not white["same_lighting"]:
                notes.append(f"the white reference was taken under {prov.get('lighting')!r}, this frame "
                             f"under {lighting!r}: reflectance assumes the same lighting")
        else:
            notes.append("the white reference records no exposure: no reflectance")
    return {"source": source, "region": region.as_dict(), "sensor": list(sensor),
            "bands_nm": [float(b) for b in model.bands_nm], "dn": [round(float(v), 3) for v in dn],
            "dark": dark_label, "reflectance": refl, "white_reference": white, "exposure_s": exposure_s,
            "gain": gain, "lighting": lighting, "notes": notes}


def _frame(store: SessionStore, session_id: str, n: int) -> FrameRecord:
    for fr in store.frames():
        if fr.index == n:
            return fr
    raise UnknownSession(f"session {session_id} has no frame {n} (frames are numbered by their index in "
                         "the plan; GET /sessions/{id}/frames lists them)")


@router.get("/sessions/{session_id}/frames/{n}/spectrum", response_model=SpectrumOut,
            responses={**NOT_FOUND, **CONFLICT})
def frame_spectrum(mg: Manager, console: ConsoleDep, session_id: SessionId, n: FrameN, x: Coord, y: Coord,
                   w: Size = 1, h: Size = 1) -> dict[str, Any]:
    """The spectrum of frame ``n`` over the region (x, y, w, h) widened to whole mosaic cells: mean
    dark-subtracted DN per band (the session's own master dark) and, when the calibration file has
    a white reference, reflectance."""
    with mg.reads.reading(session_id) as store:
        fr = _frame(store, session_id, n)
        raw, _ = decode_tiff(store.read_file(fr.files["raw"]))
        dark = store.load_dark(fr.dark_id) if fr.dark_id else None
    ev = fr.meta.get("event") or {}
    return _spectrum(np.asarray(raw), None if dark is None else np.asarray(dark),
                     fr.dark_id, source=f"{session_id}/{n}", x=x, y=y, w=w, h=h,
                     exposure_s=float(fr.meta.get("exposure_s") or ev.get("exposure_s") or 0.0),
                     gain=float(fr.meta.get("gain") or 1.0), lighting=ev.get("lighting"),
                     console=console, notes=[])


@router.get("/camera/live/spectrum", response_model=SpectrumOut, responses=CONFLICT)
def live_spectrum(console: ConsoleDep, x: Coord, y: Coord, w: Size = 1, h: Size = 1) -> dict[str, Any]:
    """The spectrum of the live view's newest frame (as held in memory: no camera request) over the
    region; dark-subtracted with the library's dark at its exposure and gain when there is one.
    409 while no live frame is held (start the live view)."""
    snap = console.live.snapshot()
    raw = getattr(snap, "raw", None)
    if snap is None or raw is None:
        raise Conflict("no live frame to read: start the live view")
    st = snap.stats
    exposure, gain = float(st.get("exposure_s", 0.0)), float(st.get("gain", 1.0))
    dark = label = None
    tol = console.manager.rig.config.processing.dark_temperature_tolerance_c
    try:
        if console.darks.root.is_dir():
            md = console.darks.get(exposure, gain, float(st.get("temperature_c", math.nan)), tol,
                                   shape=tuple(raw.shape))
            dark, label = md.data, f"library: {md.created}"
    except Exception:  # none at this setting (DarkNotFoundError, DarkMismatchError): DN as read
        dark = None
    # The lamps are not read here (that would be a device request): reflectance assumes the white
    # reference's lighting, and the notes say so.
    return _spectrum(raw, dark, label, source=f"live/{snap.seq}", x=x, y=y, w=w, h=h, exposure_s=exposure,
                     gain=gain, lighting=None, console=console, notes=[])


# ----------------------------------------------------------------------------- ten-band mosaic
def _label(img: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((22, img.shape[1], 3), 24, np.uint8)
    cv2.putText(bar, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (235, 235, 235), 1, cv2.LINE_AA)
    return np.vstack([bar, img])


def band_mosaic_png(cube: np.ndarray, bands_nm: list[float], *, cols: int = 5, tile_px: int = 256,
                    common: bool = False) -> bytes:
    """The cube's bands tiled ``cols`` to a row, each labelled with its wavelength; each band
    stretched to its own 99.5th percentile (``common``: one scale for all, so brightness compares
    across bands)."""
    nb, h, w = cube.shape
    scale = tile_px / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    top = float(np.percentile(cube, 99.5)) if common else 0.0
    tiles = []
    for b in range(nb):
        band = cube[b]
        hi = top if common else float(np.percentile(band, 99.5))
        img8 = srgb_encode(np.clip(band / max(hi, 1e-6), 0.0, 1.0))
        interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST
        img = cv2.resize(img8, size, interpolation=interp)
        tiles.append(_label(np.repeat(img[..., None], 3, axis=2), f"{bands_nm[b]:g} nm"))
    rows = []
    blank = np.zeros_like(tiles[0])
    for r in range(0, nb, cols):
        row = tiles[r: r + cols] + [blank] * (cols - len(tiles[r: r + cols]))
        rows.append(np.hstack([np.pad(t, ((2, 2), (2, 2), (0, 0))) for t in row]))
    ok, buf = cv2.imencode(".png", np.vstack(rows)[..., ::-1])
    return buf.tobytes() if ok else b""


@router.get("/sessions/{session_id}/frames/{n}/bands.png", response_class=Response,
            responses={**PNG, **NOT_FOUND, **CONFLICT})
def frame_bands(mg: Manager, session_id: SessionId, n: FrameN,
                scale: Annotated[str, Query(pattern="^(band|common)$")] = "band",
                tile: Annotated[int, Query(ge=64, le=1024)] = 256) -> Response:
    """Frame ``n``'s band images side by side (5 to a row), each labelled with its wavelength
    (``scale=common``: one brightness scale for all bands)."""
    with mg.reads.reading(session_id) as store:
        fr = _frame(store, session_id, n)
        cube = store.read_cube(fr.event_id)
        bands = list(store.rig.camera.model.bands_nm)
    png = band_mosaic_png(np.asarray(cube, np.float32), bands, tile_px=tile, common=scale == "common")
    return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


# ----------------------------------------------------------------------------- coverage map
@router.get("/sessions/{session_id}/coverage", responses={**NOT_FOUND, **CONFLICT})
def session_coverage(mg: Manager, session_id: SessionId) -> dict[str, Any]:
    """Every planned pose (lighting × tilt × azimuth) with its state (captured, flagged, skipped,
    failed, pending), QC score and flags, and the frame's index when it is stored."""
    from m2s2hil.analysis.report.coverage import coverage

    with mg.reads.reading(session_id) as store:
        return coverage(store)
