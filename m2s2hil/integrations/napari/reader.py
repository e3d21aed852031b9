"""napari reader: a session folder or a Zarr export (``m2s2hil export --layout zarr``) as layers.

Layers are napari's "layer data tuples" ``(data, kwargs, layer_type)``, so this module needs
neither napari nor npe2 to run:

- a session folder (it holds ``journal.sqlite``): ``cube`` (frame, band, y, x) float32 as the
  store gives it (:meth:`SessionStore.read_cube`), with ``wavelength_nm``, ``fwhm_nm`` and the
  event ids in its metadata, scaled so it lies over the full-resolution layers; ``raw`` (frame,
  y, x) the sensor's DN; ``labels`` (frame, y, x) the simulator's ground truth when the session
  has it for every frame.
- a Zarr export: ``raw`` and ``labels`` from the store, and ``bands`` (frame, band, y/n, x/n): the
  mean of each band's positions in the filter cell (``mosaic_layout``) of the raw mosaic, not
  dark subtracted (the export holds raw frames only).

The session is opened read-only; nothing is written.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.store.frame_files import decode_image
from m2s2hil.store.layout import JOURNAL
from m2s2hil.store.session import SessionStore

LayerData = tuple[Any, dict[str, Any], str]
Reader = Callable[[str | list[str]], list[LayerData]]


def _one(path: str | list[str]) -> Path | None:
    paths = [path] if isinstance(path, str) else list(path)
    return Path(paths[0]) if len(paths) == 1 else None


def is_session(p: Path) -> bool:
    return (p / JOURNAL).is_file()


def is_zarr_export(p: Path) -> bool:
    meta = p / "zarr.json"
    return meta.is_file() and (p / "raw" / "zarr.json").is_file()


def get_reader(path: str | list[str]) -> Reader | None:
    """npe2's reader hook: a reader for one session folder or Zarr export, else None."""
    p = _one(path)
    if p is None:
        return None
    if is_session(p):
        return read_session
    if is_zarr_export(p):
        return read_zarr
    return None


def _band_meta(bands: Any, fwhm: Any) -> dict[str, Any]:
    return {"wavelength_nm": [float(b) for b in bands], "fwhm_nm": [float(f) for f in fwhm], "band_axis": 1}


def read_session(path: str | list[str]) -> list[LayerData]:
    p = _one(path)
    if p is None:
        raise ValueError("the m2s2hil reader opens one session folder at a time")
    with SessionStore.open_path(p) as store:
        m = store.rig.camera.model
        frames = store.frames()
        if not frames:
            return []
        ids = [fr.event_id for fr in frames]
        cube = np.stack([store.read_cube(i) for i in ids])
        raw = np.stack([store.read_raw(i)[0] for i in ids])
        # the cube's pixel stands for a (H/h) x (W/w) patch of the sensor: scale it over the raw
        sy, sx = raw.shape[1] / cube.shape[2], raw.shape[2] / cube.shape[3]
        meta = {"session_id": store.session_id, "event_ids": ids, "satellite": store.sweep.satellite,
                "build": store.sweep.build, "camera": m.name}
        layers: list[LayerData] = [
            (cube, {"name": f"{store.session_id} cube", "scale": (1.0, 1.0, sy, sx),
                    "axis_labels": ("frame", "band", "y", "x"),
                    "metadata": {**meta, **_band_meta(m.bands_nm, m.fwhm_nm)}}, "image"),
            (raw, {"name": f"{store.session_id} raw", "axis_labels": ("frame", "y", "x"), "visible": False,
                   "contrast_limits": (0, 2**m.bit_depth - 1), "metadata": meta}, "image"),
        ]
        if all("truth_labels" in fr.files for fr in frames):
            labels = np.stack([decode_image(store.read_file(fr.files["truth_labels"])) for fr in frames])
            layers.append((labels.astype(np.uint8), {"name": f"{store.session_id} labels",
                                                     "axis_labels": ("frame", "y", "x"), "metadata": meta},
                           "labels"))
    return layers


def superpixel_bands(raw: np.ndarray, layout: np.ndarray, n_bands: int) -> np.ndarray:
    """(frame, y, x) mosaics to (frame, band, y/n, x/n): each band the mean of its cell positions."""
    n = layout.shape[0]
    f, h, w = raw.shape
    cells = raw.reshape(f, h // n, n, w // n, n).astype(np.float32)
    out = np.zeros((f, n_bands, h // n, w // n), np.float32)
    for b in range(n_bands):
        pos = np.argwhere(layout == b)
        out[:, b] = np.mean([cells[:, :, r, :, c] for r, c in pos], axis=0)
    return out


def read_zarr(path: str | list[str]) -> list[LayerData]:
    import xarray as xr  # the analysis extra, which wrote the export

    p = _one(path)
    if p is None:
        raise ValueError("the m2s2hil reader opens one Zarr export at a time")
    ds = xr.open_zarr(p, consolidated=False)
    camera = json.loads(ds.attrs["camera"])
    raw = np.asarray(ds["raw"].values)
    layout = np.asarray(ds["mosaic_layout"].values)
    n = layout.shape[0]
    ids = [str(v) for v in ds["event_id"].values.tolist()]
    meta = {"event_ids": ids, "session_ids": [str(v) for v in ds["session_id"].values.tolist()],
            "camera": camera.get("name", "")}
    bands = superpixel_bands(raw, layout, len(ds["wavelength_nm"]))
    layers: list[LayerData] = [
        (bands, {"name": f"{p.name} bands", "scale": (1.0, 1.0, float(n), float(n)),
                 "axis_labels": ("frame", "band", "y", "x"),
                 "metadata": {**meta, **_band_meta(ds["wavelength_nm"].values, ds["fwhm_nm"].values),
                              "note": "mean of each band's filter-cell positions; raw DN, no dark"}},
         "image"),
        (raw, {"name": f"{p.name} raw", "axis_labels": ("frame", "y", "x"), "visible": False,
               "metadata": meta}, "image"),
    ]
    has = np.asarray(ds["has_labels"].values, bool)
    if has.any():
        layers.append((np.asarray(ds["labels"].values, np.uint8),
                       {"name": f"{p.name} labels", "axis_labels": ("frame", "y", "x"),
                        "metadata": {**meta, "has_labels": has.tolist()}}, "labels"))
    return layers
