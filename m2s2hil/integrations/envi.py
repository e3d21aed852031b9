"""A session's cubes as ENVI files: ``<out>/<session_id>/<event>.hdr`` + ``.img`` per frame.

ENVI's header is the plain-text format every hyperspectral tool reads (ENVI, Spectral Python,
GDAL, QGIS): the image is band-sequential (BSQ: the cube's own band, y, x order), little-endian
float32, with the camera model's band centres as ``wavelength``, its ``fwhm`` and ``band names``,
so the spectral axis travels with the pixels. The frame's pose and lighting go in ``m2s2 ...``
fields (ENVI readers keep fields they do not know). Writing needs no library beyond numpy; the
``envi`` extra brings Spectral Python to read the files back.

Existing files are kept unless ``overwrite``; every file is written atomically.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m2s2hil.atomic import write_files_atomic
from m2s2hil.errors import UsageError
from m2s2hil.store.layout import safe_name
from m2s2hil.store.records import FrameRecord
from m2s2hil.store.session import SessionStore

#: ENVI's data type codes for the dtypes written here
_DATA_TYPE = {np.dtype("<f4"): 4, np.dtype("<u2"): 12}


class EnviExportError(UsageError):
    """An ENVI export that cannot be done (a file in the way, a cube of the wrong shape)."""


@dataclass
class EnviResult:
    out: Path
    images: int = 0
    files: list[Path] = field(default_factory=list)


def _list(values: Iterable[object]) -> str:
    return "{" + ", ".join(str(v) for v in values) + "}"


def _field(value: object) -> str:
    """A value safe inside an ENVI header (braces and newlines would end the field)."""
    return str(value).replace("{", "(").replace("}", ")").replace("\n", " ")


def band_names(bands_nm: Iterable[float]) -> list[str]:
    return [f"{nm:g} nm" for nm in bands_nm]


def envi_header(shape: tuple[int, int, int], dtype: np.dtype, bands_nm: tuple[float, ...],
                fwhm_nm: tuple[float, ...], extra: dict[str, object] | None = None) -> str:
    """The ``.hdr`` text of a BSQ cube of ``shape`` (bands, lines, samples)."""
    nb, lines, samples = shape
    if nb != len(bands_nm) or nb != len(fwhm_nm):
        raise EnviExportError(f"a cube of {nb} bands for a camera of {len(bands_nm)} bands")
    rows = [
        "ENVI",
        "description = {m2s2hil cube: radiance-like counts, dark subtracted, band-sequential}",
        f"samples = {samples}", f"lines = {lines}", f"bands = {nb}", "header offset = 0",
        "file type = ENVI Standard", f"data type = {_DATA_TYPE[np.dtype(dtype)]}",
        "interleave = bsq", "byte order = 0", "wavelength units = Nanometers",
        # repr: the shortest text that reads back as the same float
        f"wavelength = {_list(repr(float(w)) for w in bands_nm)}",
        f"fwhm = {_list(repr(float(w)) for w in fwhm_nm)}",
        f"band names = {_list(band_names(bands_nm))}",
    ]
    rows += [f"m2s2 {k} = {_field(v)}" for k, v in (extra or {}).items()]
    return "\n".join(rows) + "\n"


def _frame_fields(store: SessionStore, fr: FrameRecord) -> dict[str, object]:
    ev = fr.meta.get("event", {})
    keys = ("lighting", "elevation", "azimuth_deg", "tilt_deg", "exposure_s", "gain")
    return {"session id": store.session_id, "event id": fr.event_id, "satellite": store.sweep.satellite,
            "build": store.sweep.build, **{k.replace("_", " "): ev[k] for k in keys if k in ev}}


def export_envi(store: SessionStore, out: str | Path, *, overwrite: bool = False) -> EnviResult:
    """Write every frame's cube (:meth:`SessionStore.read_cube`) as an ENVI pair."""
    out = Path(out)
    folder = out / store.session_id
    frames = store.frames()
    # event ids hold dots: add the suffix, never replace one (Path.with_suffix would)
    pairs = [(folder / f"{safe_name(fr.event_id)}.hdr", folder / f"{safe_name(fr.event_id)}.img")
             for fr in frames]
    planned = [p for pair in pairs for p in pair]
    clash = [p for p in planned if p.exists()]
    if clash and not overwrite:
        raise EnviExportError(f"{len(clash)} file(s) already in {folder} (first: {clash[0].name}); "
                              "pass --overwrite to replace them")
    m = store.rig.camera.model
    result = EnviResult(out=out)
    for fr, (hdr_path, img_path) in zip(frames, pairs, strict=True):
        cube = np.ascontiguousarray(store.read_cube(fr.event_id), dtype="<f4")
        if cube.ndim != 3:
            raise EnviExportError(f"{store.session_id}/{fr.event_id}: cube of shape {cube.shape}")
        hdr = envi_header(cube.shape, cube.dtype, m.bands_nm, m.fwhm_nm, _frame_fields(store, fr))
        # the pair is written together: a reader never finds a header without its image
        write_files_atomic({img_path: cube.tobytes(), hdr_path: hdr.encode("ascii", "replace")})
        result.images += 1
        result.files += [hdr_path, img_path]
    return result
