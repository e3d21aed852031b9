"""Dark frames: master darks, the on-disk dark library, and the dark correction I = R − D.

The paper's correction is ``I_b = R_b − D_b`` with negatives clipped to zero. It is done with
OpenCV's saturating uint16 subtraction (``cv2.subtract``), which clips at 0 in the same pass, instead
of a round trip through int32 (6–16× slower on a 2048×2048 frame, science-notes.md and
docs/benchmarks.md). Raw pixels at full scale are reported in a boolean mask that travels with
the frame: a clipped pixel's true value is unknown, and demosaicing spreads it to its neighbours.

A master dark is the per-pixel mean (default) or median of N lens-capped frames taken at one
exposure and gain, within a temperature tolerance; averaging lowers the dark's own noise by √N.
The mean is rounded to uint16 so the correction stays an integer subtraction (≤ 0.5 DN error).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import tifffile

from m2s2hil.atomic import write_bytes_atomic
from m2s2hil.processing.errors import (
    DarkLibraryError,
    DarkMismatchError,
    DarkNotFoundError,
    FrameShapeError,
    ProcessingError,
)

Reduce = Literal["mean", "median"]
SIDECAR_FORMAT = "m2s2hil-dark/1"


@dataclass(frozen=True, eq=False)
class MasterDark:
    """A master dark frame and where it came from."""

    data: np.ndarray = field(repr=False)  # uint16 (H, W)
    created: str  # ISO 8601, UTC
    camera_serial: str
    n_frames: int
    exposure_s: float
    gain: float
    temperature_c: float
    reduce: Reduce = "mean"
    temperature_spread_c: float = 0.0  # max − min of the frames' sensor temperatures
    read_noise_dn: float | None = None  # median per-pixel temporal std of the N frames (N ≥ 2)

    @property
    def n(self) -> int:
        """Number of frames averaged (alias of ``n_frames``)."""
        return self.n_frames

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape

    def __post_init__(self) -> None:
        # The pixels are hashed once and the digest goes into every frame's metadata, so they
        # must not change afterwards: a read-only view makes an in-place edit fail loudly.
        view = np.asarray(self.data).view()
        view.flags.writeable = False
        object.__setattr__(self, "data", view)

    @cached_property
    def _digest(self) -> str:
        return hashlib.sha256(np.ascontiguousarray(self.data).data).hexdigest()

    def sha256(self) -> str:
        return self._digest

    def provenance(self) -> dict:
        """JSON-able description (no pixels) to record with every frame corrected by this dark."""
        # Built field by field: dataclasses.asdict would deep-copy the pixels on every frame.
        meta = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "data"}
        meta["shape"] = list(self.shape)
        meta["sha256"] = self.sha256()
        return meta

    def mismatch(self, exposure_s: float, gain: float, temperature_c: float, tolerance_c: float) -> list[str]:
        """What differs from the requested conditions (empty when the dark fits)."""
        out = []
        if not math.isclose(self.exposure_s, exposure_s, rel_tol=1e-6, abs_tol=1e-9):
            out.append(f"exposure {self.exposure_s:g} s ≠ {exposure_s:g} s")
        if not math.isclose(self.gain, gain, rel_tol=1e-6, abs_tol=1e-9):
            out.append(f"gain {self.gain:g} ≠ {gain:g}")
        if abs(self.temperature_c - temperature_c) > tolerance_c:
            out.append(
                f"temperature {self.temperature_c:.1f} °C is "
                f"{abs(self.temperature_c - temperature_c):.1f} °C "
                f"from {temperature_c:.1f} °C (tolerance {tolerance_c:g} °C)"
            )
        return out


def build_master_dark(
    frames: Sequence[np.ndarray] | np.ndarray,
    *,
    reduce: Reduce = "mean",
    exposure_s: float,
    gain: float,
    temperature_c: float | Sequence[float],
    camera: str = "unknown",
    tolerance_c: float = 2.0,
    created: datetime | None = None,
) -> MasterDark:
    """Reduce N lens-capped uint16 frames to a master dark.

    ``temperature_c`` is either the sensor temperature of the whole series or one value per frame;
    per-frame temperatures that spread over more than ``tolerance_c`` are refused (the dark current
    roughly doubles every 6–8 °C, so such a series mixes different darks).
    """
    stack = _stack(frames)
    n = stack.shape[0]
    temps = np.atleast_1d(np.asarray(temperature_c, dtype=np.float64))
    if temps.size not in (1, n):
        raise ProcessingError(f"got {temps.size} temperatures for {n} dark frames")
    spread = float(temps.max() - temps.min())
    if spread > tolerance_c:
        raise DarkMismatchError(
            f"dark frames span {spread:.1f} °C of sensor temperature (tolerance {tolerance_c:g} °C); "
            "wait for the sensor to settle and take the series again",
            wanted={"tolerance_c": tolerance_c},
        )
    if exposure_s <= 0:
        raise ProcessingError(f"exposure_s must be positive, got {exposure_s}")
    if reduce == "mean":
        red = stack.mean(axis=0, dtype=np.float64)
    elif reduce == "median":
        red = np.median(stack, axis=0)
    else:
        raise ProcessingError(f"reduce must be 'mean' or 'median', not {reduce!r}")
    data = np.clip(np.rint(red), 0, np.iinfo(np.uint16).max).astype(np.uint16)
    noise = None
    if n >= 2:
        sub = stack[:, ::4, ::4].astype(np.float32)  # a 1/16 sample is plenty for a median
        noise = float(np.median(sub.std(axis=0, ddof=1)))
    when = (created or datetime.now(UTC)).astimezone(UTC)
    return MasterDark(
        data=data,
        created=when.isoformat(timespec="seconds"),
        camera_serial=str(camera),
        n_frames=n,
        exposure_s=float(exposure_s),
        gain=float(gain),
        temperature_c=float(temps.mean()),
        reduce=reduce,
        temperature_spread_c=spread,
        read_noise_dn=noise,
    )


def _stack(frames: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        frames = frames[None]
    if len(frames) == 0:
        raise ProcessingError("a master dark needs at least one frame")
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1:
        raise FrameShapeError(f"dark frames differ in shape: {sorted(shapes)}")
    stack = np.asarray(frames)
    if stack.ndim != 3:
        raise FrameShapeError(f"dark frames must be 2-D, got shape {stack.shape[1:]}")
    if stack.dtype != np.uint16:
        raise FrameShapeError(f"dark frames must be uint16 raw frames, got {stack.dtype}")
    return stack


def subtract_dark(
    raw: np.ndarray,
    dark: MasterDark | np.ndarray,
    *,
    out: np.ndarray | None = None,
    sat_mask_out: np.ndarray | None = None,
    full_scale: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``(I, saturated)``: I = max(R − D, 0) in uint16, saturated = R ≥ full_scale (bool).

    ``out`` and ``sat_mask_out`` are reused when given (no allocation per frame); ``out`` may be
    ``raw`` itself (in-place correction) but not the dark.
    """
    d = dark.data if isinstance(dark, MasterDark) else dark
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise FrameShapeError(f"raw frame must be a 2-D uint16 array, got {raw.dtype} {raw.shape}")
    if d.shape != raw.shape or d.dtype != np.uint16:
        raise FrameShapeError(f"dark {d.dtype} {d.shape} does not fit raw frame {raw.dtype} {raw.shape}")
    if out is None:
        out = np.empty_like(raw)
    elif out.shape != raw.shape or out.dtype != np.uint16:
        raise FrameShapeError(f"out must be uint16 {raw.shape}, got {out.dtype} {out.shape}")
    elif np.may_share_memory(out, d):
        raise FrameShapeError("out must not be the dark frame's own buffer")
    if sat_mask_out is None:
        sat_mask_out = np.empty(raw.shape, dtype=bool)
    elif sat_mask_out.shape != raw.shape or sat_mask_out.dtype != np.bool_:
        raise FrameShapeError(f"sat_mask_out must be bool {raw.shape}, got {sat_mask_out.dtype}")
    np.greater_equal(raw, full_scale, out=sat_mask_out)  # before an in-place correction changes raw
    cv2.subtract(raw, d, dst=out)  # saturating: R − D below 0 becomes 0, no widening
    return out, sat_mask_out


