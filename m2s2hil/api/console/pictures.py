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
from fastapi import Path as FPath
from pydantic import BaseModel

from m2s2hil.daemon.errors import Conflict, UnknownSession
from m2s2hil.errors import UsageError
from m2s2hil.processing.calibration import load_calibration
from m2s2hil.processing.display import srgb_encode
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.spectrum import dark_subtracted, reflectance, snap_region, superpixel_cube
from m2s2hil.store.frame_files import decode_tiff
from m2s2hil.store.records import FrameRecord
from m2s2hil.store.session import SessionStore

from ..common import CONFLICT, CROSS_SITE, NOT_FOUND, FrameN, Manager, SessionId
from . import models as cm
from .state import ConsoleDep, device_errors

router = APIRouter(tags=["console pictures"])

Coord = Annotated[int, Query(ge=0, le=65535, description="Sensor pixel (0-based).")]
Size = Annotated[int, Query(ge=1, le=65536, description="Region size in sensor pixels (default: one cell).")]
PNG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/png": {}}, "description": "PNG image."}}


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
    calib, provenance = _calibration(console)
    prov = provenance or {}  # the white reference's capture (empty without one)
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
            if "raw" not in fr.files and "cube" not in fr.files:
                raise Conflict(f"frame {n} of session {session_id} has no raw mosaic or cube (a synthetic "
                               "render): no spectrum or band images")
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
        if "raw" not in fr.files:
            raise Conflict(f"frame {n} of session {session_id} has no raw mosaic: no spectrum")
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
        model = store.rig.camera.model
        if "cube" in fr.files:  # a stored cube (calibrated, or a slow method's): as stored
            cube = store.read_cube(fr.event_id)
        else:  # raw − dark per band: the pictures need no demosaicing method's detail
            raw, _ = decode_tiff(store.read_file(fr.files["raw"]))
            mosaic = np.asarray(raw, np.float32)
            if fr.dark_id:
                mosaic = np.clip(mosaic - np.asarray(store.load_dark(fr.dark_id), np.float32), 0.0, None)
            cube = superpixel_cube(mosaic, MosaicLayout.from_camera(model))
        bands = list(model.bands_nm)
    png = band_mosaic_png(np.asarray(cube, np.float32), bands, tile_px=tile, common=scale == "common")
    return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


# ----------------------------------------------------------------------------- coverage map
@router.get("/sessions/{session_id}/coverage", responses={**NOT_FOUND, **CONFLICT})
def session_coverage(mg: Manager, session_id: SessionId) -> dict[str, Any]:
    """Every planned pose (lighting × tilt × azimuth) with its state (captured, flagged, skipped,
    failed, pending), QC score and flags, and the frame's index when it is stored; with the twin,
    a cell's ``twin_flags`` (the twin's own among its flags) and ``labels`` (it has projected labels)."""
    from m2s2hil.analysis.report.coverage import coverage

    with mg.reads.reading(session_id) as store:
        cov = coverage(store)
        by_n = {fr.index: fr for fr in store.frames()}
    for c in cov["cells"]:
        fr = by_n.get(c["n"]) if c.get("n") is not None else None
        c["twin_flags"] = [str(f) for f in _twin_of(fr)[0].get("flags") or []] if fr else []
        c["labels"] = bool(fr and PROJECTED in fr.files)
    cov["twin"] = {"checked": sum(bool(fr and _twin_of(fr)[0]) for fr in by_n.values()),
                   "flagged": sum(bool(c["twin_flags"]) for c in cov["cells"]),
                   "labelled": sum(c["labels"] for c in cov["cells"])}
    return cov


# ----------------------------------------------------------------------------- calibration pictures
DarkName = Annotated[str, FPath(pattern=r"^dark_[A-Za-z0-9_.+-]{1,200}$", max_length=205,
                                description="A dark's name in the library (its files' stem).")]


