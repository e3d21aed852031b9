"""Encoding and decoding of the session's image files (in memory, so they can be hashed and
written atomically).

Two formats, chosen by the rig's ``[storage] format`` (the ``compress`` arguments below);
readers accept both, since every TIFF says how it is compressed:

- ``compressed`` (default): raw mosaic and master dark as 2-D uint16 TIFF, deflate (TIFF
  compression 8, level 1) in 64-row strips, no predictor. Chosen by measurement on simulated
  frames of every lighting (``benchmarks/bench_storage.py``, docs/benchmarks.md): 2.8×
  smaller than uncompressed (about 3 MB a 2048² frame); the strips are compressed by Intel
  ISA-L (16 ms a frame, against 23 ms for libdeflate and 65 ms for zlib at the same level);
  zstd is 5 % smaller but OpenCV cannot read it (nor many GDAL/libtiff builds), and
  horizontal differencing (the predictor) made these noise-dominated 10-bit frames *larger*.
  Readers: tifffile, Pillow (``Image.open`` → mode ``I;16``), OpenCV
  (``cv2.imread(path, cv2.IMREAD_UNCHANGED)``), anything on libtiff. The master dark is the
  rounded mean of N frames (``processing.dark.build_master_dark`` rounds it to whole DN,
  the precision the correction uses), so uint16 stores it exactly; a master that is not
  whole numbers stays float32.
- ``legacy`` (before 0.2): uncompressed raw, float32 master dark, float32 cube always stored.

- Cube (when stored: legacy sessions, ``[storage] cubes = true``, calibrated frames): one
  TIFF page per band, shape (bands, height, width), float32 (or uint16), deflate unless
  legacy. float64 is stored as float32.
- Metadata as JSON in the ImageDescription tag. A frame's metadata is encoded once
  (:class:`EncodedJSON`) and the same text goes into the TIFF and the journal.
- Preview: JPEG (quality 90) in the compressed format, PNG in the legacy one; exported mosaics
  and truth labels: PNG through OpenCV (8-bit gray/RGB, 16-bit gray).
"""

from __future__ import annotations

import io
import json
import math
import re
from typing import Any

import cv2
import imagecodecs
import numpy as np
import tifffile

try:  # Intel ISA-L's deflate, the fastest writer of the raw frames' strips (see _deflate_strips)
    from isal import isal_zlib as _isal_zlib
except ImportError:  # pragma: no cover - platforms without an isal wheel
    _isal_zlib = None

from m2s2hil.errors import UsageError


class InvalidImage(UsageError):
    """An array that does not fit the file it is meant for (dtype, shape)."""


def json_default(o: Any) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, set | frozenset):
        return sorted(o)
    if hasattr(o, "model_dump"):
        return o.model_dump(mode="json")
    return str(o)


def _finite(o: Any) -> Any:
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    return o


class EncodedJSON(str):
    """JSON text already encoded by :func:`dumps`; ``dumps`` passes it through unchanged."""


def dumps(obj: Any) -> str:
    """Strict JSON (NaN and infinities become null, numpy scalars plain numbers)."""
    if isinstance(obj, EncodedJSON):
        return obj
    try:
        return json.dumps(obj, default=json_default, sort_keys=True, allow_nan=False)
    except ValueError:
        plain = json.loads(json.dumps(obj, default=json_default))
        return json.dumps(_finite(plain), sort_keys=True, allow_nan=False)


#: TIFF compression of the ``compressed`` format (see the module docstring for the measurement).
COMPRESSION = "zlib"
COMPRESSION_ARGS = {"level": 1}
#: Rows per TIFF strip of a compressed 2-D image: 256 KiB of a 2048-wide uint16 row block,
#: what tifffile chooses itself, so readers can decode strips in parallel or read a band of rows.
STRIP_BYTES = 1 << 18


