"""The ``hf`` export: a Hugging Face ``datasets`` dataset that keeps the 10-bit data exact.

Layout under ``out``::

    README.md                            dataset card: features, bands, how to load
    data/train-<session_id>.parquet      one file per exported session (more sessions merge)
    metadata/<session_id>.json           camera, bands, sweep, darks (as the m2s2 layout)
    metadata/<session_id>/<dark>.tiff    the master darks

Columns of each row (one per frame):

- ``raw``: the sensor's DN unchanged, an ``Array2D(shape=(H, W), dtype="uint16")``. Not an
  image, so no image conversion can touch it: ``np.asarray(row["raw"])`` is the mosaic.
- ``image``: the release's 8-bit view of the same mosaic (``raw >> (bit_depth - 8)``, three
  identical channels) for browsing; ``.convert("RGB")`` on it loses nothing it holds.
  (A 16-bit PNG decodes as PIL ``I;16``, which ``.convert("RGB")`` clips at 255: the
  reason the exact data is an array column and not an image.)
- ``bands_nm``, ``fwhm_nm`` (band order: index b of a cube), ``mosaic_layout`` (band index at
  each position of the repeating cell, row-major from the top-left pixel), ``bit_depth``;
  the same in every row of a session, so a row is self-describing after shuffling.
- the m2s2 CSV columns (satellite, build, elevation, lighting, azimuth, exposure, pose
  read-backs, dark id, ...).
- ``mask``: the simulator's truth label map (8-bit PNG, label i = ``class_names[i]``) and
  ``labels``: the twin's projected labels, where the frame has them (else null).

A synthetic session (``m2s2hil synth``) goes to ``data/synthetic-<session_id>.parquet``, the
card's ``synthetic`` configuration (m2s2hil.store.export_synthetic): ``rgb``, ``bands`` (ten
images), ``mask`` and the pose columns the HIL rows pair with (satellite, build, elevation,
nominal_azimuth_deg).

Load it offline with ``datasets.load_dataset(out, split="train")``.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.atomic import fsync_dir, write_text_atomic
from m2s2hil.errors import UsageError
from m2s2hil.store.frame_files import encode_png

if TYPE_CHECKING:
    from m2s2hil.store.export import Progress
    from m2s2hil.store.records import FrameRecord
    from m2s2hil.store.session import SessionStore

CARD = """---
configs:
- config_name: default
  data_files:
  - split: train
    path: data/train-*.parquet
- config_name: synthetic
  data_files:
  - split: train
    path: data/synthetic-*.parquet
---
# M2S2 hardware-in-the-loop captures

Written by `m2s2hil export --layout hf`. One row per frame.

- `raw` (uint16, H x W): the {bits}-bit sensor values, exact. Use this for training.
- `image`: an 8-bit view (`raw >> {shift}`, three identical channels), for browsing only.
- `mask`, `labels`: the simulator's truth label map and the twin's projected labels, where
  present (else null).
- `load_dataset("{name}", "synthetic")`: the synthetic domain (RGB render, ten band
  renders, mask), paired with these rows by satellite, build, elevation and nominal azimuth.
- `bands_nm`, `fwhm_nm`: the {n} band centres and widths in band order;
  `mosaic_layout`: the band index at each position of the {p}x{p} filter cell (row-major,
  from the top-left pixel), so band b of pixel (y, x) is `mosaic_layout[y % {p}][x % {p}]`.