@router.get("/calibration/pictures")
def calibration_pictures(console: ConsoleDep) -> dict[str, Any]:
    """The calibration pictures there are to see: one per dark in the library (level map and hot
    pixels), the white reference's uniformity per band; each with its URL and text alternative."""
    items: list[dict[str, Any]] = []
    try:
        entries = console.darks.entries() if console.darks.root.is_dir() else []
    except UsageError:
        entries = []
    for e in sorted(entries, key=lambda e: str(e.get("created", "")), reverse=True)[:12]:
        name = Path(e["_sidecar"]).stem
        what = f"dark {1e3 * float(e['exposure_s']):g} ms gain {float(e['gain']):g}, {e.get('created', '')}"
        items.append({"kind": "dark", "title": what, "url": f"/calibration/darks/{name}/map.png",
                      "alt": f"{what}: dark level map and hot pixels"})
    calib, prov = _calibration(console)
    if calib is not None and calib.white_mosaic is not None:
        p = prov or {}
        what = f"white reference, {p.get('lighting') or '?'}, {p.get('captured_at') or '?'}"
        items.append({"kind": "white", "title": what, "url": "/calibration/white/uniformity.png",
                      "alt": f"{what}: uniformity per band"})
    return {"items": items, "empty": None if items else
            "no darks in the library and no white reference yet: take them above"}


def _png_response(png: bytes, alt: str) -> Response:
    # the text alternative travels as a header too (ASCII: headers are Latin-1)
    return Response(png, media_type="image/png",
                    headers={"Cache-Control": "no-store", "X-Alt": alt.encode("ascii", "replace").decode()})


@router.get("/calibration/darks/{name}/map.png", response_class=Response, responses={**PNG, **NOT_FOUND})
def dark_map(console: ConsoleDep, name: DarkName) -> Response:
    """A master dark of the library: its level per mosaic cell and its hot pixels."""
    from m2s2hil.analysis.report.calibration_figures import dark_maps_png

    side = console.darks.root / f"{name}.json"
    entry = next((e for e in (console.darks.entries() if console.darks.root.is_dir() else [])
                  if Path(e["_sidecar"]).name == side.name), None)
    if entry is None:
        raise UnknownSession(f"path.name: the dark library has no dark {name!r} "
                             "(GET /calibration lists them)")
    dark = console.darks._load(entry)  # checks the TIFF against its sidecar's sha256
    model = console.manager.rig.config.camera.model
    title = (f"dark {1e3 * dark.exposure_s:g} ms · gain {dark.gain:g} · {dark.n_frames} frames · "
             f"{dark.temperature_c:.1f} °C")
    png, alt = dark_maps_png(dark.data, model.period, title=title)
    return _png_response(png, alt)


@router.get("/calibration/white/uniformity.png", response_class=Response, responses={**PNG, **NOT_FOUND})
def white_uniformity(console: ConsoleDep) -> Response:
    """The calibration file's white reference: each band relative to its brightest block."""
    from m2s2hil.analysis.report.calibration_figures import white_uniformity_png

    calib, prov = _calibration(console)
    if calib is None or calib.white_mosaic is None:
        raise UnknownSession(f"no white reference in {console.calibration_path} (capture one first)")
    model = console.manager.rig.config.camera.model
    cube = superpixel_cube(calib.white_mosaic, _layout(model, calib))
    title = f"white reference ({(prov or {}).get('lighting') or '?'})"
    png, alt = white_uniformity_png(cube, list(model.bands_nm), title=title)
    return _png_response(png, alt)


@router.post("/calibration/phase.png", response_class=Response,
             responses={**PNG, **CONFLICT, **CROSS_SITE})
def phase_map(mg: Manager, console: ConsoleDep, body: cm.PhaseIn) -> Response:
    """One frame's mosaic phase check (as ``POST /calibration/phase``) drawn as the cost of every
    origin shift; ``X-Phase-Summary`` says the result in words."""
    from m2s2hil.analysis.report.calibration_figures import phase_cost_png
    from m2s2hil.rig.calibrate import check_mosaic_phase

    with mg.guard.manual_access("the phase check") as rig, device_errors("the phase check"):
        console.camera.release(rig)
        res = check_mosaic_phase(rig, exposure_s=body.exposure_s, gain=body.gain)
    png, alt = phase_cost_png(res["cost_map"] or [[0.0]], res["offset"], conclusive=res["conclusive"])
    summary = (f"{res['message']}; cost at origin {100 * res['cost_nominal']:.2f} %, "
               f"best {100 * res['cost_best']:.2f} %")
    resp = _png_response(png, alt)
    resp.headers["X-Phase-Summary"] = summary.encode("ascii", "replace").decode()
    return resp


# ----------------------------------------------------------------------------- the twin on a frame
PROJECTED = "projected_labels"  # the twin's label map of a frame (store role; m2s2hil/twin/labels.py)
# A colour per label index (matplotlib's tab10 without its grey, then tab20's light ones): the
# filaments of one build are at most a handful, each told apart at a glance; 0 (background) is clear.
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf",
           "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5")


