"""Checks during the sweep: each frame against the twin at its recorded pose and lighting.

What stands on the turntable should be what the session says, where it says. For a frame
(its processed cube, reduced to ``size`` px) the checks ask:

1. **Geometry.** The twin's silhouette of the session's mockup, on axis, at the recorded
   pose, is aligned to the frame's mask by two Gauss-Newton steps over an image shift
   (u, v), a yaw and a tilt (the shift's derivative is the blurred silhouette's gradient; yaw
   and tilt by one extra render each). ``off_axis``: the shift exceeds ``shift_mm``
   (the mockup off the turntable axis, or the frame off centre); ``yawed``: the yaw at this
   azimuth exceeds ``yaw_deg``; ``tilt_off``: the tilt exceeds ``tilt_deg`` (a biased or
   drifting tilt stage; against the registration's bias once there is one: ``tilt_drift``);
   ``wrong_mockup``: even aligned, the silhouettes overlap less than ``min_iou`` (another
   satellite, or none). A displacement along the line of sight does not move an
   orthographic silhouette: it shows only once the turntable has turned (docs/twin.md).
   *Debiased*: the mask rule loses what does not stand out from the backdrop (the shadowed
   side in directional light), which the raw alignment reads as a shift and a yaw (Hubble in
   directional light: 2.3° and 0.8 mm on a nominal mount). The twin predicts that loss: its
   shaded frame at twice the size, under the frame's lamps and exposure, through the same
   mask rule with the frame's noise (:meth:`TwinChecks.predicted_coverage`); the frame is
   aligned as its mask less (that prediction − the twin's silhouette) (``debias``).
   *Jointly* (:class:`SweepChecks`, from the second checked frame of a lighting): the yaw and
   tilt are the mean of the lighting's frames' estimates and the offset a fit of their lateral
   shifts over azimuth; those decide the geometry flags, with tolerances ``joint_*`` set from
   the nominal distribution (mean + 3 sd over 27 nominal cells, docs/benchmarks.md).
   *Fitted* (``joint_fit``): the offset and yaw flags come instead from the placement fitted
   to the lighting's latest checked frames together (``SweepChecks.fitter``: the
   registration's refinement, one round against the twin's predicted masks, scale held), in
   which an offset along the line of sight and a yaw show within three frames 10° apart.
2. **Materials.** The twin's label map, aligned, says which filament each pixel should show;
   its shaded render under the frame's lamps predicts that pixel's spectrum. A filament
   region (eroded by a pixel, unsaturated) is wrong when its median spectrum is more than
   ``spectrum_deg`` from the prediction or its brightness, relative to the frame's, off by
   more than ``brightness_ratio``. ``wrong_build``: wrong regions hold more than
   ``max_wrong_fraction`` of the pixels, or two regions are wrong, or one of at least 3 % is
   far off (twice the angle, the ratio squared).
3. **Lamps.** The frame's light against the twin's prediction under the lit lamps, exposure
   and gain applied (the backdrop, lit by every lamp, is the main witness): the ratio says
   what one lamp short would leave of it; ``lamp_out`` below ``out_factor``, ``lamp_dim``
   below ``dim_factor``. Which lamp: the frame fitted as a non-negative mix of the twin
   rendered under each lit lamp alone (``scipy.optimize.nnls``, pulled towards 1), the
   factors per lamp name in the result. A frame with nothing like the mockup in view and
   almost no light is ``lamp_out``, not ``wrong_mockup``.

The twin's photometry is the simulator's (catalog reflectances, the sensor's QE and gain):
exact on the simulated rig, an assumption a real rig would calibrate (white reference).

Cost: a median 39 ms per checked frame on a 2048² frame's cube (docs/benchmarks.md); :class:`SweepChecks` (the
capture-time QC's companion, ``analysis.qc``) runs them on the first ``first_frames``
frames after every change of lighting, tilt or mount and then on every ``every``-th
frame, so the processing thread keeps up with 65 frames/s; a flag is raised once
``confirm`` (2) checked frames of the same lighting and elevation had it (a single frame's
flag is kept as ``frame_flags``), which removes most false alarms of one odd view.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import nnls  # type: ignore[import-untyped]

from m2s2hil.simulators.scene import MountedScene
from m2s2hil.twin.projection import (
    NOMINAL,
    Placement,
    TwinCamera,
    backdrop_noise,
    coverage_of,
    observed_mask,
)

CHECKS_VERSION = 1
_GEOMETRY = ("off_axis", "yawed", "tilt_off", "tilt_drift")
FLAGS = ("off_axis", "yawed", "tilt_off", "tilt_drift", "wrong_mockup", "wrong_build", "lamp_out", "lamp_dim")


@dataclass(frozen=True)
class CheckConfig:
    """Tolerances and effort of the twin's checks (see the module docstring)."""

    size: int = 96
    shift_mm: float = 1.0
    yaw_deg: float = 1.5
    tilt_deg: float = 1.0
    min_iou: float = 0.6
    spectrum_deg: float = 15.0
    brightness_ratio: float = 1.6
    max_wrong_fraction: float = 0.2
    out_factor: float = 0.3
    dim_factor: float = 0.75
    first_frames: int = 3
    every: int = 8
    confirm: int = 2  # a flag is raised once this many checked frames of a lighting had it
    diameter_mm: float | None = None  # None: the twin's default (projection.DIAMETER_MM)
    debias: bool = True  # align against the mask less the twin's predicted mask bias
    # The joint fit over a lighting's checked frames (SweepChecks): its tolerances, set from
    # the nominal distribution of the fitted placement (docs/benchmarks.md), and its effort.
    joint: bool = True
    joint_shift_mm: float = 3.0
    joint_yaw_deg: float = 1.35
    joint_tilt_deg: float = 1.0
    joint_noise_mm: float = 0.2  # one frame's lateral shift noise (nominal spread, docs/benchmarks.md)
    joint_prior_mm: float = 3.0
    # The placement fitted to the lighting's checked frames together (the twin's silhouettes
    # against the masks less their predicted bias, ``registration.Registrar``): an offset along
    # the line of sight and a yaw show in it where one view's alignment cannot tell them from
    # a shift; its tolerances from the nominal cells (docs/benchmarks.md).
    joint_fit: bool = True
    joint_fit_shift_mm: float = 0.8
    joint_fit_yaw_deg: float = 0.6
    joint_fit_frames: int = 4  # the latest checked frames of the lighting it fits

    def __post_init__(self) -> None:
        checks = {
            "size": 24 <= self.size <= 1024, "shift_mm": self.shift_mm > 0, "yaw_deg": self.yaw_deg > 0,
            "tilt_deg": self.tilt_deg > 0, "min_iou": 0 <= self.min_iou <= 1,
            "spectrum_deg": 0 < self.spectrum_deg < 90,
            "brightness_ratio": self.brightness_ratio > 1,
            "max_wrong_fraction": 0 < self.max_wrong_fraction < 1,
            "out_factor": 0 <= self.out_factor <= self.dim_factor <= 1,
            "first_frames": self.first_frames >= 0, "confirm": self.confirm >= 1,
            "every": self.every >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"CheckConfig.{name} out of range: {getattr(self, name)!r}")