```python
import numpy as np
from datasets import load_dataset
ds = load_dataset("{name}", split="train").with_format("numpy", columns=["raw", "lighting"])
raw = np.asarray(ds[0]["raw"], dtype=np.uint16)  # (H, W), exact DN 0..{full}
```
"""


class HfExportError(UsageError):
    """An hf export that cannot be done (``datasets`` missing, a file in the way)."""


def _features(h: int, w: int, n_bands: int, period: int) -> Any:
    from datasets import Array2D, Features, Image, Sequence, Value

    from m2s2hil.store.export import CSV_COLUMNS

    numeric = {"k", "azimuth_index", "frame", "bit_depth"}
    floats = {"nominal_azimuth_deg", "azimuth_deg", "turntable_readback_deg", "tilt_deg", "tilt_readback_deg",
              "exposure_s", "gain", "temperature_c", "timestamp", "exposure_factor"}
    cols: dict[str, Any] = {
        "raw": Array2D(shape=(h, w), dtype="uint16"),
        "image": Image(),
        "bands_nm": Sequence(Value("float32"), length=n_bands),
        "fwhm_nm": Sequence(Value("float32"), length=n_bands),
        "mosaic_layout": Array2D(shape=(period, period), dtype="int8"),
        "mask": Image(),
        "labels": Image(),
    }
    for c in CSV_COLUMNS:
        cols[c] = Value("int32") if c in numeric else Value("float64") if c in floats else Value("string")
    return Features(cols)


def _value(v: Any) -> Any:
    return None if v == "" else v


def export_hf(store: SessionStore, out: Path, frames: list[FrameRecord], rows: list[dict], *,
              overwrite: bool, progress: Progress | None = None) -> list[Path]:
    """Write ``data/train-<session>.parquet`` and the card (see the module docstring)."""
    require_datasets()
    from m2s2hil.store.export import LABELS_ROLE, MASK_ROLE, mosaic_png8

    m = store.rig.camera.model
    target = out / "data" / f"train-{store.session_id}.parquet"
    if target.exists() and not overwrite:
        raise HfExportError(f"{target} already exists; use overwrite to replace it")
    features = _features(m.height, m.width, m.n_bands, m.period)
    layout = np.asarray(m.layout, dtype=np.int8)

    def batches(size: int = 8) -> Iterator[dict[str, list]]:
        batch: dict[str, list] = {c: [] for c in features}
        for i, (fr, r) in enumerate(zip(frames, rows, strict=True)):
            raw, _ = store.read_raw(fr.event_id)
            ex = {"raw": raw, "image": {"bytes": encode_png(mosaic_png8(raw, m.bit_depth)), "path": None},
                  "bands_nm": list(m.bands_nm), "fwhm_nm": list(m.fwhm_nm), "mosaic_layout": layout,
                  **{c: _value(r[c]) for c in features if c in r}}
            for col, role in (("mask", MASK_ROLE), ("labels", LABELS_ROLE)):  # PNGs as stored
                ex[col] = {"bytes": store.read_file(fr.files[role]), "path": None} if role in fr.files \
                    else None
            for c in features:
                batch[c].append(ex.get(c))
            if progress is not None:
                progress.step()
            if len(batch["raw"]) == size or i == len(frames) - 1:
                yield batch
                batch = {c: [] for c in features}

    write_parquet(out, target, features, batches())
    card = out / "README.md"
    write_text_atomic(card, CARD.format(bits=m.bit_depth, shift=m.bit_depth - 8, n=m.n_bands, p=m.period,
                                        name=out.name or str(out), full=m.full_scale))
    return [target, card]


def require_datasets() -> None:
    if importlib.util.find_spec("datasets") is None:
        raise HfExportError("the hf export needs the datasets library: pip install 'm2s2hil[hf]'")


def write_parquet(out: Path, target: Path, features: Any, batches: Iterator[dict[str, list]]) -> None:
    """``batches`` through datasets' encoding into ``target``, written beside and renamed."""
    import datasets
    import pyarrow.parquet as pq

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".hf-export-", dir=out))
    try:
        part = tmp / target.name
        writer = None
        try:
            # A few frames at a time through datasets' own encoding (the features go into the
            # Parquet schema, so load_dataset restores them); memory stays at one batch.
            for batch in batches:
                table = datasets.Dataset.from_dict(batch, features=features).data.table
                if writer is None:
                    writer = pq.ParquetWriter(str(part), table.schema, compression="zstd")
                writer.write_table(table)
        finally:
            if writer is not None:
                writer.close()
        with open(part, "rb") as f:
            os.fsync(f.fileno())
        os.replace(part, target)
        fsync_dir(target.parent)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

