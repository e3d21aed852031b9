"""Camera calibration: MSFA layout, band crosstalk and the white reference.

The vendor keeps the TOUCAN's calibration in an XML file of its own; m2s2hil reads a JSON file of
its own (``format = "m2s2hil-calibration/1"``) that can carry:

- ``layout``: the real n×n band layout (overrides the camera model's documented default);
- ``crosstalk``: the bands×bands mixing matrix M of the filter array, ``measured = M · true``
  per pixel (row b = how much of each true band the band-b pixels see). The correction applies
  M⁻¹; a near-singular M is refused.
- ``white_reference``: ``{"file": "white.tiff", "reflectance": 0.99 or [per band]}``, a
  dark-subtracted mosaic (float32 or uint16, usually the mean of N frames) of a white panel
  filling the view under the capture lighting. It is demosaiced once with the frame's method
  (super-pixel stays super-pixel; full-resolution methods use WB, which is exact on such a
  smooth field), crosstalk-corrected, and turned into a per-pixel, per-band gain
  ``reflectance / white`` that flattens vignetting and the illuminant's spectrum and maps the
  frame to reflectance.

Order of operations on a cube x: ``ρ = gain ⊙ (M⁻¹ x)`` with ``gain = ρ_white / (M⁻¹ white)``.
For a distortion measured = M · (F ⊙ E ⊙ ρ) with a band-independent spatial field F (vignetting,
uneven lighting) and a per-band illuminant E this returns ρ exactly.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tifffile

from m2s2hil.atomic import write_bytes_atomic
from m2s2hil.processing import kernels
from m2s2hil.processing.errors import CalibrationError
from m2s2hil.processing.mosaic import MosaicLayout

FORMAT = "m2s2hil-calibration/1"
MAX_CONDITION = 1e3  # a crosstalk matrix worse than this amplifies noise beyond use


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    source: str = "<in memory>"
    camera_serial: str | None = None
    layout: tuple[tuple[int, ...], ...] | None = None
    crosstalk: np.ndarray | None = field(default=None, repr=False)  # (bands, bands) mixing matrix M
    white_mosaic: np.ndarray | None = field(default=None, repr=False)  # (H, W) float32
    white_reflectance: np.ndarray | None = field(default=None, repr=False)  # (bands,)

    def correction_matrix(self) -> np.ndarray | None:
        if self.crosstalk is None:
            return None
        return np.linalg.inv(self.crosstalk.astype(np.float64)).astype(np.float32)

    def provenance(self) -> dict:
        out: dict = {"source": self.source, "camera_serial": self.camera_serial}
        if self.crosstalk is not None:
            out["crosstalk_sha256"] = hashlib.sha256(self.crosstalk.astype(np.float64).tobytes()).hexdigest()
        if self.white_mosaic is not None:
            out["white_sha256"] = hashlib.sha256(self.white_mosaic.tobytes()).hexdigest()
        return out


def load_calibration(path: str | Path, camera=None) -> CameraCalibration:
    """Read and validate a calibration file; ``camera`` (a ``CameraModel``) checks bands and sensor size."""
    p = Path(path)
    src = str(p)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibrationError(src, "", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(src, "", f"cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(src, "", f"not valid JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CalibrationError(
            src,
            "format",
            f"expected {FORMAT!r}, got {data.get('format') if isinstance(data, dict) else data!r}",
        )
    unknown = set(data) - {"format", "camera_serial", "bands_nm", "layout", "crosstalk", "white_reference"}
    if unknown:
        raise CalibrationError(src, sorted(unknown)[0], "unknown key")
    n_bands = camera.n_bands if camera is not None else None

    if "bands_nm" in data:
        bands = data["bands_nm"]
        if not isinstance(bands, list) or not all(isinstance(b, int | float) for b in bands):
            raise CalibrationError(src, "bands_nm", "must be a list of numbers")
        if n_bands is not None and len(bands) != n_bands:
            raise CalibrationError(src, "bands_nm", f"{len(bands)} bands, the camera model has {n_bands}")
        if camera is not None and not np.allclose(bands, camera.bands_nm, atol=2.0):
            raise CalibrationError(
                src, "bands_nm", f"{bands} differ from the camera model's {list(camera.bands_nm)}"
            )
        n_bands = len(bands)

    layout = None
    if "layout" in data:
        try:
            lay = MosaicLayout.from_pattern(data["layout"], n_bands)
        except Exception as exc:  # LayoutError, or numpy failing on a ragged list
            raise CalibrationError(src, "layout", str(exc)) from None
        layout = lay.pattern
        n_bands = lay.n_bands
        if camera is not None and (camera.width % lay.n or camera.height % lay.n):
            raise CalibrationError(
                src, "layout", f"{lay.n}×{lay.n} does not tile {camera.width}×{camera.height}"
            )

    crosstalk = None
    if "crosstalk" in data:
        try:
            m = np.array(data["crosstalk"], dtype=np.float64)
        except (TypeError, ValueError):
            raise CalibrationError(src, "crosstalk", "must be a square list of lists of numbers") from None
        if m.ndim != 2 or m.shape[0] != m.shape[1] or (n_bands is not None and m.shape[0] != n_bands):
            want = f"{n_bands}×{n_bands}" if n_bands else "square"
            raise CalibrationError(src, "crosstalk", f"must be {want}, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise CalibrationError(src, "crosstalk", "contains NaN or infinity")
        cond = np.linalg.cond(m)
        if not np.isfinite(cond) or cond > MAX_CONDITION:
            raise CalibrationError(src, "crosstalk", f"matrix is near-singular (condition number {cond:.3g})")
        crosstalk = m
        n_bands = m.shape[0]

    white = refl = None
    if "white_reference" in data:
        wr = data["white_reference"]
        if not isinstance(wr, dict) or "file" not in wr:
            raise CalibrationError(src, "white_reference", 'must be {"file": ..., "reflectance": ...}')
        wpath = (p.parent / wr["file"]).resolve()
        try:
            buf = wpath.read_bytes()
        except OSError as exc:
            raise CalibrationError(src, "white_reference.file", f"cannot read {wpath}: {exc}") from None
        if "sha256" in wr and hashlib.sha256(buf).hexdigest() != wr["sha256"]:
            raise CalibrationError(src, "white_reference.sha256", f"{wpath} does not match its checksum")
        try:
            white = tifffile.imread(wpath)
        except Exception as exc:  # tifffile raises many types for a damaged file
            raise CalibrationError(
                src, "white_reference.file", f"{wpath} is not a readable TIFF: {exc}"
            ) from None
        if white.ndim != 2:
            raise CalibrationError(
                src, "white_reference.file", f"must be a 2-D mosaic, got shape {white.shape}"
            )
        if camera is not None and white.shape != (camera.height, camera.width):
            raise CalibrationError(
                src,
                "white_reference.file",
                f"is {white.shape[1]}×{white.shape[0]}, sensor is {camera.width}×{camera.height}",
            )
        white = white.astype(np.float32)
        rho = wr.get("reflectance", 1.0)
        refl = np.atleast_1d(np.asarray(rho, dtype=np.float64))
        if n_bands is not None and refl.size == 1:
            refl = np.full(n_bands, refl[0])
        if (n_bands is not None and refl.size != n_bands) or not np.all((refl > 0) & (refl <= 1.5)):
            raise CalibrationError(
                src, "white_reference.reflectance", f"need one value in (0, 1.5] or {n_bands}, got {rho!r}"
            )
    return CameraCalibration(
        source=src,
        camera_serial=data.get("camera_serial"),
        layout=layout,
        crosstalk=crosstalk,
        white_mosaic=white,
        white_reflectance=refl,
    )


def save_calibration(
    path: str | Path, calib: CameraCalibration, *, bands_nm: list[float] | None = None,
    provenance: dict | None = None,
) -> Path:
    """Write ``calib`` as ``path`` (JSON) plus ``<stem>_white.tiff``; both written atomically.
    ``provenance``: how the white reference was captured (recorded beside it)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    doc: dict = {"format": FORMAT}
    if calib.camera_serial is not None:
        doc["camera_serial"] = calib.camera_serial
    if bands_nm is not None:
        doc["bands_nm"] = list(bands_nm)
    if calib.layout is not None:
        doc["layout"] = [list(r) for r in calib.layout]
    if calib.crosstalk is not None:
        doc["crosstalk"] = calib.crosstalk.tolist()
    if calib.white_mosaic is not None:
        wname = f"{p.stem}_white.tiff"
        import io

        bio = io.BytesIO()
        tifffile.imwrite(bio, calib.white_mosaic.astype(np.float32), photometric="minisblack")
        write_bytes_atomic(p.parent / wname, bio.getvalue())
        refl = calib.white_reflectance if calib.white_reflectance is not None else [1.0]
        doc["white_reference"] = {
            "file": wname,
            "reflectance": [float(v) for v in np.atleast_1d(refl)],
            "sha256": hashlib.sha256(bio.getvalue()).hexdigest(),
        }
        if provenance is not None:
            doc["white_reference"]["provenance"] = provenance
    write_bytes_atomic(p, json.dumps(doc, indent=2).encode())
    return p


