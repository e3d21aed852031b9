"""The ``hf`` and ``zarr`` exports of a synthetic session (``m2s2hil synth``), beside the HIL ones.

(The m2s2 layout of a synthetic session is m2s2hil.store.export's: ``Synthetic/...`` beside
``HIL/...`` and ``metadata/pairs.csv``.)

- ``hf``: ``data/synthetic-<session_id>.parquet``, the card's ``synthetic`` configuration
  (``load_dataset(out, "synthetic", split="train")``): ``rgb`` (the RGB render), ``bands``
  (the ten band renders, band order), ``mask`` (label map, 8-bit), ``class_names`` and the
  pose columns the HIL rows share (``satellite``, ``build``, ``elevation``,
  ``nominal_azimuth_deg``, ``k``), so a join on them pairs the domains by pose.
- ``zarr``: group ``synthetic`` of the same store the HIL sessions go to: ``rgb`` (frame, y,
  x, rgb), ``bands`` (frame, band, y, x, rgb), ``mask`` (frame, y, x) uint8, one chunk per
  view, with the coordinates ``satellite``, ``build``, ``elevation``, ``azimuth_deg``,
  ``tilt_deg``, ``session_id``, ``event_id`` named as the root group's (the HIL frames).
  More synthetic sessions append along ``frame`` (the same image size required).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.catalog import load_catalog
from m2s2hil.store.frame_files import decode_image

if TYPE_CHECKING:
    from m2s2hil.store.export import ExportResult, Progress
    from m2s2hil.store.records import FrameRecord
    from m2s2hil.store.session import SessionStore

MASK_ROLE = "truth_labels"


def _bands(fr: FrameRecord) -> list[str]:
    return sorted(r for r in fr.files if r.startswith("band_"))


def export_synthetic(store: SessionStore, out: Path, layout: str, frames: list[FrameRecord], *,
                     overwrite: bool, progress: Progress | None = None) -> ExportResult:
    from m2s2hil.store.export import ExportError, ExportResult

    for fr in frames:
        if "rgb" not in fr.files or MASK_ROLE not in fr.files or not _bands(fr):
            raise ExportError(f"synthetic frame {fr.event_id} of {store.session_id} lacks its rgb, bands "
                              "or mask")
    if layout == "hf":
        target = out / "data" / f"synthetic-{store.session_id}.parquet"
        if target.exists() and not overwrite:
            raise ExportError(f"{target} already exists; use overwrite to replace it")
        _hf(store, out, target, frames, progress)
        return ExportResult(layout=layout, out=out, images=len(frames), files=[target, out / "README.md"])
    if layout == "zarr":
        return ExportResult(layout=layout, out=out, images=_zarr(store, out, frames, progress), files=[out])
    raise ExportError(f"unknown export layout {layout!r} for a synthetic session")


def _row(store: SessionStore, fr: FrameRecord) -> dict[str, Any]:
    ev = fr.meta["event"]
    return {
        "satellite": load_catalog().satellites[store.sweep.satellite].name, "build": store.sweep.build,
        "elevation": ev["elevation"], "k": int(ev["azimuth_index"]),
        "nominal_azimuth_deg": float(ev["nominal_azimuth_deg"]), "tilt_deg": float(ev["tilt_deg"]),
        "session_id": store.session_id, "event_id": fr.event_id,
        "class_names": list(fr.meta.get("class_names", [])),
    }


def _hf(store: SessionStore, out: Path, target: Path, frames: list[FrameRecord],
        progress: Progress | None = None) -> None:
    from m2s2hil.store.export_hf import CARD, require_datasets, write_parquet

    require_datasets()
    from datasets import Features, Image, Sequence, Value  # type: ignore[import-untyped]

    features = Features({
        "rgb": Image(), "bands": Sequence(Image()), "mask": Image(),
        "satellite": Value("string"), "build": Value("string"), "elevation": Value("string"),
        "k": Value("int32"), "nominal_azimuth_deg": Value("float64"), "tilt_deg": Value("float64"),
        "session_id": Value("string"), "event_id": Value("string"), "class_names": Sequence(Value("string")),
    })

    def png(fr: FrameRecord, role: str) -> dict[str, Any]:
        return {"bytes": store.read_file(fr.files[role]), "path": None}  # as stored: PNG, checked

    def batches(size: int = 8) -> Iterator[dict[str, list]]:
        batch: dict[str, list] = {c: [] for c in features}
        for i, fr in enumerate(frames):
            ex = {"rgb": png(fr, "rgb"), "bands": [png(fr, r) for r in _bands(fr)],
                  "mask": png(fr, MASK_ROLE), **_row(store, fr)}
            for c in features:
                batch[c].append(ex[c])
            if progress is not None:
                progress.step()
            if len(batch["rgb"]) == size or i == len(frames) - 1:
                yield batch
                batch = {c: [] for c in features}

    write_parquet(out, target, features, batches())
    card = out / "README.md"
    if not card.exists():  # the HIL export writes the card; a synthetic-only folder gets it too
        from m2s2hil.atomic import write_text_atomic

        m = store.rig.camera.model
        write_text_atomic(card, CARD.format(bits=m.bit_depth, shift=m.bit_depth - 8, n=m.n_bands, p=m.period,
                                            name=out.name or str(out), full=m.full_scale))


def _zarr(store: SessionStore, out: Path, frames: list[FrameRecord], progress: Progress | None = None) -> int:
    from m2s2hil.store.zarr_export import ZarrExportError, _libs

    xr, da, _ = _libs()
    import dask
    from dask import delayed

    def load(event_id: str, role: str) -> np.ndarray:
        return decode_image(store.read_file(store.frame(event_id).files[role]))

    first = load(frames[0].event_id, "rgb")
    h, w = first.shape[:2]
    nb = len(_bands(frames[0]))

    def bands_of(event_id: str) -> np.ndarray:
        out = np.stack([load(event_id, r) for r in _bands(store.frame(event_id))])
        if progress is not None:  # once per view, as to_zarr writes it
            progress.step()
        return out

    def lazy(fn: Any, shape: tuple[int, ...], *args: str) -> Any:
        return da.stack([da.from_delayed(delayed(fn)(fr.event_id, *args), shape, np.uint8) for fr in frames])

    rgb, mask = lazy(load, (h, w, 3), "rgb"), lazy(load, (h, w), MASK_ROLE)
    bands = lazy(bands_of, (nb, h, w, 3))
    rows = [_row(store, fr) for fr in frames]
    coords = {c: ("frame", np.array([r[c] for r in rows], dtype=object)) for c in
              ("satellite", "build", "elevation", "session_id", "event_id")}
    coords["azimuth_deg"] = ("frame", np.array([r["nominal_azimuth_deg"] for r in rows]))
    coords["tilt_deg"] = ("frame", np.array([r["tilt_deg"] for r in rows]))
    coords["wavelength_nm"] = ("band", np.asarray(store.rig.camera.model.bands_nm, np.float32))
    ds = xr.Dataset({"rgb": (("frame", "y", "x", "rgb"), rgb), "mask": (("frame", "y", "x"), mask),
                     "bands": (("frame", "band", "y", "x", "rgb"), bands)}, coords=coords)
    ds.attrs["description"] = "M2S2 synthetic domain (m2s2hil synth): RGB and band renders, masks"
    ds.attrs["class_names"] = list(frames[0].meta.get("class_names", []))
    group = out / "synthetic"
    with dask.config.set(scheduler="synchronous"):
        if (group / "zarr.json").is_file():
            old = xr.open_zarr(out, group="synthetic", consolidated=False)
            if store.session_id in set(old["session_id"].values.tolist()):
                raise ZarrExportError(f"{out} already holds session {store.session_id}")
            if (old.sizes["y"], old.sizes["x"]) != (h, w):
                raise ZarrExportError(f"{out} holds {old.sizes['x']}x{old.sizes['y']} synthetic views, "
                                      f"session {store.session_id} has {w}x{h}")
            old.close()
            ds.to_zarr(out, group="synthetic", append_dim="frame", zarr_format=3, consolidated=False)
        else:
            enc = {"rgb": {"chunks": (1, h, w, 3)}, "bands": {"chunks": (1, nb, h, w, 3)},
                   "mask": {"chunks": (1, h, w)}}
            ds.to_zarr(out, group="synthetic", mode="w-", encoding=enc, zarr_format=3, consolidated=False)
    return len(frames)
