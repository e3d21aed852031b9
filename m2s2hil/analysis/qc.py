"""Capture-time quality control: a stability score and flags for every processed frame.

Why not the paper's mTC? With a pixel-wise predictor (the spectral segmenter, or Otsu
on band energy) a cyclic shift is undone exactly, so binary mTC is identically 1.0
(docs/analysis.md); and mTC of the full material segmenter is dominated by the Gaussian
mixture's own randomness (a different number of components after a shift), not by the
capture. What a capture can spoil is the *signal*: too little light (noise), clipping,
shadows under the spotlight. So the QC score asks: **would a re-capture of this pose
give the same segmentation?**

Score (``capture_stability``), for a cube ``(bands, H, W)`` in DN after dark subtraction:

1. Foreground threshold t: Otsu on log band energy of the whole cube (as
   ``SpectralSegmenter``). Material model: ``SpectralSegmenter`` on the cube
   block-averaged to at most ``model_size`` px; each material is the mean unit
   spectrum of its pixels (the model is then *fixed*, so its own randomness drops out).
2. Noise σ_b per band, estimated from the frame itself: Immerkær's Laplacian-difference
   operator, robust version (median absolute response / (0.6745·6)) over the eroded
   foreground, i.e. at the object's signal level, shot noise included. It also counts
   fixed-pattern noise and fine texture, so it is an upper bound: the score is pessimistic.
3. Predictor f(x): foreground if log energy > t, then the material whose spectrum makes
   the smallest angle with the pixel's. Evaluated on a regular grid of about
   ``sample_pixels`` pixels (f is pixel-wise, so a grid sample loses nothing but precision).
4. K = ``draws`` re-captures x + ε_k, ε_k ~ N(0, σ_b²) per band and pixel (seeded,
   ``seed`` = 42): score = mean_k micro-IoU(f(x), f(x + ε_k)) with background left out
   of the sums (``metrics.micro_iou(..., exclude_labels=(0,))``, the mTC IoU with g = 0),
   so the large, trivially stable background does not inflate it. Pixels the processor
   flags as saturated (``ProcessedFrame.saturated_mask``) carry no reliable spectrum: in
   every re-capture they count as disagreeing.

Flags (a frame is *flagged* when any is raised): ``unstable`` (score < ``threshold``),
``saturated`` (more than ``max_saturated`` of the object's pixels clipped),
``underexposed`` (the object's 99th-percentile band value below ``min_level`` of full
scale), ``no_object`` (foreground below ``min_object_fraction`` of the frame, or no
contrast), ``object_cut`` (foreground touching more than ``max_border_fraction`` of the
frame border).

Cost: 60–150 ms per 2048² frame (512² cube) on a busy 2-core machine, mostly the small
Gaussian mixture (docs/benchmarks.md); it runs in the engine's processing thread, behind a
bounded queue, off the camera thread.

Twin checks (``capture_qc_hook(twin=True)``): the hook also compares frames with the digital
twin at their recorded pose and lighting (``m2s2hil.twin.checks``: mockup off the axis, wrong
build, a lamp out, tilt drift), on the first frames of every lighting and elevation and
every 8th after; their result is ``meta["qc"]["twin"]`` and their flags join ``flags``. The
engine tells the hook its session through ``hook.bind(sweep, rig)``.

Engine hook: ``capture_qc_hook()`` returns a callable ``hook(processed_frame, event,
meta) -> dict`` whose dict (``score`` + details + ``flags`` + ``flagged``) the engine
stores as ``meta["qc"]``. It also keeps the session's score distribution
(``hook.summary()``). ``qc_summary(frames)`` computes the same from stored frames.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np
from skimage.filters import threshold_otsu

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import micro_iou
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter

QC_VERSION = 1
#: The capture QC's own flags, then the twin's (``m2s2hil.twin.checks.FLAGS``, when its
#: checks run: ``capture_qc_hook(twin=True)``).
FLAGS = ("unstable", "saturated", "underexposed", "no_object", "object_cut",
         "off_axis", "yawed", "tilt_off", "tilt_drift", "wrong_mockup", "wrong_build", "lamp_out", "lamp_dim")
# Immerkær's noise operator: the difference of two Laplacians, blind to planes and ramps.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
_MAD_TO_SIGMA = 1.0 / (0.6745 * 6.0)  # 6 = the operator's L2 norm


@dataclass(frozen=True)
class QcConfig:
    """Thresholds and effort of the capture QC (see the module docstring)."""

    threshold: float = 0.90
    draws: int = 4
    sample_pixels: int = 16_384
    model_size: int = 64
    max_materials: int = 8
    merge_angle_deg: float = 5.0
    seed: int = 42
    max_saturated: float = 0.01
    min_level: float = 0.05
    min_object_fraction: float = 0.002
    max_border_fraction: float = 0.05
    full_scale: float | None = None  # DN; None: from meta["bit_depth"], else 10 bits

    def __post_init__(self) -> None:
        checks = {
            "threshold": 0.0 <= self.threshold <= 1.0,
            "draws": self.draws >= 1,
            "sample_pixels": self.sample_pixels >= 16,
            "model_size": self.model_size >= 8,
            "max_materials": self.max_materials >= 1,
            "max_saturated": 0.0 <= self.max_saturated <= 1.0,
            "min_level": 0.0 <= self.min_level <= 1.0,
            "min_object_fraction": 0.0 <= self.min_object_fraction < 1.0,
            "max_border_fraction": 0.0 <= self.max_border_fraction <= 1.0,
            "full_scale": self.full_scale is None or self.full_scale > 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise AnalysisInputError(f"QcConfig.{name}", f"out of range: {getattr(self, name)!r}")


@dataclass(frozen=True)
class QcResult:
    """Score, flags and the measurements behind them for one frame."""

    score: float
    flags: tuple[str, ...]
    ious: tuple[float, ...]
    n_materials: int
    foreground_fraction: float
    saturated_fraction: float  # of the object's pixels
    level: float  # object's 99th-percentile band value / full scale
    noise_dn: float  # mean estimated σ over bands
    border_fraction: float
    elapsed_s: float
    threshold: float

    @property
    def flagged(self) -> bool:
        return bool(self.flags)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["flags"] = list(self.flags)
        out["ious"] = list(self.ious)
        out["flagged"] = self.flagged
        out["qc_version"] = QC_VERSION
        return out


def block_reduce(cube: np.ndarray, size: int) -> np.ndarray:
    """Block-average ``(bands, H, W)`` by the smallest integer factor that brings H, W to ≤ ``size``."""
    b, h, w = cube.shape
    f = max(1, math.ceil(max(h, w) / size))
    if f == 1:
        return cube
    hh, ww = h // f, w // f
    return cube[:, : hh * f, : ww * f].reshape(b, hh, f, ww, f).mean(axis=(2, 4))


def band_energy(cube: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("bhw,bhw->hw", cube, cube))


def log_energy(energy: np.ndarray, top: float) -> np.ndarray:
    # Same offset as spectral.foreground_mask, so the threshold means the same thing.
    return np.log(energy + 1e-3 * top)


def estimate_noise(cube: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """σ per band (DN) inside ``mask`` eroded by one pixel (Immerkær, median form)."""
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if inner.sum() < 16:
        inner = mask
    if inner.sum() < 4:
        return np.zeros(cube.shape[0], dtype=np.float32)
    sig = [
        np.median(np.abs(cv2.filter2D(band, cv2.CV_32F, _IMMERKAER)[inner])) * _MAD_TO_SIGMA for band in cube
    ]
    return np.asarray(sig, dtype=np.float32)


def _grid(shape: tuple[int, int], n: int) -> tuple[slice, slice]:
    step = max(1, int(math.sqrt(shape[0] * shape[1] / n)))
    return slice(step // 2, None, step), slice(step // 2, None, step)


def _material_spectra(cube: np.ndarray, cfg: QcConfig) -> np.ndarray:
    """(materials, bands) unit mean spectra from SpectralSegmenter on the reduced cube."""
    small = block_reduce(cube, cfg.model_size).astype(np.float32)
    seg = SpectralSegmenter(  # the model the QC thresholds were set with (before issue 15)
        max_materials=cfg.max_materials, sample_size=4096, seed=0, merge_angle_deg=cfg.merge_angle_deg,
        fit_pixels="all", brightness_weight=0.0, foreground="otsu", robust=False,
    )
    labels = seg.segment(small)
    out = []
    for lab in range(1, int(labels.max()) + 1):
        px = small[:, labels == lab]
        if px.shape[1] == 0:
            continue
        unit = px / np.maximum(np.linalg.norm(px, axis=0, keepdims=True), 1e-12)
        m = unit.mean(axis=1)
        out.append(m / max(float(np.linalg.norm(m)), 1e-12))
    return np.asarray(out, dtype=np.float32).reshape(len(out), cube.shape[0])


def _predict(x: np.ndarray, threshold: float, top: float, spectra: np.ndarray) -> np.ndarray:
    """Pixel-wise f on ``(bands, N)``: 0 below the energy threshold, else 1 + nearest spectrum."""
    e = np.sqrt(np.einsum("bn,bn->n", x, x))
    fg = log_energy(e, top) > threshold
    out = np.zeros(x.shape[1], dtype=np.int64)
    if spectra.shape[0] == 0 or not fg.any():
        out[fg] = 1
        return out
    cos = spectra @ x[:, fg]  # (materials, n_fg); the pixel norm does not change the argmax
    out[fg] = 1 + np.argmax(cos, axis=0)
    return out


def capture_stability(
    cube: object,
    saturated: np.ndarray | None = None,
    *,
    config: QcConfig | None = None,
    full_scale: float | None = None,
) -> QcResult:
    """QC score and flags of one processed cube (see the module docstring)."""
    t0 = time.perf_counter()
    cfg = config or QcConfig()
    arr = as_cube(cube)
    fs = float(full_scale or cfg.full_scale or 1023.0)
    bands, h, w = arr.shape
    energy = band_energy(arr)
    top = float(energy.max())
    sat = np.zeros((h, w), bool) if saturated is None else np.asarray(saturated, dtype=bool)
    if sat.shape != (h, w):
        raise AnalysisInputError("saturated", f"shape {sat.shape}, expected {(h, w)}")
    if top <= 0 or top == float(energy.min()):
        return QcResult(
            0.0, ("no_object",), (), 0, 0.0, 0.0, 0.0, 0.0, 0.0, time.perf_counter() - t0, cfg.threshold
        )
    loge = log_energy(energy, top)
    t = float(threshold_otsu(loge))
    fg = loge > t
    fg_frac = float(fg.mean())
    border = np.concatenate([fg[0], fg[-1], fg[1:-1, 0], fg[1:-1, -1]])
    border_frac = float(border.mean())
    sat_frac = float(sat[fg].mean()) if fg.any() else 0.0
    level = float(np.percentile(arr[:, fg], 99)) / fs if fg.any() else 0.0
    sigma = estimate_noise(arr, fg)
    spectra = _material_spectra(arr, cfg)

    rows, cols = _grid((h, w), cfg.sample_pixels)
    x = np.ascontiguousarray(arr[:, rows, cols].reshape(bands, -1))
    sat_s = sat[rows, cols].ravel()
    base = _predict(x, t, top, spectra)
    rng = np.random.default_rng(cfg.seed)
    spoiled = spectra.shape[0] + 2  # a label no prediction uses: saturated pixels never agree
    ious = []
    for _ in range(cfg.draws):
        noisy = x + rng.standard_normal(x.shape, dtype=np.float32) * sigma[:, None]
        y = _predict(noisy, t, top, spectra)
        y[sat_s & (base > 0)] = spoiled
        ious.append(micro_iou(base[None], y[None], exclude_labels=(0,)))
    score = float(np.mean(ious))

    flags = []
    if score < cfg.threshold:
        flags.append("unstable")
    if sat_frac > cfg.max_saturated:
        flags.append("saturated")
    if fg_frac < cfg.min_object_fraction:
        flags.append("no_object")
    elif level < cfg.min_level:
        flags.append("underexposed")
    if border_frac > cfg.max_border_fraction:
        flags.append("object_cut")
    return QcResult(
        score,
        tuple(flags),
        tuple(float(v) for v in ious),
        int(spectra.shape[0]),
        fg_frac,
        sat_frac,
        level,
        float(sigma.mean()),
        border_frac,
        time.perf_counter() - t0,
        cfg.threshold,
    )


def _full_scale(meta: Mapping[str, Any], cfg: QcConfig) -> float:
    if cfg.full_scale:
        return float(cfg.full_scale)
    bits = meta.get("bit_depth")
    return float((1 << int(bits)) - 1) if isinstance(bits, int) and bits > 0 else 1023.0


@dataclass
class CaptureQC:
    """The engine's QC hook: ``hook(processed_frame, event, meta) -> dict`` (stored as ``meta["qc"]``).

    Thread-safe; remembers every score it produced so ``summary()`` gives the session's
    distribution while the run goes on.
    """

    config: QcConfig = field(default_factory=QcConfig)
    #: The twin's checks (``m2s2hil.twin.checks``): off (False), on with their defaults (True)
    #: or with a ``CheckConfig``. They need the session, which the engine gives ``bind``.
    twin: Any = False
    _scores: list[tuple[str, float, tuple[str, ...]]] = field(default_factory=list, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _checks: Any = field(default=None, repr=False)
    _files: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False)

    def bind(self, sweep: Any, rig: Any) -> None:
        """The session the frames belong to (called by the engine when a run is built)."""
        if self.twin is False or self.twin is None:
            return
        from m2s2hil.twin.checks import CheckConfig, sweep_checks

        cfg = self.twin if isinstance(self.twin, CheckConfig) else CheckConfig()
        cube_side = max(rig.camera.model.width, rig.camera.model.height) // 4  # superpixel cube
        if cube_side < cfg.size:  # never upsample a small sensor's cube
            from dataclasses import replace

            cfg = replace(cfg, size=max(24, cube_side))
        self._checks = sweep_checks(sweep, rig, cfg, register=True)

    def frame_files(self, event: Any) -> dict[str, np.ndarray]:
        """Arrays to store with the frame just scored (the engine asks after the hook ran):
        the twin's projected labels once the sweep's registration has them."""
        with self._lock:
            return self._files.pop(str(getattr(event, "event_id", "?")), {})

    def __call__(self, processed: Any, event: Any, meta: Mapping[str, Any]) -> dict[str, Any]:
        res = capture_stability(
            processed.cube,
            getattr(processed, "saturated_mask", None),
            config=self.config,
            full_scale=_full_scale(meta, self.config),
        )
        out = res.as_dict()
        flags = res.flags
        if self._checks is not None:
            key = (getattr(event, "lighting", None), getattr(event, "elevation", None))
            sat = getattr(processed, "saturated_mask", None)
            twin = self._checks(np.asarray(processed.cube), meta, key, sat)
            if twin is not None:
                out["twin"] = twin
                flags = (*flags, *(f for f in twin.get("flags", ()) if f not in flags))
                out["flags"] = list(flags)
                out["flagged"] = bool(flags)
            labels = self._checks.labels(meta, np.shape(processed.cube)[1:])
            if labels is not None:
                out["projected_labels"] = labels.meta()
                with self._lock:
                    self._files[str(getattr(event, "event_id", "?"))] = {"projected_labels": labels.labels}
        with self._lock:
            self._scores.append((str(getattr(event, "event_id", "?")), res.score, flags))
        return out

    def summary(self) -> dict[str, Any]:
        with self._lock:
            rows = list(self._scores)
        return _summarise([(e, s, list(f)) for e, s, f in rows], self.config.threshold)


def capture_qc_hook(config: QcConfig | None = None, *, twin: Any = False) -> CaptureQC:
    """The QC callable to pass as ``Engine(..., qc=capture_qc_hook())``; ``twin`` turns on the
    twin's checks during the sweep (True, or a ``twin.checks.CheckConfig``)."""
    return CaptureQC(config or QcConfig(), twin=twin)