# --- the dark library -------------------------------------------------------------------------


class DarkLibrary:
    """Master darks on disk, one uint16 TIFF + one JSON sidecar each, keyed by exposure, gain, temperature.

    Files are written to a temporary name, fsynced and renamed, and the sidecar records the
    TIFF's sha256, checked on every load.
    """

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)

    def put(self, dark: MasterDark) -> Path:
        self.root.mkdir(parents=True, exist_ok=True)
        stamp = dark.created.replace(":", "").replace("-", "").replace("+0000", "Z")
        key = (
            f"dark_{_safe(dark.camera_serial)}_{dark.exposure_s * 1e6:.0f}us_g{dark.gain:g}"
            f"_T{dark.temperature_c:+.1f}_{stamp}"
        )
        tif = self.root / f"{key}.tiff"
        buf = _tiff_bytes(dark.data)
        write_bytes_atomic(tif, buf)
        meta = dark.provenance()
        meta.update(format=SIDECAR_FORMAT, file=tif.name, file_sha256=hashlib.sha256(buf).hexdigest())
        write_bytes_atomic(tif.with_suffix(".json"), json.dumps(meta, indent=2, sort_keys=True).encode())
        return tif

    def entries(self) -> list[dict]:
        """Provenance of every dark in the library (no pixels loaded)."""
        out = []
        for side in sorted(self.root.glob("dark_*.json")):
            try:
                meta = json.loads(side.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise DarkLibraryError(f"{side}: unreadable sidecar ({exc})") from None
            if meta.get("format") != SIDECAR_FORMAT:
                raise DarkLibraryError(f"{side}: not a dark sidecar (format {meta.get('format')!r})")
            meta["_sidecar"] = str(side)
            out.append(meta)
        return out

    def get(
        self,
        exposure_s: float,
        gain: float,
        temperature_c: float,
        tolerance_c: float = 2.0,
        allow_mismatch: bool = False,
        *,
        shape: tuple[int, int] | None = None,
    ) -> MasterDark:
        """The dark taken at this exposure and gain whose temperature is closest (newest on ties).

        A dark from another exposure, gain, or more than ``tolerance_c`` away is a
        ``DarkMismatchError`` unless ``allow_mismatch``; then the closest one is returned and its
        provenance says what it was taken at.
        """
        entries = [e for e in self.entries() if shape is None or tuple(e["shape"]) == tuple(shape)]
        wanted = {
            "exposure_s": exposure_s,
            "gain": gain,
            "temperature_c": temperature_c,
            "tolerance_c": tolerance_c,
        }
        if not entries:
            raise DarkNotFoundError(f"dark library {self.root} holds no dark frames", wanted=wanted)

        def distance(e: dict) -> tuple:
            exp_off = abs(math.log(max(e["exposure_s"], 1e-12) / max(exposure_s, 1e-12)))
            gain_off = abs(e["gain"] - gain)
            return (
                exp_off > 1e-6 or gain_off > 1e-9,
                exp_off,
                gain_off,
                abs(e["temperature_c"] - temperature_c),
                _neg_time(e["created"]),
            )

        entries.sort(key=distance)
        best = entries[0]
        problems = _meta_mismatch(best, exposure_s, gain, temperature_c, tolerance_c)
        if problems and not allow_mismatch:
            near = [
                {k: e[k] for k in ("exposure_s", "gain", "temperature_c", "created")} for e in entries[:3]
            ]
            raise DarkMismatchError(
                f"no dark for exposure {exposure_s:g} s, gain {gain:g}, {temperature_c:.1f} °C "
                f"± {tolerance_c:g} °C in {self.root}; closest: {'; '.join(problems)} "
                "(take a new dark series, or pass allow_mismatch=True to use it anyway)",
                wanted=wanted,
                available=near,
            )
        return self._load(best)

    def _load(self, meta: dict) -> MasterDark:
        tif = Path(meta["_sidecar"]).with_name(meta["file"])
        try:
            buf = tif.read_bytes()
        except OSError as exc:
            raise DarkLibraryError(f"{tif}: cannot read ({exc})") from None
        if hashlib.sha256(buf).hexdigest() != meta["file_sha256"]:
            raise DarkLibraryError(f"{tif}: checksum does not match its sidecar (file damaged or replaced)")
        data = tifffile.imread(tif)
        if data.dtype != np.uint16 or list(data.shape) != list(meta["shape"]):
            raise DarkLibraryError(
                f"{tif}: holds {data.dtype} {data.shape}, sidecar says uint16 {meta['shape']}"
            )
        return MasterDark(
            data=data,
            created=meta["created"],
            camera_serial=meta["camera_serial"],
            n_frames=int(meta["n_frames"]),
            exposure_s=float(meta["exposure_s"]),
            gain=float(meta["gain"]),
            temperature_c=float(meta["temperature_c"]),
            reduce=meta["reduce"],
            temperature_spread_c=float(meta.get("temperature_spread_c", 0.0)),
            read_noise_dn=meta.get("read_noise_dn"),
        )


def _meta_mismatch(meta: dict, exposure_s: float, gain: float, temperature_c: float, tol: float) -> list[str]:
    probe = MasterDark(
        data=np.zeros((1, 1), np.uint16),
        created=meta["created"],
        camera_serial=meta["camera_serial"],
        n_frames=meta["n_frames"],
        exposure_s=meta["exposure_s"],
        gain=meta["gain"],
        temperature_c=meta["temperature_c"],
    )
    return probe.mismatch(exposure_s, gain, temperature_c, tol)


def _neg_time(created: str) -> float:
    try:
        return -datetime.fromisoformat(created).timestamp()
    except ValueError:
        return 0.0


def _safe(text: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-." else "_" for ch in text) or "unknown"


def _tiff_bytes(data: np.ndarray) -> bytes:
    import io

    bio = io.BytesIO()
    tifffile.imwrite(bio, data, photometric="minisblack")
    return bio.getvalue()