def _deflate_strips(arr: np.ndarray) -> tuple[int, list[bytes]]:
    """A 2-D little-endian array cut into row strips, each a zlib (TIFF deflate) stream.

    Compressed with Intel ISA-L (``isal``) at its level 1: 16 ms a 2048² frame against 23 ms
    for libdeflate level 1 (tifffile's own), 3 % larger (docs/benchmarks.md). The streams are
    plain deflate, so every TIFF reader opens the file; without ``isal`` the strips go through
    imagecodecs' libdeflate at level 1 instead.
    """
    rows = max(1, min(arr.shape[0], STRIP_BYTES // max(1, arr.shape[1] * arr.itemsize)))
    chunks = [arr[r:r + rows] for r in range(0, arr.shape[0], rows)]
    if _isal_zlib is not None:
        return rows, [_isal_zlib.compress(c, 1) for c in chunks]
    return rows, [imagecodecs.deflate_encode(c, level=1) for c in chunks]  # zlib-wrapped


def _tiff(arr: np.ndarray, description: dict | EncodedJSON, *, compress: bool = False) -> bytes:
    buf = io.BytesIO()
    # metadata=None: tifffile adds nothing of its own to our description.
    # The array's shape leads the JSON: tifffile reads any JSON description holding a "shape"
    # key (ours may nest one, e.g. a dark's provenance) as its own shaped-array metadata, so
    # a correct top-level shape keeps stored files readable by plain tifffile.imread.
    shape = json.dumps(list(arr.shape))
    if isinstance(description, EncodedJSON):  # has no top-level "shape" (see frame_meta)
        body = description[1:]
        text = f'{{"shape": {shape}' + (", " + body if body.strip() != "}" else "}")
    else:
        text = dumps({"shape": list(arr.shape), **{k: v for k, v in description.items() if k != "shape"}})
    common: dict[str, Any] = {"description": text, "metadata": None, "photometric": "minisblack"}
    if compress and arr.ndim == 2 and arr.size:
        # Raw mosaics and darks: strips compressed here, written as they are (tifffile's
        # documented iterator-of-bytes input) with the compression tag they were made for.
        le = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
        rows, strips = _deflate_strips(le)
        tifffile.imwrite(buf, iter(strips), shape=le.shape, dtype=le.dtype, byteorder="<",
                         compression=COMPRESSION, rowsperstrip=rows, **common)
    else:
        kw: dict[str, Any] = {"compression": COMPRESSION, "compressionargs": COMPRESSION_ARGS}
        tifffile.imwrite(buf, arr, **common, **(kw if compress else {}))
    return buf.getvalue()


def encode_tiff(arr: np.ndarray, description: dict) -> bytes:
    """Any numeric array as TIFF, dtype kept."""
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "buif":
        raise InvalidImage(f"TIFF needs a numeric array, got {_desc(arr)}")
    return _tiff(np.ascontiguousarray(arr), description)


def encode_raw(raw: np.ndarray, description: dict | EncodedJSON, shape: tuple[int, int] | None = None, *,
               compress: bool = True) -> bytes:
    if not isinstance(raw, np.ndarray) or raw.dtype != np.uint16 or raw.ndim != 2:
        raise InvalidImage(f"raw mosaic must be a 2-D uint16 array, got {_desc(raw)}")
    if shape is not None and raw.shape != shape:
        raise InvalidImage(f"raw mosaic is {raw.shape[0]}x{raw.shape[1]}, the camera gives "
                           f"{shape[0]}x{shape[1]} (height x width)")
    return _tiff(np.ascontiguousarray(raw), description, compress=compress)


def normalise_cube(cube: np.ndarray, n_bands: int) -> np.ndarray:
    """(bands, H, W) in float32 or uint16; (H, W, bands) is transposed."""
    if not isinstance(cube, np.ndarray) or cube.ndim != 3:
        raise InvalidImage(f"cube must be a 3-D array, got {_desc(cube)}")
    if cube.shape[0] != n_bands:
        if cube.shape[2] != n_bands:
            raise InvalidImage(f"cube {cube.shape} has no axis of {n_bands} bands")
        cube = np.moveaxis(cube, 2, 0)
    if cube.dtype == np.float64:
        cube = cube.astype(np.float32)
    if cube.dtype not in (np.float32, np.uint16):
        raise InvalidImage(f"cube dtype must be float32 or uint16, got {cube.dtype}")
    return np.ascontiguousarray(cube)


def encode_cube(cube: np.ndarray, description: dict, n_bands: int, *, compress: bool = False) -> bytes:
    return _tiff(normalise_cube(cube, n_bands), description, compress=compress)


def dark_array(master: np.ndarray, *, compress: bool) -> np.ndarray:
    """The master dark as stored: uint16 when its values are whole DN in range (the master
    darks processing builds are), else float32; always float32 in the legacy format."""
    if compress and master.dtype.kind in "ui" and master.size and master.min() >= 0 and master.max() <= 65535:
        return np.ascontiguousarray(master, dtype=np.uint16)
    if compress and master.dtype.kind == "f" and master.size:
        whole = np.rint(master)
        if np.array_equal(whole, master) and whole.min() >= 0 and whole.max() <= 65535:
            return whole.astype(np.uint16)
    return np.ascontiguousarray(master, dtype=np.float32)


def encode_dark(master: np.ndarray, description: dict, shape: tuple[int, int] | None = None, *,
                compress: bool = True) -> bytes:
    if not isinstance(master, np.ndarray) or master.ndim != 2 or master.dtype.kind not in "uif":
        raise InvalidImage(f"master dark must be a 2-D numeric array, got {_desc(master)}")
    if shape is not None and master.shape != shape:
        raise InvalidImage(f"master dark is {master.shape}, the camera gives {shape}")
    return _tiff(dark_array(master, compress=compress), description, compress=compress)


def encode_png(img: np.ndarray) -> bytes:
    """8-bit gray or RGB (H, W, 3), or 16-bit gray, to PNG bytes."""
    if not isinstance(img, np.ndarray):
        raise InvalidImage(f"image must be an array, got {_desc(img)}")
    if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif not ((img.dtype in (np.uint8, np.uint16)) and img.ndim == 2):
        raise InvalidImage(f"PNG needs uint8 gray/RGB or uint16 gray, got {_desc(img)}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise InvalidImage("OpenCV could not encode the PNG")
    return buf.tobytes()


#: JPEG quality of the compressed format's previews: 8-bit display images, made again from raw +
#: dark whenever needed, so lossless PNG (0.41 MB, 6 ms a 512² preview) buys nothing; quality 90
#: 4:4:4 is 0.05 MB in 0.8 ms, 2 DN from the PNG on average (docs/benchmarks.md).
PREVIEW_JPEG_QUALITY = 90


def encode_jpeg(rgb: np.ndarray, quality: int = PREVIEW_JPEG_QUALITY) -> bytes:
    """8-bit RGB (H, W, 3) to baseline JPEG bytes."""
    if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
        raise InvalidImage(f"JPEG needs uint8 RGB (H, W, 3), got {_desc(rgb)}")
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    # 4:4:4 (no chroma subsampling): colour stays sharp at material edges, for 1.5x the bytes
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality),
              cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    ok, buf = cv2.imencode(".jpg", bgr, params)
    if not ok:
        raise InvalidImage("OpenCV could not encode the JPEG")
    return buf.tobytes()


def preview_file(name: str, rgb: np.ndarray, *, compress: bool) -> tuple[str, bytes]:
    """A frame's preview file (relative path, bytes): JPEG in the compressed format, PNG in the legacy one."""
    if compress:
        return f"frames/{name}.preview.jpg", encode_jpeg(rgb)
    return f"frames/{name}.preview.png", encode_png(rgb)


#: File roles of a frame that ``extra`` files cannot take.
RESERVED_ROLES = ("raw", "cube", "preview")


def extra_file(name: str, role: str, arr: np.ndarray, event_id: str) -> tuple[str, bytes]:
    """A frame's extra 2-D array (or 8-bit RGB image) as a file (relative path, bytes): integer
    arrays that fit 8 or 16 bits and RGB images as PNG, others as TIFF."""
    if role in RESERVED_ROLES or not re.fullmatch(r"[a-z][a-z0-9_]{0,31}", role):
        raise UsageError(f"invalid extra file role {role!r}: lower-case letters, digits, '_'; "
                         f"not {', '.join(RESERVED_ROLES)}")
    if isinstance(arr, np.ndarray) and arr.ndim == 3 and arr.shape[2] == 3 and arr.dtype == np.uint8:
        return f"frames/{name}.{role}.png", encode_png(arr)  # an 8-bit RGB image (a synthetic render)
    if not isinstance(arr, np.ndarray) or arr.ndim != 2:
        raise InvalidImage(f"extra {role!r} must be a 2-D array (or 8-bit RGB)")
    if arr.dtype.kind in "ui" or arr.dtype == np.bool_:
        lo, hi = (int(arr.min()), int(arr.max())) if arr.size else (0, 0)
        for dt in (np.uint8, np.uint16):
            if lo >= 0 and hi <= np.iinfo(dt).max:
                return f"frames/{name}.{role}.png", encode_png(arr.astype(dt))
    return f"frames/{name}.{role}.tiff", encode_tiff(arr, {"role": role, "event_id": event_id})


def image_media_type(path: str) -> str:
    """The media type of a stored preview or label image, from its name."""
    return "image/jpeg" if path.lower().endswith((".jpg", ".jpeg")) else "image/png"


def decode_image(data: bytes) -> np.ndarray:
    """PNG (or JPEG) bytes to an array as stored (RGB order for colour); InvalidImage if unreadable."""
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise InvalidImage("not a readable PNG or JPEG")
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)
    elif arr.ndim == 3 and arr.shape[2] == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGBA)
    return arr


def decode_tiff(data: bytes) -> tuple[np.ndarray, dict]:
    """TIFF bytes to (array, description JSON); a non-JSON description gives {}."""
    # is_shaped=False: our JSON descriptions may hold a nested "shape" key (a dark's
    # provenance), which tifffile would otherwise take for its own shaped-series metadata.
    with tifffile.TiffFile(io.BytesIO(data), is_shaped=False) as tf:
        arr = tf.asarray()
        desc = tf.pages[0].description
    try:
        meta = json.loads(desc) if desc else {}
    except json.JSONDecodeError:
        meta = {}
    if not isinstance(meta, dict):
        return arr, {}
    if meta.get("shape") == list(arr.shape):
        del meta["shape"]  # written by _tiff for tifffile's sake, not part of the metadata
    return arr, meta


def _desc(x: Any) -> str:
    if isinstance(x, np.ndarray):
        return f"{x.dtype} array of shape {x.shape}"
    return type(x).__name__