def _colour(k: int) -> str:
    return PALETTE[(k - 1) % len(PALETTE)]


def _stored_frame(store: SessionStore, session_id: str, n: int) -> FrameRecord:
    fr = next((f for f in store.frames() if f.index == n), None)
    if fr is None:
        raise UnknownSession(f"session {session_id} has no frame {n} (frames are numbered by their index in "
                             "the plan; GET /sessions/{id}/frames lists them)")
    return fr


def _twin_of(fr: FrameRecord) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the twin's checks, the projected labels' metadata) of a frame, each {} when absent."""
    raw_qc = fr.meta.get("qc")
    qc: dict[str, Any] = raw_qc if isinstance(raw_qc, dict) else {}
    raw_twin = qc.get("twin")
    twin: dict[str, Any] = raw_twin if isinstance(raw_twin, dict) else {}
    labels = qc.get(PROJECTED) or fr.meta.get(PROJECTED)
    return twin, labels if isinstance(labels, dict) else {}


def _projected(store: SessionStore, session_id: str, n: int) -> tuple[np.ndarray, list[str], dict[str, Any]]:
    from m2s2hil.store.frame_files import decode_image

    fr = _stored_frame(store, session_id, n)
    if PROJECTED not in fr.files:
        raise UnknownSession(f"frame {n} of session {session_id} has no projected labels: the twin projects "
                             "them once its registration has a placement (docs/twin.md)")
    lab = np.asarray(decode_image(store.read_file(fr.files[PROJECTED])))
    names = [str(c) for c in _twin_of(fr)[1].get("class_names") or []]
    return lab, names, _twin_of(fr)[1]


class LegendItem(BaseModel):
    index: int
    name: str
    colour: str
    pixels: int


class TwinFrameOut(BaseModel):
    flags: list[str]
    frame_flags: list[str]
    checked: bool
    labels_url: str | None
    confidence: float | None
    legend: list[LegendItem]


@router.get("/sessions/{session_id}/frames/{n}/twin", response_model=TwinFrameOut, responses=NOT_FOUND)
def frame_twin(mg: Manager, session_id: SessionId, n: FrameN) -> dict[str, Any]:
    """The twin on frame ``n``: its QC flags (``flags``: confirmed over the lighting's frames;
    ``frame_flags``: this frame's own), and its projected labels' legend (material, colour,
    pixels) with the overlay's URL, when the frame has them (else ``labels_url`` null)."""
    with mg.reads.reading(session_id) as store:
        fr = _stored_frame(store, session_id, n)
        twin, meta = _twin_of(fr)
        legend: list[dict[str, Any]] = []
        url = None
        if PROJECTED in fr.files:
            lab, names, meta = _projected(store, session_id, n)
            counts = np.bincount(lab.ravel(), minlength=len(names))
            legend = [{"index": k, "name": names[k] if k < len(names) else f"label {k}", "colour": _colour(k),
                       "pixels": int(counts[k])} for k in range(1, len(counts)) if counts[k]]
            url = f"/sessions/{session_id}/frames/{n}/labels.png"
    conf = meta.get("confidence")
    return {"flags": [str(f) for f in twin.get("flags") or []],
            "frame_flags": [str(f) for f in twin.get("frame_flags") or twin.get("flags") or []],
            "checked": bool(twin), "labels_url": url,
            "confidence": float(conf) if isinstance(conf, int | float) else None, "legend": legend}


@router.get("/sessions/{session_id}/frames/{n}/labels.png", response_class=Response,
            responses={**PNG, **NOT_FOUND})
def frame_labels(mg: Manager, session_id: SessionId, n: FrameN) -> Response:
    """Frame ``n``'s projected labels (the registered twin's label map at its pose) as an RGBA
    PNG at the label map's size: a colour per material (``GET …/twin`` has the legend), the
    background transparent; 404 when the frame has none."""
    with mg.reads.reading(session_id) as store:
        lab, names, _ = _projected(store, session_id, n)
    lut = np.zeros((256, 4), np.uint8)
    for k in range(1, 256):
        h = _colour(k)
        lut[k] = (int(h[5:7], 16), int(h[3:5], 16), int(h[1:3], 16), 255)  # BGRA for OpenCV
    ok, buf = cv2.imencode(".png", lut[lab.astype(np.uint8)])
    present = [names[k] if k < len(names) else f"label {k}" for k in np.unique(lab) if k]
    return _png_response(buf.tobytes() if ok else b"",
                         f"projected labels of frame {n}: {', '.join(present) or 'background only'}")
