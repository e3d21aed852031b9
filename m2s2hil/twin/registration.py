"""Registration: how the mockup sits on the rig, from the frames a session captured.

The twin (``projection.TwinCamera``: the simulator's mockup at the frame's recorded pose)
is fitted to the captured frames across azimuths: the mockup's offset from the turntable
axis (x, y, mm), its yaw at azimuth 0, the tilt stage's bias and a scale. An offset moves
the silhouette along a sinusoid in azimuth and the yaw turns it, so frames at several
azimuths pin all of them down; one frame alone cannot tell an offset from a yaw.

The fit: the residual of frame i is ``blur(twin coverage_i) − blur(observed mask_i)`` at a
low resolution (fractional coverage, supersampled, so it moves smoothly with the
parameters); ``scipy.optimize.least_squares`` minimises the sum over frames, with a
finite-difference Jacobian of fixed steps (a silhouette does not change under a step of
1e-8), coarse to fine (``levels``: 48 px with σ = 1.5 px first, then 96 px with σ = 0.8 px),
each level starting where the last stopped. The residual reported is 1 − the mean IoU of
the observed mask with the fitted twin's silhouette (above half coverage) at the finest
level: 0 is a perfect fit; the mask's own edge pixels keep it at about 0.1 on the simulated
rig (docs/twin.md).

Incrementally during a sweep, :class:`IncrementalRegistration` keeps each frame's small
mask (a few kB) and refits, warm-started, when enough new azimuth has been seen.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from m2s2hil.errors import UsageError
from m2s2hil.twin.projection import NOMINAL, Placement, TwinCamera, coverage_of, observed_mask

REGISTRATION_VERSION = 1
#: Finite-difference steps: dx, dy (mm), yaw, tilt bias (°), scale.
_STEPS = np.array([0.4, 0.4, 0.4, 0.3, 0.004])
#: Bounds the fit stays in: ±40 mm, ±60°, ±20°, scale 0.7–1.4.
_LOWER = np.array([-40.0, -40.0, -60.0, -20.0, 0.7])
_UPPER = np.array([40.0, 40.0, 60.0, 20.0, 1.4])


class RegistrationError(UsageError):
    """Registration that cannot run: no frames, or frames without a mockup in view (exit 2)."""


@dataclass(frozen=True)
class Observation:
    """One captured frame as registration sees it: the pose read back and the mask."""

    satellite: str
    build: str
    azimuth_deg: float
    tilt_deg: float
    mask: np.ndarray  # (H, W) bool foreground, any resolution (area-averaged to each level)

    @classmethod
    def from_cube(cls, satellite: str, build: str, azimuth_deg: float, tilt_deg: float,
                  cube: np.ndarray, keep: int = 128) -> Observation:
        """From a processed cube; the mask is kept at ``keep`` px (coverage ≥ 0.5)."""
        mask = observed_mask(np.asarray(cube))
        h, w = mask.shape
        f = max(h, w) / keep
        if f > 1:
            small = coverage_of(mask, (max(8, round(h / f)), max(8, round(w / f))))
            mask = small >= 0.5
        return cls(satellite, build, float(azimuth_deg), float(tilt_deg), mask)


@dataclass(frozen=True)
class Registration:
    """The fitted placement, how well it fits, and what it cost."""

    placement: Placement
    residual: float  # 1 − mean IoU at the finest level
    ious: tuple[float, ...]  # per frame
    frames: int
    azimuth_span_deg: float  # how much of the turn the frames cover
    evaluations: int  # twin renders
    elapsed_s: float
    fit_scale: bool = True

    def as_dict(self) -> dict[str, Any]:
        return {
            "placement": self.placement.as_dict(), "residual": round(self.residual, 4),
            "ious": [round(v, 4) for v in self.ious], "frames": self.frames,
            "azimuth_span_deg": round(self.azimuth_span_deg, 1), "evaluations": self.evaluations,
            "elapsed_s": round(self.elapsed_s, 3), "fit_scale": self.fit_scale,
            "registration_version": REGISTRATION_VERSION,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Registration:
        return cls(Placement.from_dict(d.get("placement", {})), float(d.get("residual", 1.0)),
                   tuple(float(v) for v in d.get("ious", ())), int(d.get("frames", 0)),
                   float(d.get("azimuth_span_deg", 0.0)), int(d.get("evaluations", 0)),
                   float(d.get("elapsed_s", 0.0)), bool(d.get("fit_scale", True)))


def azimuth_span(azimuths: Sequence[float]) -> float:
    """Degrees of the turn the azimuths cover (360 − the largest gap between them)."""
    a = np.sort(np.mod(np.asarray(azimuths, dtype=float), 360.0))
    if a.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, a[:1] + 360.0]))
    return float(360.0 - gaps.max())


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img


@dataclass
class _Level:
    twin: TwinCamera
    sigma: float
    targets: list[np.ndarray]
    masks: list[np.ndarray]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


class Registrar:
    """Fits placements for one camera model; holds the twin cameras of its levels."""

    def __init__(self, model: Any, *, levels: Sequence[tuple[int, float]] = ((48, 1.5), (96, 0.8)),
                 diameter_mm: float | None = None, max_nfev: int = 12) -> None:
        kw = {} if diameter_mm is None else {"diameter_mm": diameter_mm}
        self.levels = [(TwinCamera(model, size, **kw), float(sigma)) for size, sigma in levels]
        self.max_nfev = int(max_nfev)
        self._renders = 0

    def _level(self, obs: Sequence[Observation], twin: TwinCamera, sigma: float) -> _Level:
        masks = [coverage_of(o.mask, twin.shape) >= 0.5 for o in obs]
        targets = [_blur(coverage_of(o.mask, twin.shape), sigma) for o in obs]
        return _Level(twin, sigma, targets, masks)

    def _residuals(self, x: np.ndarray, lv: _Level, obs: Sequence[Observation], mounts: list) -> np.ndarray:
        p = Placement.from_vector(x)
        out = []
        for o, m, tgt in zip(obs, mounts, lv.targets, strict=True):
            cov = lv.twin.coverage(m, o.azimuth_deg, o.tilt_deg, p)
            out.append((_blur(cov, lv.sigma) - tgt).ravel())
        self._renders += len(obs)
        return np.concatenate(out)

    def _jacobian(self, x: np.ndarray, lv: _Level, obs: Sequence[Observation], mounts: list,
                  free: np.ndarray) -> np.ndarray:
        f0 = self._residuals(x, lv, obs, mounts)
        cols = []
        for k in range(x.size):
            if not free[k]:
                cols.append(np.zeros_like(f0))
                continue
            h = _STEPS[k] if x[k] + _STEPS[k] <= _UPPER[k] else -_STEPS[k]
            xk = x.copy()
            xk[k] += h
            cols.append((self._residuals(xk, lv, obs, mounts) - f0) / h)
        return np.column_stack(cols)

    def register(self, observations: Sequence[Observation], start: Placement = NOMINAL, *,
                 fit_scale: bool = True, fit_tilt: bool = True) -> Registration:
        """Fit a placement to ``observations`` (frames of one mount), from ``start``."""
        t0 = time.perf_counter()
        obs = [o for o in observations if o.mask.any()]
        if not obs:
            raise RegistrationError("no frame with the mockup in view to register against")
        mounts = [self.levels[0][0].mounted(o.satellite, o.build) for o in obs]
        free = np.array([True, True, True, fit_tilt, fit_scale])
        x = np.clip(start.vector(), _LOWER, _UPPER)
        self._renders = 0
        lv = self._level(obs, *self.levels[0])
        for i, (twin, sigma) in enumerate(self.levels):
            lv = self._level(obs, twin, sigma)
            mounts = [twin.mounted(o.satellite, o.build) for o in obs]
            idx = np.flatnonzero(free)

            def fun(z: np.ndarray, lv: _Level = lv, mounts: list = mounts,
                    idx: np.ndarray = idx) -> np.ndarray:
                full = x.copy()
                full[idx] = z
                return self._residuals(full, lv, obs, mounts)

            def jac(z: np.ndarray, lv: _Level = lv, mounts: list = mounts,
                    idx: np.ndarray = idx) -> np.ndarray:
                full = x.copy()
                full[idx] = z
                return self._jacobian(full, lv, obs, mounts, free)[:, idx]

            res = least_squares(fun, x[idx], jac=jac, bounds=(_LOWER[idx], _UPPER[idx]), method="trf",
                                x_scale=_STEPS[idx] * 5, max_nfev=self.max_nfev if i else 2 * self.max_nfev)
            x[idx] = res.x
        p = Placement.from_vector(x)
        twin = lv.twin
        ious = tuple(iou(twin.coverage(m, o.azimuth_deg, o.tilt_deg, p) >= 0.5, mk)
                     for o, m, mk in zip(obs, mounts, lv.masks, strict=True))
        self._renders += len(obs)
        return Registration(p, 1.0 - float(np.mean(ious)), ious, len(obs),
                            azimuth_span([o.azimuth_deg for o in obs]), self._renders,
                            time.perf_counter() - t0, fit_scale)


@dataclass
class IncrementalRegistration:
    """Registration kept up to date during a sweep: ``add`` each frame's observation; the
    fit is redone (warm-started) once the frames span ``min_span_deg`` and then every
    ``every`` frames, so most frames cost only their small mask."""

    registrar: Registrar
    min_span_deg: float = 90.0
    every: int = 6
    min_frames: int = 3
    _obs: list[Observation] = field(default_factory=list)
    _current: Registration | None = None
    _since: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, obs: Observation) -> Registration | None:
        """Record a frame; the registration as it stands (refitted if due)."""
        with self._lock:
            if self._obs and (obs.satellite, obs.build) != (self._obs[0].satellite, self._obs[0].build):
                self._obs, self._current, self._since = [], None, 0  # another mount: start again
            self._obs.append(obs)
            self._since += 1
            obs_now = list(self._obs)
            due = (len(obs_now) >= self.min_frames
                   and azimuth_span([o.azimuth_deg for o in obs_now]) >= self.min_span_deg
                   and (self._current is None or self._since >= self.every))
            start = self._current.placement if self._current else NOMINAL
            if not due:
                return self._current
            self._since = 0
        reg = self.registrar.register(obs_now, start)
        with self._lock:
            self._current = reg
        return reg

    @property
    def current(self) -> Registration | None:
        with self._lock:
            return self._current


def mm_error(a: Placement, b: Placement) -> float:
    """Distance between two placements' offsets, mm."""
    return math.hypot(a.dx_mm - b.dx_mm, a.dy_mm - b.dy_mm)


