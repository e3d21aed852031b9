"""The ``zarr`` export: raw frames as one chunked array for analysis at scale, and its reader.

``m2s2hil export SESSION --layout zarr --out DATA.zarr`` writes (or appends to) a Zarr v3
store that ``xarray.open_zarr`` opens lazily:

- ``raw`` (frame, y, x) uint16, one chunk per frame: the sensor's DN unchanged.
- coordinates along ``frame``: ``satellite``, ``build``, ``elevation``, ``lighting``,
  ``azimuth_deg`` (nominal), ``session_id``, ``event_id``, ``exposure_s``, ``gain``,
  ``temperature_c``, ``turntable_readback_deg``, ``tilt_readback_deg``, ``dark_key``
  (``<session>/<dark id>``, "" without one), ``processing_method``, ``has_labels``;
- ``wavelength_nm`` and ``fwhm_nm`` along ``band`` (band order), ``mosaic_layout``
  (cell_y, cell_x) = band index at each position of the filter cell; the camera model in
  the attributes;
- ``labels`` (frame, y, x) uint8: the simulator's ground truth where the session has it (0
  elsewhere, ``has_labels`` false); ``projected_labels`` the same for the twin's projected
  labels (``has_projected_labels``);
- group ``synthetic``: the synthetic sessions' views (m2s2hil.store.export_synthetic), with
  the same pose coordinates, so the domains pair by pose;
- group ``darks``: ``master`` (dark, y, x) with ``dark_key``, exposure and gain.

More sessions append along ``frame`` (the same sensor size required). ``m2s2hil evaluate
DATA.zarr`` (and its Dask mode) reads it through :func:`zarr_jobs`: each job points into
the store with a ``<store>#zarr:<what>/<index>.tiff`` reference (:func:`zarr_frames`), which
the analysis loader resolves with :func:`read_ref` to the bytes a session file would give.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.errors import UsageError

if TYPE_CHECKING:
    from m2s2hil.store.export import Progress
    from m2s2hil.store.records import FrameRecord
    from m2s2hil.store.session import SessionStore

REF = "#zarr:"
PROJECTED = "projected_labels"  # the twin's label map of a frame (extra file role)


class ZarrExportError(UsageError):
    """A zarr export or read that cannot be done (library missing, store mismatch, bad ref)."""


def _libs() -> tuple[Any, Any, Any]:
    try:
        import dask.array as da
        import xarray as xr
        import zarr
    except ImportError:
        raise ZarrExportError("the zarr layout needs xarray and zarr: "
                              "pip install 'm2s2hil[analysis]'") from None
    return xr, da, zarr


def _frames_dataset(store: SessionStore, xr: Any, da: Any, dark_keys: dict[str, str],
                    progress: Progress | None = None) -> Any:
    from dask import delayed

    from m2s2hil.catalog import load_catalog

    m = store.rig.camera.model
    frames = store.frames()
    shape = (m.height, m.width)

    def raw_of(event_id: str) -> np.ndarray:
        raw = store.read_raw(event_id)[0]
        if progress is not None:  # computed once per frame as to_zarr writes it (synchronous scheduler)
            progress.step()
        return raw

    def labels_of(event_id: str, role: str = "truth_labels") -> np.ndarray:
        from m2s2hil.store.frame_files import decode_image

        fr = store.frame(event_id)
        if role not in fr.files:
            return np.zeros(shape, np.uint8)
        return decode_image(store.read_file(fr.files[role])).astype(np.uint8)

    def lazy(fn: Callable[..., np.ndarray], dtype: Any, *args: str) -> Any:
        return da.stack([da.from_delayed(delayed(fn)(fr.event_id, *args), shape, dtype) for fr in frames])

    raw = lazy(raw_of, np.uint16)
    labels = lazy(labels_of, np.uint8)
    projected = lazy(labels_of, np.uint8, PROJECTED)
    cat = load_catalog()

    def col(fn: Callable[[FrameRecord], Any]) -> np.ndarray:
        values = [fn(fr) for fr in frames]
        # strings as variable-length: fixed-width ones could not be appended to by a longer name
        return np.array(values, dtype=object) if values and isinstance(values[0], str) else np.array(values)

    def pose(fr: FrameRecord, key: str) -> float:
        p = fr.meta.get("pose") or {}
        v = p.get(key)
        return float(v) if isinstance(v, int | float) else float("nan")

    def num(fr: FrameRecord, key: str) -> float:
        v = fr.meta.get(key)
        return float(v) if isinstance(v, int | float) else float("nan")

    coords = {
        "satellite": ("frame", col(lambda fr: store.sweep.satellite)),
        "satellite_name": ("frame", col(lambda fr: cat.satellites[store.sweep.satellite].name)),
        "build": ("frame", col(lambda fr: store.sweep.build)),
        "elevation": ("frame", col(lambda fr: fr.meta["event"]["elevation"])),
        "lighting": ("frame", col(lambda fr: fr.meta["event"]["lighting"])),
        "azimuth_deg": ("frame", col(lambda fr: float(fr.meta["event"]["nominal_azimuth_deg"]))),
        "session_id": ("frame", col(lambda fr: store.session_id)),
        "event_id": ("frame", col(lambda fr: fr.event_id)),
        # a bracket's extra exposure of its pose (Sweep.bracket); 1 for the pose's own frame
        "exposure_factor": ("frame", col(lambda fr: float(fr.meta["event"].get("exposure_factor", 1.0)))),
        "exposure_s": ("frame", col(lambda fr: num(fr, "exposure_s"))),
        "gain": ("frame", col(lambda fr: num(fr, "gain"))),
        "temperature_c": ("frame", col(lambda fr: num(fr, "temperature_c"))),
        "turntable_readback_deg": ("frame", col(lambda fr: pose(fr, "turntable_deg"))),
        "tilt_readback_deg": ("frame", col(lambda fr: pose(fr, "tilt_deg"))),
        "dark_key": ("frame", col(lambda fr: dark_keys.get(fr.dark_id or "", ""))),
        "processing_method": ("frame", col(lambda fr: str(fr.meta.get("processing_method")
                                                         or store.sweep.processing))),
        "has_labels": ("frame", col(lambda fr: "truth_labels" in fr.files)),
        "has_projected_labels": ("frame", col(lambda fr: PROJECTED in fr.files)),
        "wavelength_nm": ("band", np.asarray(m.bands_nm, np.float32)),
        "fwhm_nm": ("band", np.asarray(m.fwhm_nm, np.float32)),
        "mosaic_layout": (("cell_y", "cell_x"), np.asarray(m.layout, np.int8)),
    }
    ds = xr.Dataset({"raw": (("frame", "y", "x"), raw), "labels": (("frame", "y", "x"), labels),
                     "projected_labels": (("frame", "y", "x"), projected)}, coords=coords)
    ds.attrs["camera"] = json.dumps(m.model_dump(mode="json"))
    ds.attrs["description"] = ("M2S2 hardware-in-the-loop raw mosaics (m2s2hil export --layout zarr); "
                               "band b of pixel (y, x) is mosaic_layout[y % n, x % n]")
    return ds


def export_zarr(store: SessionStore, out: str | Path, *, progress: Progress | None = None) -> int:
    """Write ``store``'s frames (and darks) into the Zarr store ``out`` (created, or appended
    to); returns the number of frames written. ``progress`` counts the frames as they are read."""
    xr, da, _ = _libs()
    import dask

    out = Path(out)
    m = store.rig.camera.model
    darks = store.darks()
    dark_keys = {d.dark_id: f"{store.session_id}/{d.dark_id}" for d in darks}
    exists = (out / "zarr.json").is_file()
    fresh_root = False  # a store holding only the synthetic group so far
    if exists:
        old = xr.open_zarr(out, consolidated=False)
        fresh_root = "raw" not in old.variables
    if exists and not fresh_root:
        if store.session_id in set(old["session_id"].values.tolist()):
            raise ZarrExportError(f"{out} already holds session {store.session_id}")
        if (old.sizes["y"], old.sizes["x"]) != (m.height, m.width):
            raise ZarrExportError(f"{out} holds {old.sizes['x']}x{old.sizes['y']} frames, "
                                  f"session {store.session_id} has {m.width}x{m.height}")
        old_vars = set(old.variables)
        old.close()
    elif out.exists() and not fresh_root:
        raise ZarrExportError(f"{out} exists and is not a Zarr store")
    ds = _frames_dataset(store, xr, da, dark_keys, progress)
    if exists and not fresh_root and "exposure_factor" not in old_vars:
        # a store written before brackets keeps its layout: a bracket member is then told by its
        # event id's /x<factor> alone
        ds = ds.drop_vars("exposure_factor")
    chunk = {"chunks": (1, m.height, m.width)}
    encoding = {"raw": chunk, "labels": chunk, "projected_labels": chunk}
    with dask.config.set(scheduler="synchronous"):  # one frame in memory at a time
        if fresh_root:
            ds.to_zarr(out, mode="a", encoding=encoding, zarr_format=3, consolidated=False)
        elif exists:
            ds.to_zarr(out, append_dim="frame", zarr_format=3, consolidated=False)
        else:
            ds.to_zarr(out, mode="w-", encoding=encoding, zarr_format=3, consolidated=False)
    if darks:
        masters = np.stack([store.load_dark(d.dark_id).astype(np.float32) for d in darks])
        dk = xr.Dataset({"master": (("dark", "y", "x"), masters)},
                        coords={"dark_key": ("dark", np.array([dark_keys[d.dark_id] for d in darks], object)),
                                "exposure_s": ("dark", [d.exposure_s for d in darks]),
                                "gain": ("dark", [d.gain for d in darks]),
                                "n_frames": ("dark", [d.n_frames for d in darks])})
        if (out / "darks" / "zarr.json").is_file():
            dk.to_zarr(out, group="darks", append_dim="dark", zarr_format=3, consolidated=False)
        else:
            dk.to_zarr(out, group="darks", mode="w-", zarr_format=3, consolidated=False,
                       encoding={"master": {"chunks": (1, m.height, m.width)}})
    return len(ds["frame"])


# ------------------------------------------------------------------------------ reading
def zarr_frames(path: str | Path) -> list[dict[str, Any]]:
    """The fields of one evaluation job (``analysis.evaluation.jobs.FrameJob``) per frame of a Zarr
    export; ``raw``, ``dark`` and ``labels`` are references for :func:`read_ref`."""
    xr, _, _ = _libs()
    from m2s2hil.catalog import load_catalog
    from m2s2hil.plan import bracket_base_id

    p = Path(path)
    ds = xr.open_zarr(p, consolidated=False)
    cat = load_catalog()
    camera = json.loads(ds.attrs["camera"])
    dark_index: dict[str, int] = {}
    if (p / "darks" / "zarr.json").is_file():
        dk = xr.open_zarr(p, group="darks", consolidated=False)
        dark_index = {str(k): i for i, k in enumerate(dk["dark_key"].values.tolist())}
    jobs = []
    keys = ("satellite", "build", "elevation", "lighting", "azimuth_deg", "session_id", "event_id",
            "dark_key", "processing_method", "has_labels")
    cols = {k: ds[k].values for k in keys}  # each coordinate read once
    for i in range(ds.sizes["frame"]):
        c = {k: _plain(cols[k][i]) for k in keys}
        if bracket_base_id(str(c["event_id"])) != c["event_id"]:
            continue  # a bracket's extra exposure: the export keeps it, the pose's image is its own frame
        d = dark_index.get(str(c["dark_key"]))
        jobs.append(dict(
            image_id=f"{c['session_id']}/{c['event_id']}", source=str(p), satellite=str(c["satellite"]),
            build=str(c["build"]),
            n_classes=len(cat.build(str(c["satellite"]), str(c["build"])).materials) + 1,
            elevation=str(c["elevation"]), lighting=str(c["lighting"]), azimuth_deg=float(c["azimuth_deg"]),
            camera=camera, method=str(c["processing_method"]), raw_kind="tiff",
            raw=f"{p}{REF}raw/{i}.tiff",
            dark=f"{p}{REF}dark/{d}.tiff" if d is not None else None,
            labels=f"{p}{REF}labels/{i}.tiff" if c["has_labels"] else None,
        ))
    return jobs


def _plain(v: Any) -> Any:
    return v.item() if isinstance(v, np.generic) else v


def read_ref(path: str) -> bytes:
    """The TIFF bytes a ``<store>#zarr:<raw|dark|labels>/<index>.tiff`` reference stands for
    (uncompressed; what the session's own file would decode to)."""
    import tifffile

    xr, _, _ = _libs()
    store, _, what = path.partition(REF)
    kind, _, name = what.partition("/")
    try:
        i = int(name.removesuffix(".tiff"))
    except ValueError:
        raise ZarrExportError(f"{path}: not a zarr frame reference") from None
    desc: dict[str, Any] = {}
    if kind in ("raw", "labels"):
        arr = xr.open_zarr(store, consolidated=False)[kind][i].values
    elif kind == "dark":
        dk = xr.open_zarr(store, group="darks", consolidated=False)
        arr = dk["master"][i].values
        desc = {"exposure_s": float(dk["exposure_s"][i]), "gain": float(dk["gain"][i]),
                "n_frames": int(dk["n_frames"][i])}
    else:
        raise ZarrExportError(f"{path}: unknown zarr reference {kind!r}")
    buf = io.BytesIO()
    tifffile.imwrite(buf, arr, description=json.dumps({"shape": list(arr.shape), **desc}), metadata=None)
    return buf.getvalue()
