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

The mask is not the silhouette (edge pixels partly covered, dark or shadowed parts, the
mosaic's band offsets), and fitted as one its bias comes out as a larger scale and a yaw.
``rounds`` of refinement take it out (``session_registrar``, what ``sessions register`` runs):
the twin predicts each frame's mask at the placement found so far
(``projection.MaskPredictor``: its shaded frame under the frame's lamps and exposure, through
the same mask rule), and the silhouettes, supersampled 4×, are fitted to the masks less that
predicted bias; the residual is then 1 − the IoU of the predicted masks with the seen ones.
That step from silhouette to mask is linear, which a part a pixel wide is not; a pattern
search (``polish``) then minimises the count of pixels where the predicted masks (scale
included) and the seen ones differ, which is cheap (a predicted mask is one shaded render).

Incrementally during a sweep, :class:`IncrementalRegistration` keeps each frame's small
mask (a few kB) and refits, warm-started, when enough new azimuth has been seen.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares  # type: ignore[import-untyped]

from m2s2hil.errors import UsageError
from m2s2hil.twin.projection import (
    NOMINAL,
    MaskPredictor,
    Placement,
    TwinCamera,
    backdrop_noise,
    coverage_of,
    observed_mask,
)

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
    # The frame's light, for the twin's prediction of the mask's bias (``MaskPredictor``);
    # an exposure of 0: unknown, the fit then takes the mask as the silhouette.
    lamps_on: tuple[int, ...] = ()
    exposure_s: float = 0.0
    gain: float = 1.0
    noise_norm: float = 0.0
    backdrop_norm: float = 0.0

    @classmethod
    def from_cube(cls, satellite: str, build: str, azimuth_deg: float, tilt_deg: float,
                  cube: np.ndarray, keep: int = 128, *, lamps_on: Sequence[int] = (),
                  exposure_s: float = 0.0, gain: float = 1.0) -> Observation:
        """From a processed cube; the mask is kept at ``keep`` px (coverage ≥ 0.5)."""
        arr = np.asarray(cube)
        mask = observed_mask(arr)
        h, w = mask.shape
        f = max(h, w) / keep
        if f > 1:
            small = coverage_of(mask, (max(8, round(h / f)), max(8, round(w / f))))
            mask = small >= 0.5
        bg, noise = backdrop_noise(arr)
        return cls(satellite, build, float(azimuth_deg), float(tilt_deg), mask,
                   tuple(int(c) for c in lamps_on), float(exposure_s), float(gain), noise, bg)

    @classmethod
    def from_meta(cls, satellite: str, build: str, cube: np.ndarray, meta: Mapping[str, Any],
                  keep: int = 128) -> Observation | None:
        """From a processed cube and its frame's metadata (pose read back, lamps, exposure);
        None when the metadata has no pose."""
        pose = meta.get("pose") or {}
        az, tilt = pose.get("turntable_deg"), pose.get("tilt_deg")
        if not isinstance(az, (int, float)) or not isinstance(tilt, (int, float)):
            return None
        lamps = [int(c) for c in meta.get("lamps_on") or [] if isinstance(c, int)]
        exposure = meta.get("exposure_s")
        gain = meta.get("gain")
        return cls.from_cube(satellite, build, float(az), float(tilt), cube, keep, lamps_on=lamps,
                             exposure_s=float(exposure) if isinstance(exposure, (int, float)) else 0.0,
                             gain=float(gain) if isinstance(gain, (int, float)) else 1.0)


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
    """Fits placements for one camera model; holds the twin cameras of its levels.

    ``levels`` are the coarse-to-fine fit from the start (size px, blur σ); ``refine`` the
    levels of the ``rounds`` refinements after it, supersampled ``refine_supersample``× (so
    the silhouette moves smoothly at a tenth of a pixel). With a ``predictor`` each round
    first predicts, at the placement found so far, what the mask rule makes of every frame
    (``MaskPredictor``) and fits the silhouettes to the masks less that bias; the residual is
    then 1 − the IoU of the predicted masks with the seen ones. Without one (or for frames of
    unknown exposure) the masks stand for the silhouettes."""

    def __init__(self, model: Any, *, levels: Sequence[tuple[int, float]] = ((48, 1.5), (96, 0.8)),
                 diameter_mm: float | None = None, max_nfev: int = 12,
                 refine: Sequence[tuple[int, float]] = ((96, 0.8), (128, 0.5)), rounds: int = 0,
                 refine_supersample: int = 4, refine_nfev: int = 30, predictor: MaskPredictor | None = None,
                 meshes: Mapping[tuple[str, str], Any] | None = None, polish: bool = False,
                 polish_halvings: int = 3, polish_evals: int = 150) -> None:
        kw: dict[str, Any] = {"meshes": meshes}
        if diameter_mm is not None:
            kw["diameter_mm"] = diameter_mm
        self.levels = [(TwinCamera(model, size, **kw), float(sigma)) for size, sigma in levels]
        self.refine = [(TwinCamera(model, size, supersample=refine_supersample, **kw), float(sigma))
                       for size, sigma in refine] if rounds > 0 else []
        self.rounds = int(rounds)
        self.max_nfev = int(max_nfev)
        self.refine_nfev = int(refine_nfev)
        self.predictor = predictor
        self.polish = bool(polish)
        self.polish_halvings, self.polish_evals = int(polish_halvings), int(polish_evals)
        self._renders = 0

    def _level(self, obs: Sequence[Observation], twin: TwinCamera, sigma: float) -> _Level:
        masks = [coverage_of(o.mask, twin.shape) >= 0.5 for o in obs]
        targets = [_blur(coverage_of(np.asarray(o.mask, np.float32), twin.shape), sigma) for o in obs]
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

    def _fit(self, obs: Sequence[Observation], x: np.ndarray, levels: Sequence[tuple[TwinCamera, float]],
             free: np.ndarray, first_nfev: int, nfev: int) -> tuple[np.ndarray, _Level, list]:
        lv: _Level | None = None
        mounts: list[Any] = []
        x = x.copy()
        for i, (twin, sigma) in enumerate(levels):
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
                                x_scale=_STEPS[idx] * 5, max_nfev=nfev if i else first_nfev)
            x[idx] = res.x
        assert lv is not None
        return x, lv, mounts

    def _predicted(self, obs: Sequence[Observation], p: Placement, *,
                   scaled: bool = False) -> list[np.ndarray] | None:
        """Each frame's mask as the twin predicts it at ``p`` (its scale too if ``scaled``;
        None: no predictor, or a frame whose light is unknown)."""
        pr = self.predictor
        if pr is None or any(o.exposure_s <= 0 or not o.lamps_on for o in obs):
            return None
        q = p if scaled else replace(p, scale=1.0)
        out = []
        for o in obs:
            m = pr.twin.mounted(o.satellite, o.build)
            out.append(pr.coverage(m, o.azimuth_deg, o.tilt_deg, q, o.lamps_on,
                                   o.exposure_s, o.gain, o.noise_norm, o.backdrop_norm, o.mask.shape))
        self._renders += len(obs)
        return out

    def _polish(self, obs: Sequence[Observation], x: np.ndarray, free: np.ndarray) -> np.ndarray:
        """A pattern search on what the fit is for: the pixels where the predicted masks and
        the seen ones differ. The refinement's step from silhouette to mask is linear, which a
        part a pixel wide (the ISS's trusses) is not; the count is exact but not smooth, so no
        gradient: each parameter is stepped both ways, improvements kept, steps halved."""

        def cost(v: np.ndarray) -> int:
            pred = self._predicted(obs, Placement.from_vector(v), scaled=True)
            assert pred is not None
            return sum(int(((pm >= 0.5) ^ o.mask).sum()) for pm, o in zip(pred, obs, strict=True))

        x = x.copy()
        best = cost(x)
        step = _STEPS / 4  # 0.1 mm, 0.1 deg, 0.075 deg, 0.1 % of scale
        evals = 0
        for _ in range(self.polish_halvings):
            improved = True
            while improved and evals < self.polish_evals:
                improved = False
                for k in np.flatnonzero(free):
                    for sign in (1.0, -1.0):
                        v = x.copy()
                        v[k] = float(np.clip(v[k] + sign * step[k], _LOWER[k], _UPPER[k]))
                        c = cost(v)
                        evals += 1
                        if c < best:
                            x, best, improved = v, c, True
                            break
            step = step / 2
        return x

    def register(self, observations: Sequence[Observation], start: Placement = NOMINAL, *,
                 fit_scale: bool = True, fit_tilt: bool = True) -> Registration:
        """Fit a placement to ``observations`` (frames of one mount), from ``start``."""
        t0 = time.perf_counter()
        obs = [o for o in observations if o.mask.any()]
        if not obs:
            raise RegistrationError("no frame with the mockup in view to register against")
        free = np.array([True, True, True, fit_tilt, fit_scale])
        x = np.clip(start.vector(), _LOWER, _UPPER)
        self._renders = 0
        if not self.levels and not self.refine:
            raise RegistrationError("a registrar needs levels or refinement rounds")
        lv: _Level | None = None
        mounts: list[Any] = []
        if self.levels:  # none: refine only, from ``start`` (a warm start or a check's prior)
            x, lv, mounts = self._fit(obs, x, self.levels, free, 2 * self.max_nfev, self.max_nfev)
        pred = None
        for _ in range(self.rounds):
            p = Placement.from_vector(x)
            pred = self._predicted(obs, p)
            targets = obs
            if pred is not None:
                # The masks less the bias the twin predicts at this placement: what a silhouette
                # alone would show (the bias is the predicted mask less the twin's silhouette).
                fine = self.refine[-1][0]
                targets = []
                for o, pm in zip(obs, pred, strict=True):
                    m = fine.mounted(o.satellite, o.build)
                    cov = coverage_of(fine.coverage(m, o.azimuth_deg, o.tilt_deg, replace(p, scale=1.0)),
                                      o.mask.shape)
                    targets.append(replace(o, mask=o.mask.astype(np.float32) - (pm - cov)))
                self._renders += len(obs)  # the silhouettes (the predictions count themselves)
            x, lv, mounts = self._fit(targets, x, self.refine, free, self.refine_nfev, self.refine_nfev)
        if self.polish and self._predicted(obs[:1], Placement.from_vector(x)) is not None:
            x = self._polish(obs, x, free)
        p = Placement.from_vector(x)
        assert lv is not None
        twin = lv.twin
        pred = self._predicted(obs, p, scaled=self.polish) if self.rounds else None
        if pred is not None:  # how well the twin explains the masks as seen
            ious = tuple(iou(pm >= 0.5, o.mask) for pm, o in zip(pred, obs, strict=True))
        else:
            masks = [coverage_of(o.mask, twin.shape) >= 0.5 for o in obs]
            ious = tuple(iou(twin.coverage(m, o.azimuth_deg, o.tilt_deg, p) >= 0.5, mk)
                         for o, m, mk in zip(obs, mounts, masks, strict=True))
        self._renders += len(obs)
        return Registration(p, 1.0 - float(np.mean(ious)), ious, len(obs),
                            azimuth_span([o.azimuth_deg for o in obs]), self._renders,
                            time.perf_counter() - t0, fit_scale)