#: The session event that holds a registration (``SessionStore.record_event``).
EVENT_KIND = "twin_registration"


def session_observations(store: Any, *, max_frames: int = 24, keep: int = 128) -> list[Observation]:
    """Observations of a stored session's frames (at most ``max_frames``, spread over the
    sweep in capture order), the pose read back from each frame's metadata."""
    sweep = store.sweep
    frames = store.frames()
    if len(frames) > max_frames:
        pick = np.linspace(0, len(frames) - 1, max_frames).round().astype(int)
        frames = [frames[i] for i in sorted(set(pick.tolist()))]
    out = []
    for fr in frames:
        pose = fr.meta.get("pose") or {}
        az, tilt = pose.get("turntable_deg"), pose.get("tilt_deg")
        if not isinstance(az, (int, float)) or not isinstance(tilt, (int, float)):
            continue
        cube = store.read_cube(fr.event_id)
        out.append(Observation.from_cube(sweep.satellite, sweep.build, float(az), float(tilt), cube, keep))
    return out


def register_session(store: Any, registrar: Registrar | None = None, *, max_frames: int = 24,
                     record: bool = True) -> Registration:
    """Register a stored session's mockup from its frames; with ``record`` (the store open for
    writing), the result goes into the session's event log as ``twin_registration``."""
    fitter = registrar or Registrar(store.rig.camera.model)
    reg = fitter.register(session_observations(store, max_frames=max_frames))
    if record:
        store.record_event(EVENT_KIND, reg.as_dict())
    return reg