HISTOGRAM_EDGES: tuple[float, ...] = (0.0, 0.5, 0.7, 0.8, 0.85, 0.9, 0.95, 0.98, 1.0)


def _summarise(rows: Sequence[tuple[str, float | None, list[str]]], threshold: float) -> dict[str, Any]:
    scores = np.array([s for _, s, _ in rows if s is not None and math.isfinite(s)], dtype=float)
    flagged = [{"event_id": e, "score": s, "flags": f} for e, s, f in rows if f]
    out: dict[str, Any] = {
        "frames": len(rows),
        "scored": int(scores.size),
        "threshold": threshold,
        "flagged": len(flagged),
        "flagged_frames": flagged,
        "flag_counts": {k: sum(k in f for _, _, f in rows) for k in FLAGS},
    }
    if scores.size:
        q = np.quantile(scores, [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0])
        out.update(
            mean=float(scores.mean()),
            min=float(q[0]),
            p05=float(q[1]),
            p25=float(q[2]),
            median=float(q[3]),
            p75=float(q[4]),
            p95=float(q[5]),
            max=float(q[6]),
        )
        counts, _ = np.histogram(scores, bins=np.array(HISTOGRAM_EDGES))
        out["histogram"] = {"edges": list(HISTOGRAM_EDGES), "counts": [int(c) for c in counts]}
    return out


def qc_of_meta(meta: Mapping[str, Any]) -> tuple[float | None, list[str]]:
    """(score, flags) of a stored frame's ``meta["qc"]`` (a dict from this module, or a bare number)."""
    qc = meta.get("qc")
    if isinstance(qc, (int, float)) and not isinstance(qc, bool):
        return float(qc), []
    if isinstance(qc, Mapping):
        s = qc.get("score")
        flags = [str(f) for f in qc.get("flags", []) or []]
        return (float(s) if isinstance(s, (int, float)) else None), flags
    return None, []


def qc_summary(frames: Iterable[Any], threshold: float | None = None) -> dict[str, Any]:
    """Score distribution and flagged frames of stored frames (``event_id`` and ``meta`` each)."""
    rows = []
    thr = threshold
    for fr in frames:
        s, flags = qc_of_meta(fr.meta)
        rows.append((fr.event_id, s, flags))
        qc = fr.meta.get("qc")
        if thr is None and isinstance(qc, Mapping) and isinstance(qc.get("threshold"), (int, float)):
            thr = float(qc["threshold"])
    return _summarise(rows, QcConfig().threshold if thr is None else thr)