def session_registrar(rig: Any, **kw: Any) -> Registrar:
    """The offline fit for a rig's frames: coarse to fine, then three rounds refined against
    the twin's prediction of each mask (``MaskPredictor``, the rig's lamps, sensor and meshes)."""
    model = rig.camera.model
    meshes = rig_meshes(rig)
    # Refined at the masks' own size (the superpixel cube's, at most the 128 px they are kept at).
    side = min(128, max(int(model.width), int(model.height)) // 4)
    kw.setdefault("refine", ((max(24, 3 * side // 4), 0.8), (side, 0.5)))
    kw.setdefault("rounds", 3)
    kw.setdefault("polish", True)
    kw.setdefault("predictor", rig_predictor(rig, meshes))
    return Registrar(model, meshes=meshes, **kw)


def rig_meshes(rig: Any) -> dict[tuple[str, str], Any]:
    """The lab's meshes the rig file names (empty for the built-in mockups)."""
    sim = getattr(rig, "simulation", None)
    if sim is None or not getattr(sim, "mockups", None):
        return {}
    from m2s2hil.sim_config import mesh_mockups

    return mesh_mockups(rig)


def rig_predictor(rig: Any, meshes: Mapping[tuple[str, str], Any] | None = None) -> MaskPredictor:
    """The twin's mask prediction for a rig: its camera, lamps, spotlight angle and sensor."""
    from m2s2hil.simulators.world import LampInfo

    sim = getattr(rig, "simulation", None)
    info = {lc.channel: LampInfo(name, lc.kind, lc.warmup_s) for name, lc in rig.lamps.items()}
    return MaskPredictor(rig.camera.model, info,
                         spot_angle_deg=sim.spot_angle_deg if sim is not None else 45.0,
                         sensor_params=sim.sensor.params() if sim is not None else None,
                         meshes=meshes if meshes is not None else rig_meshes(rig))


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
        if not isinstance(pose.get("turntable_deg"), (int, float)) or not isinstance(pose.get("tilt_deg"),
                                                                                     (int, float)):
            continue
        o = Observation.from_meta(sweep.satellite, sweep.build, store.read_cube(fr.event_id), fr.meta, keep)
        if o is not None:
            out.append(o)
    return out


def register_session(store: Any, registrar: Registrar | None = None, *, max_frames: int = 24,
                     record: bool = True) -> Registration:
    """Register a stored session's mockup from its frames; with ``record`` (the store open for
    writing), the result goes into the session's event log as ``twin_registration``."""
    fitter = registrar or session_registrar(store.rig)
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