def stored_registration(store: Any) -> dict[str, Any] | None:
    """The session's latest registration (its event's payload), or, lacking one, the last
    one the capture-time checks reached (``meta["qc"]["twin"]["registration"]``)."""
    for ev in reversed(store.events()):
        if ev.get("kind") == EVENT_KIND:
            payload = ev.get("payload")
            return dict(payload, source="session") if isinstance(payload, dict) else None
    for fr in reversed(store.frames()):
        qc = fr.meta.get("qc")
        twin = qc.get("twin") if isinstance(qc, dict) else None
        if isinstance(twin, dict) and isinstance(twin.get("registration"), dict):
            return dict(twin["registration"], source="capture")
    return None


def registration_text(reg: dict[str, Any]) -> str:
    """One line for people: a stored registration (``stored_registration``'s dict)."""
    p = Placement.from_dict(reg.get("placement") or {})
    residual = float(reg.get("residual", 1.0))
    return (f"offset ({p.dx_mm:+.2f}, {p.dy_mm:+.2f}) mm, yaw {p.yaw_deg:+.2f} deg, tilt bias "
            f"{p.tilt_bias_deg:+.2f} deg, scale {p.scale:.3f}; residual {residual:.3f} "
            f"over {int(reg.get('frames', 0))} frames ({float(reg.get('azimuth_span_deg', 0.0)):.0f} deg of "
            f"azimuth; {reg.get('source', 'session')})")