@dataclass(frozen=True)
class LampSpec:
    """A lamp as the twin needs it: name, relay channel, kind (as ``simulators.world.LampInfo``)."""

    name: str
    channel: int
    kind: str
    warmup_s: float = 0.0


@dataclass
class Alignment:
    u_px: float
    v_px: float
    yaw_deg: float
    tilt_deg: float
    iou: float
    info: np.ndarray | None = None  # (4, 4) information of (u, v, yaw, tilt), the grow term marginalised


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma)


def _shift(img: np.ndarray, u: float, v: float) -> np.ndarray:
    m = np.array([[1, 0, u], [0, 1, v]], dtype=np.float32)
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between spectra ``a`` and ``b`` (bands first), degrees."""
    na = np.linalg.norm(a, axis=0)
    nb = np.linalg.norm(b, axis=0)
    cos = np.einsum("b...,b...->...", a, b) / np.maximum(na * nb, 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class TwinChecks:
    """The checks of one camera model and lamp set (thread-safe: one frame at a time)."""

    def __init__(self, model: Any, lamps: Sequence[LampSpec], *, config: CheckConfig | None = None,
                 spot_angle_deg: float = 45.0, sensor_params: Any = None,
                 meshes: Mapping[tuple[str, str], Any] | None = None) -> None:
        self.config = cfg = config or CheckConfig()
        kw: dict[str, Any] = {"meshes": meshes}
        if cfg.diameter_mm is not None:
            kw["diameter_mm"] = cfg.diameter_mm
        self.twin = TwinCamera(model, cfg.size, **kw)
        # The twin's own frame at twice the checks' size: which pixels a nominal frame's mask
        # would hold (shadowed or dark parts the mask rule misses, edge pixels), to debias.
        self.fine = TwinCamera(model, 2 * cfg.size, **kw)
        self.lamps = {lp.channel: lp for lp in lamps}
        self.spot_angle_deg = float(spot_angle_deg)
        from m2s2hil.simulators.sensor import Sensor
        from m2s2hil.simulators.world import LampInfo

        self._lamp_info = {lp.channel: LampInfo(lp.name, lp.kind, lp.warmup_s) for lp in lamps}
        self._sensor = Sensor(8, 8, model.layout, model.bands_nm, model.fwhm_nm, int(model.full_scale),
                              sensor_params)
        self.full_scale = float(model.full_scale)
        self._lock = threading.Lock()

    # -- geometry --------------------------------------------------------------------
    def align(self, m: MountedScene, az: float, tilt: float, obs: np.ndarray, prior: Placement = NOMINAL,
              iterations: tuple[float, ...] = (2.0, 1.0), raw: np.ndarray | None = None) -> Alignment:
        """Image shift, yaw and tilt that align the twin (at ``prior``) with the mask coverage ``obs``
        (``raw``: the mask as seen, for the IoU, when ``obs`` is debiased)."""
        u = v = dyaw = dtilt = 0.0
        info = None
        h_ang = 0.5
        for sigma in iterations:
            tgt = _blur(obs, sigma)
            p = Placement(prior.dx_mm, prior.dy_mm, prior.yaw_deg + dyaw, prior.tilt_bias_deg + dtilt,
                          prior.scale)
            base = _blur(_shift(self.twin.coverage(m, az, tilt, p), u, v), sigma)
            py = Placement(p.dx_mm, p.dy_mm, p.yaw_deg + h_ang, p.tilt_bias_deg, p.scale)
            pt = Placement(p.dx_mm, p.dy_mm, p.yaw_deg, p.tilt_bias_deg + h_ang, p.scale)
            by = _blur(_shift(self.twin.coverage(m, az, tilt, py), u, v), sigma)
            bt = _blur(_shift(self.twin.coverage(m, az, tilt, pt), u, v), sigma)
            gy, gx = np.gradient(base)
            # The fifth column grows the silhouette evenly (|gradient|): the mask counts the
            # pixels its edge only partly covers, which a yaw or tilt must not explain.
            jac = np.column_stack([-gx.ravel(), -gy.ravel(), ((by - base) / h_ang).ravel(),
                                   ((bt - base) / h_ang).ravel(), np.hypot(gx, gy).ravel()])
            r = (base - tgt).ravel()
            jtj = jac.T @ jac
            jtj += np.eye(5) * max(float(np.trace(jtj)), 1e-9) * 1e-6
            step = np.linalg.solve(jtj, -jac.T @ r)
            info = jtj[:4, :4] - np.outer(jtj[:4, 4], jtj[4, :4]) / jtj[4, 4]
            step = np.clip(step, [-8, -8, -6, -6, -3], [8, 8, 6, 6, 3])
            u, v, dyaw, dtilt = u + step[0], v + step[1], dyaw + step[2], dtilt + step[3]
        p = Placement(prior.dx_mm, prior.dy_mm, prior.yaw_deg + dyaw, prior.tilt_bias_deg + dtilt,
                      prior.scale)
        final = _shift(self.twin.coverage(m, az, tilt, p), u, v) >= 0.5
        seen = (obs if raw is None else raw) >= 0.5
        union = np.logical_or(final, seen).sum()
        iou = float(np.logical_and(final, seen).sum() / union) if union else 1.0
        return Alignment(float(u), float(v), float(dyaw), float(dtilt), iou, info)

    def predicted_coverage(self, m: MountedScene, az: float, tilt: float, lit: Sequence[int],
                           exposure_s: float, gain: float, cube: np.ndarray) -> np.ndarray:
        """The mask coverage a nominal frame would give (the twin's shaded frame at twice the
        size, under the lit lamps, through the same mask rule with the frame's noise)."""
        mf = self.fine.scene.mount(m.satellite, m.materials, m.build)
        sh = self.fine.shaded(mf, az, tilt, NOMINAL, dict.fromkeys(lit, 1.0), self._lamp_info,
                              self.spot_angle_deg, band_gain=self._sensor.band_gain)
        pred = sh.cube(float(exposure_s) * self._sensor.dn_per_e(gain))
        bg_obs, noise = backdrop_noise(cube)
        bg_pred, _ = backdrop_noise(pred)
        noise *= bg_pred / bg_obs if bg_obs > 0 else 1.0
        return coverage_of(observed_mask(pred, noise_norm=noise), self.twin.shape)

    # -- the frame -------------------------------------------------------------------
    def check(self, cube: np.ndarray, satellite: str, build: str, azimuth_deg: float, tilt_deg: float,
              lamps_on: Sequence[int], exposure_s: float, gain: float = 1.0,
              registered: Placement | None = None, saturated: np.ndarray | None = None,
              keep: list[Any] | None = None) -> dict[str, Any]:
        """Flags and measurements of one frame (a dict for ``meta["qc"]["twin"]``); ``keep``: a
        list the frame's estimates are appended to, ``(azimuth, lateral shift mm, yaw, tilt)``,
        for the joint estimate over a lighting's frames (``SweepChecks``)."""
        t0 = time.perf_counter()
        cfg = self.config
        with self._lock:
            arr = np.asarray(cube, dtype=np.float32)
            shape = self.twin.shape
            small = np.stack([cv2.resize(b, (shape[1], shape[0]), interpolation=cv2.INTER_AREA) for b in arr])
            clipped = np.zeros(shape, dtype=bool)
            if saturated is not None and saturated.shape == arr.shape[1:]:
                clipped = coverage_of(saturated, shape) > 0
            clipped |= (small >= 0.95 * self.full_scale).any(axis=0)
            obs = coverage_of(observed_mask(arr), shape)
            m = self.twin.mounted(satellite, build)
            out: dict[str, Any] = {"checks_version": CHECKS_VERSION}
            flags: list[str] = []
            seen = (obs >= 0.5).any()
            lit = [ch for ch in lamps_on if ch in self.lamps]
            target = obs
            if seen and lit and exposure_s > 0 and cfg.debias:
                # What the mask rule makes of a nominal frame, less the twin's silhouette: the
                # estimator's own bias at this pose and lighting (shadowed parts missed, edges).
                pred = self.predicted_coverage(m, azimuth_deg, tilt_deg, lit, exposure_s, gain, arr)
                target = obs - (pred - self.twin.coverage(m, azimuth_deg, tilt_deg, NOMINAL))
            al = self.align(m, azimuth_deg, tilt_deg, target, raw=obs) if seen else Alignment(0, 0, 0, 0, 0.0)
            if al.iou < cfg.min_iou:
                # Nothing like the mockup in view: the light first (a dead lamp leaves the
                # frame dark), else another satellite (or none) stands there.
                ratio = self._light_ratio(m, azimuth_deg, tilt_deg, al, small, clipped, lamps_on,
                                          exposure_s, gain)
                dark = ratio is not None and ratio < cfg.out_factor
                out.update(flags=["lamp_out" if dark else "wrong_mockup"], iou=round(al.iou, 4),
                           light_ratio=None if ratio is None else round(ratio, 4),
                           elapsed_s=round(time.perf_counter() - t0, 4))
                return out
            mm = 1.0 / self.twin.px_per_mm()
            shift_mm = math.hypot(al.u_px, al.v_px) * mm
            if al.info is not None:  # marginal precision of yaw and tilt (1 / their variance ∝)
                cov = np.linalg.pinv(al.info)
                out["precision"] = [round(1.0 / max(float(cov[k, k]), 1e-12), 3) for k in (2, 3)]
            out.update(shift_mm=[round(al.u_px * mm, 3), round(al.v_px * mm, 3)],
                       yaw_deg=round(al.yaw_deg, 3),
                       tilt_deg=round(al.tilt_deg, 3), iou=round(al.iou, 4))
            if keep is not None:
                keep.append((float(azimuth_deg), al.u_px * mm, al.yaw_deg, al.tilt_deg))
            if shift_mm > cfg.shift_mm:
                flags.append("off_axis")
            if abs(al.yaw_deg) > cfg.yaw_deg:
                flags.append("yawed")
            if registered is None and abs(al.tilt_deg) > cfg.tilt_deg:
                flags.append("tilt_off")
            if registered is not None and abs(al.tilt_deg - registered.tilt_bias_deg) > cfg.tilt_deg:
                flags.append("tilt_drift")  # a bias the registration knows is no news; a change is
            p = Placement(0.0, 0.0, al.yaw_deg, al.tilt_deg, 1.0)
            flags += self._photometry(m, azimuth_deg, tilt_deg, p, al, small, clipped, lamps_on,
                                      exposure_s, gain, out)
            out["flags"] = flags
            out["elapsed_s"] = round(time.perf_counter() - t0, 4)
            return out

    def _renders(self, m: MountedScene, az: float, tilt: float, p: Placement, al: Alignment,
                 outputs: Mapping[int, float], dn_scale: float) -> tuple[np.ndarray, np.ndarray]:
        sh = self.twin.shaded(m, az, tilt, p, outputs, self._lamp_info, self.spot_angle_deg,
                              band_gain=self._sensor.band_gain)
        cube = sh.cube(dn_scale)
        cube = np.stack([_shift(b, al.u_px, al.v_px) for b in cube])
        lab = cv2.warpAffine(sh.label, np.array([[1, 0, al.u_px], [0, 1, al.v_px]], dtype=np.float32),
                             (sh.label.shape[1], sh.label.shape[0]), flags=cv2.INTER_NEAREST)
        return cube, lab

    def _light_ratio(self, m: MountedScene, az: float, tilt: float, al: Alignment, small: np.ndarray,
                     clipped: np.ndarray, lamps_on: Sequence[int], exposure_s: float,
                     gain: float) -> float | None:
        lit = [ch for ch in lamps_on if ch in self.lamps]
        if not lit:
            return None
        dn_scale = float(exposure_s) * self._sensor.dn_per_e(gain)
        nominal, _ = self._renders(m, az, tilt, NOMINAL, al, dict.fromkeys(lit, 1.0), dn_scale)
        whole = ~clipped
        return float(small[:, whole].sum() / max(float(nominal[:, whole].sum()), 1e-9))

    def _photometry(self, m: MountedScene, az: float, tilt: float, p: Placement, al: Alignment,
                    small: np.ndarray, clipped: np.ndarray, lamps_on: Sequence[int], exposure_s: float,
                    gain: float, out: dict[str, Any]) -> list[str]:
        cfg = self.config
        flags: list[str] = []
        lit = [ch for ch in lamps_on if ch in self.lamps]
        if not lit:
            return flags
        dn_scale = float(exposure_s) * self._sensor.dn_per_e(gain)
        nominal, lab = self._renders(m, az, tilt, p, al, dict.fromkeys(lit, 1.0), dn_scale)
        # Materials: pixels well inside a region, unclipped, bright enough to have a spectrum.
        inner = np.zeros(lab.shape, dtype=bool)
        for k in np.unique(lab):
            if k == 0:
                continue
            inner |= cv2.erode((lab == k).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        energy = np.linalg.norm(small, axis=0)
        good = inner & ~clipped & (energy > 0.02 * self.full_scale) & (np.linalg.norm(nominal, axis=0) > 0)
        if good.sum() >= 20:
            # Per filament region: the median angle between seen and predicted spectra; the
            # regions whose median is off count with their area.
            ang = _angle_deg(small, nominal)
            bright = np.log(np.maximum(np.linalg.norm(small, axis=0), 1e-6)
                            / np.maximum(np.linalg.norm(nominal, axis=0), 1e-6))
            ref = float(np.median(bright[good]))  # the frame's own level (exposure, lamps)
            wrong_px, strong, regions = 0, False, {}
            for k in np.unique(lab[good]):
                sel = good & (lab == k)
                if sel.sum() < 4:
                    continue
                med = float(np.median(ang[sel]))
                level = float(np.median(bright[sel])) - ref
                regions[m.class_names[int(k)]] = [round(med, 2), round(math.exp(level), 3)]
                if med > cfg.spectrum_deg or abs(level) > math.log(cfg.brightness_ratio):
                    wrong_px += int(sel.sum())
                    # Far off (twice the angle, the ratio squared) and not a sliver: alone enough.
                    far = med > 2 * cfg.spectrum_deg or abs(level) > 2 * math.log(cfg.brightness_ratio)
                    strong |= bool(far and sel.sum() >= 0.03 * good.sum())
            wrong = wrong_px / max(1, int(good.sum()))
            n_wrong = sum(a > cfg.spectrum_deg or abs(math.log(b)) > math.log(cfg.brightness_ratio)
                          for a, b in regions.values())
            out["materials"] = {"pixels": int(good.sum()), "wrong_fraction": round(wrong, 4),
                                "wrong_regions": n_wrong, "regions": regions}
            if wrong > cfg.max_wrong_fraction or n_wrong >= 2 or strong:
                flags.append("wrong_build")
        # Lamps: the frame as a non-negative mix of single-lamp renders (backdrop included).
        use = ~clipped & (cv2.dilate(inner.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
        if use.sum() >= 20:
            cols = []
            for ch in lit:
                single, _ = self._renders(m, az, tilt, p, al, {ch: 1.0}, dn_scale)
                cols.append(single[:, use].ravel())
            factors = _lamp_factors(np.column_stack(cols), small[:, use].ravel())
            named = {self.lamps[ch].name: round(float(f), 3) for ch, f in zip(lit, factors, strict=True)}
            # The light as a whole: seen over predicted, object and backdrop (the backdrop is
            # lit by every lamp, a large and uniform witness of their sum).
            whole = ~clipped
            ratio = float(small[:, whole].sum() / max(float(nominal[:, whole].sum()), 1e-9))
            out["lamps"] = named
            out["light_ratio"] = round(ratio, 4)
            low = ratio * len(lit) - (len(lit) - 1)  # what one lamp short would explain the ratio with
            if low < cfg.out_factor:
                flags.append("lamp_out")
            elif low < cfg.dim_factor:
                flags.append("lamp_dim")
        return flags


def _lamp_factors(a: np.ndarray, y: np.ndarray, ridge: float = 0.05) -> np.ndarray:
    """Non-negative lamp factors f with ``a @ f ≈ y``, pulled towards 1 (nominal) by a ridge of
    ``ridge`` × the mean column energy: lamps from mirrored directions (the two side bars)
    light a symmetric mockup alike, and without the pull the fit trades one for the other."""
    a = a.astype(np.float64)
    y = y.astype(np.float64)
    k = a.shape[1]
    lam = math.sqrt(ridge * float(np.einsum("ij,ij->", a, a)) / k)
    aa = np.vstack([a, lam * np.eye(k)])
    yy = np.concatenate([y, lam * np.ones(k)])
    f, _ = nnls(aa, yy)
    return f


@dataclass
class SweepChecks:
    """The checks through a sweep: which frames to check, and the incremental registration.

    ``due(key)`` says whether a frame is checked: the first ``first_frames`` after every
    change of ``key`` (lighting, elevation, mount), then every ``every``-th.
    """

    checks: TwinChecks
    satellite: str
    build: str
    registration: Any = None  # registration.IncrementalRegistration, if registration runs too
    _key: Any = None
    _count: int = 0
    _seen: dict[str, int] = field(default_factory=dict)  # flag -> checked frames of this key with it
    _frames: list[Any] = field(default_factory=list)  # this key's checked frames (Observation)
    fitter: Any = None  # registration.Registrar of the joint fit over a lighting's frames
    _fit_obs: list[Any] = field(default_factory=list)  # this key's latest checked frames (Observation)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def due(self, key: Any) -> bool:
        with self._lock:
            if key != self._key:
                self._key, self._count, self._seen, self._frames, self._fit_obs = key, 0, {}, [], []
            self._count += 1
            n, cfg = self._count, self.checks.config
            return n <= cfg.first_frames or (n - cfg.first_frames) % cfg.every == 0

    def __call__(self, cube: np.ndarray, meta: Mapping[str, Any], key: Any = None,
                 saturated: np.ndarray | None = None) -> dict[str, Any] | None:
        """The twin's result for a frame (None: not checked this frame)."""
        pose = meta.get("pose") or {}
        az, tilt = pose.get("turntable_deg"), pose.get("tilt_deg")
        if not isinstance(az, (int, float)) or not isinstance(tilt, (int, float)):
            return None
        if not self.due(key):
            return None
        from m2s2hil.twin.registration import Observation

        reg = None
        if self.registration is not None:  # the checked frames feed the sweep's registration too
            r = self.registration.add(Observation.from_cube(self.satellite, self.build, az, tilt, cube, 96))
            reg = r.placement if r is not None else None
        with self._lock:
            frames = self._frames
            if self.fitter is not None and self.checks.config.joint_fit:
                o = Observation.from_meta(self.satellite, self.build, cube, meta, 128)
                if o is not None and o.mask.any():
                    self._fit_obs.append(o)
                    del self._fit_obs[:-self.checks.config.joint_fit_frames]  # only the last few are fitted
            fit_obs = list(self._fit_obs)
        res = self.checks.check(cube, self.satellite, self.build, float(az), float(tilt),
                                list(meta.get("lamps_on") or []), float(meta.get("exposure_s") or 0.0),
                                float(meta.get("gain") or 1.0), registered=reg, saturated=saturated,
                                keep=frames)
        if self.registration is not None and self.registration.current is not None:
            res["registration"] = self.registration.current.as_dict()
        # One frame's flag may be noise (a shadow, a symmetric pose); what the next checked
        # frame of the same lighting confirms is not: flags are raised from the ``confirm``-th.
        with self._lock:
            for f in res["flags"]:
                self._seen[f] = self._seen.get(f, 0) + 1
            confirmed = [f for f in res["flags"] if self._seen[f] >= self.checks.config.confirm]
        joint = self._joint_flags(frames, res, reg, fit_obs)
        if joint is not None:  # the joint fit decides the geometry; one frame's estimate does not
            confirmed = [f for f in confirmed if f not in _GEOMETRY] + joint
        res["frame_flags"], res["flags"] = res["flags"], confirmed
        return res

    def _joint_flags(self, frames: list[Any], res: dict[str, Any], reg: Placement | None,
                     fit_obs: Sequence[Any] = ()) -> list[str] | None:
        """Geometry flags from the estimates of all this lighting's checked frames together
        (None: fewer than two, or this frame was not aligned).

        Yaw and tilt: the mean over the frames (one view's estimate carries the pose's own
        bias, docs/twin.md; the mean narrows its spread). The offset: the lateral shifts
        fitted as ``u_i = dx cos(az_i) − dy sin(az_i)`` (an orthographic view, the turntable
        turning the offset), ridge-pulled to 0 with a prior of ``joint_prior_mm``, so an offset
        along the line of sight at the first azimuth shows as the turntable turns; or, as one
        frame sees it, a lateral shift over ``shift_mm`` in two frames. With ``joint_fit``, the
        offset and yaw of a placement fitted to the frames themselves decide instead."""
        cfg = self.checks.config
        if not cfg.joint or len(frames) < 2 or "shift_mm" not in res:
            return None
        az = np.radians([f[0] for f in frames])
        a = np.column_stack([np.cos(az), -np.sin(az)])
        u = np.array([f[1] for f in frames])
        lam = (cfg.joint_noise_mm / cfg.joint_prior_mm) ** 2
        dx, dy = (float(x) for x in np.linalg.solve(a.T @ a + lam * np.eye(2), a.T @ u))
        yaw = float(np.mean([f[2] for f in frames]))
        tilt = float(np.mean([f[3] for f in frames]))
        res["joint"] = {"frames": len(frames), "offset_mm": [round(dx, 3), round(dy, 3)],
                        "yaw_deg": round(yaw, 3), "tilt_deg": round(tilt, 3)}
        flags = []
        with self._lock:
            shifted = self._seen.get("off_axis", 0) >= cfg.confirm
        fit = self._fit(fit_obs) if len(fit_obs) >= 2 else None
        if fit is not None:
            fp = fit.placement
            res["joint"]["fit"] = {"offset_mm": [round(fp.dx_mm, 3), round(fp.dy_mm, 3)],
                                   "yaw_deg": round(fp.yaw_deg, 3),
                                   "tilt_bias_deg": round(fp.tilt_bias_deg, 3),
                                   "residual": round(fit.residual, 4), "frames": fit.frames,
                                   "elapsed_s": round(fit.elapsed_s, 3)}
            off = math.hypot(fp.dx_mm, fp.dy_mm) > cfg.joint_fit_shift_mm
            yawed = abs(fp.yaw_deg) > cfg.joint_fit_yaw_deg
        else:
            off = math.hypot(dx, dy) > cfg.joint_shift_mm
            yawed = abs(yaw) > cfg.joint_yaw_deg
        if off or shifted:
            flags.append("off_axis")
        if yawed:
            flags.append("yawed")
        if reg is None and abs(tilt) > cfg.joint_tilt_deg:
            flags.append("tilt_off")
        if reg is not None and abs(tilt - reg.tilt_bias_deg) > cfg.joint_tilt_deg:
            flags.append("tilt_drift")
        return flags

    def _fit(self, obs: Sequence[Any]) -> Any:
        """The placement fitted to ``obs`` from the nominal mount, scale held (None: no fit)."""
        from m2s2hil.twin.registration import RegistrationError

        try:
            return self.fitter.register(obs, NOMINAL, fit_scale=False)
        except RegistrationError:
            return None

    def labels(self, meta: Mapping[str, Any], shape: tuple[int, ...]) -> Any:
        """The frame's projected labels (``twin.labels.ProjectedLabels``) at ``shape`` (the
        cube's), once the sweep's registration has a placement; else None."""
        from m2s2hil.twin.labels import projected_labels

        reg = self.registration.current if self.registration is not None else None
        pose = meta.get("pose") or {}
        az, tilt = pose.get("turntable_deg"), pose.get("tilt_deg")
        if reg is None or len(shape) != 2:
            return None
        if not isinstance(az, (int, float)) or not isinstance(tilt, (int, float)):
            return None
        return projected_labels(self.checks.twin, self.satellite, self.build, float(az), float(tilt), reg,
                                (int(shape[0]), int(shape[1])))


def sweep_checks(sweep: Any, rig: Any, config: CheckConfig | None = None, *,
                 register: bool = False) -> SweepChecks:
    """The checks for a session: its sweep's satellite and build, its rig's camera and lamps."""
    from m2s2hil.twin.registration import IncrementalRegistration, Registrar, rig_meshes, rig_predictor

    lamps = [LampSpec(name, lc.channel, lc.kind, lc.warmup_s) for name, lc in rig.lamps.items()]
    sim = getattr(rig, "simulation", None)
    meshes = rig_meshes(rig)
    checks = TwinChecks(rig.camera.model, lamps, config=config,
                        spot_angle_deg=sim.spot_angle_deg if sim is not None else 45.0,
                        sensor_params=sim.sensor.params() if sim is not None else None, meshes=meshes)
    incremental = None
    if register:
        # One coarse level, few iterations: it runs in the processing thread, warm-started.
        incremental = IncrementalRegistration(Registrar(rig.camera.model, levels=((48, 1.5),), max_nfev=6,
                                                        meshes=meshes))
    fitter = None
    if checks.config.joint_fit:
        side = min(128, max(rig.camera.model.width, rig.camera.model.height) // 4)
        fitter = Registrar(rig.camera.model, levels=(), refine=((max(24, 3 * side // 4), 0.8), (side, 0.5)),
                           rounds=1, refine_nfev=20, predictor=rig_predictor(rig, meshes), meshes=meshes)
    return SweepChecks(checks, sweep.satellite, sweep.build, incremental, fitter=fitter)