class CalibrationStep:
    """Crosstalk correction and white-reference normalisation applied in place to a demosaiced cube."""

    def __init__(self, calib: CameraCalibration, demosaicer) -> None:
        from m2s2hil.processing.demosaic import get_demosaicer

        self.calibration = calib
        self.warnings: list[str] = []
        nb, h, _ = demosaicer.out_shape
        self._m = calib.correction_matrix()
        if self._m is not None and self._m.shape[0] != nb:
            raise CalibrationError(calib.source, "crosstalk", f"{self._m.shape[0]} bands, the cube has {nb}")
        self._nblocks = max(1, min(h, 16))
        self._gain = None
        self.white_band_levels: np.ndarray | None = None  # raw band means of the white (PPID's balancing)
        if calib.white_mosaic is not None:
            if calib.white_mosaic.shape != demosaicer.shape:
                raise CalibrationError(
                    calib.source,
                    "white_reference.file",
                    f"mosaic is {calib.white_mosaic.shape}, frames are {demosaicer.shape}",
                )
            how = "superpixel" if not demosaicer.full_resolution else "wb"
            wcube = (
                get_demosaicer(how, demosaicer.layout, demosaicer.shape).process(calib.white_mosaic).copy()
            )
            self.white_band_levels = wcube.mean(axis=(1, 2), dtype=np.float64)
            if self._m is not None:
                kernels.mix_kernel(wcube, self._m, np.zeros((0, 0, 0), np.float32), self._nblocks)
            refl = calib.white_reflectance if calib.white_reflectance is not None else np.ones(nb)
            if len(refl) != nb:
                raise CalibrationError(
                    calib.source, "white_reference.reflectance", f"{len(refl)} values for {nb} bands"
                )
            floor = 1e-3 * float(np.nanmax(wcube)) if wcube.size else 0.0
            dark = wcube <= floor
            if dark.any():
                self.warnings.append(
                    f"white reference is (near) zero at {int(dark.sum())} cube samples; "
                    "reflectance set to 0 there"
                )
            with np.errstate(divide="ignore", invalid="ignore"):
                gain = np.where(dark, 0.0, refl[:, None, None] / wcube)
            self._gain = gain.astype(np.float32)

    @property
    def active(self) -> bool:
        return self._m is not None or self._gain is not None

    def apply(self, cube: np.ndarray) -> np.ndarray:
        if self._m is not None:
            gain = self._gain if self._gain is not None else np.zeros((0, 0, 0), np.float32)
            kernels.mix_kernel(cube, self._m, gain, self._nblocks)
        elif self._gain is not None:
            np.multiply(cube, self._gain, out=cube)
        return cube
