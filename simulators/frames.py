"""The simulated TOUCAN's frame source: the World's state → a raw mosaic, plus its ground truth.

The camera simulator (USB3 Vision transport) calls :meth:`SimFrameSource.capture` for
every frame; tests and the processing benchmarks call :meth:`SimFrameSource.truth`
to compare what processing recovered with what the scene really was.

Exposure over time: given the exposure's start (``start_s``, as the camera knows it),
the frame shows the stage pose at mid-exposure, and if the stage moved during the
exposure by more than ``blur_threshold_px`` at the mockup's rim, the sensor integrates
the average of K renders at evenly spaced moments (K odd, so the middle one is the
mid-exposure pose; about one render per pixel of motion, at most ``max_sub_exposures``):
a frame taken while the turntable turns carries the motion blur a real one has. A
stage at rest costs one (cached) render, as before.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from m2s2hil.simulators.scene import Scene, SceneError, SceneParams, Shaded
from m2s2hil.simulators.sensor import Sensor, SensorParams
from m2s2hil.simulators.targets import white_panel_pattern, white_panel_rate

MaterialsOfBuild = Callable[[str, str], Sequence[str]] | Mapping[Any, Any]


@dataclass
class FrameTruth:
    """Ground truth of one captured frame.

    ``labels`` index ``class_names`` (0 = background). ``signal()`` and ``radiance()``
    are the noise-free scene signal in DN for the frame's exposure and gain, without
    black level or dark current and before clipping: ``signal()`` on the mosaic,
    ``radiance()`` for every band at every pixel (computed on first use: 168 MB at
    2048²). Sampling ``radiance()`` through the MSFA layout gives ``signal()``.
    With the lens cap on nothing reaches the sensor: labels are all background and
    both are zero.

    A frame exposed while the stage moved (``sub_exposures`` > 1): ``labels``,
    ``radiance()`` and the pose are those of mid-exposure (the sharp scene the frame is
    meant to show); ``signal()`` is what the sensor integrated, the average over the
    exposure, blur included (so it is no longer the MSFA sampling of ``radiance()``).
    ``motion_px`` is the stage's motion during the exposure at the mockup's rim.
    """

    labels: np.ndarray  # (H, W) uint8
    class_names: list[str]
    satellite: str
    build: str
    azimuth_deg: float
    tilt_deg: float
    lamps: dict[int, float]  # relay channel → relative output
    spot_angle_deg: float
    exposure_s: float
    gain: float
    temperature_c: float
    lens_cap: bool
    dn_scale: float  # DN per (electron/s) for this exposure and gain
    exposure_start_s: float | None = None  # clock time; None: rendered at the pose of the call
    motion_px: float = 0.0  # path of the mockup's rim during the exposure, in sensor pixels
    sub_exposures: int = 1  # renders averaged into the frame (1: no motion blur)
    _shaded: Shaded | None = field(default=None, repr=False)
    _rate: np.ndarray | None = field(default=None, repr=False)  # integrated rate, if not _shaded's
    _n_bands: int = field(default=10, repr=False)
    _cube: np.ndarray | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def signal(self) -> np.ndarray:
        """(H, W) float32 noise-free signal DN each pixel receives through its own band."""
        if self._shaded is None:
            return np.zeros(self.labels.shape, dtype=np.float32)
        rate = self._shaded.rate if self._rate is None else self._rate
        return rate * np.float32(self.dn_scale)

    def irradiance(self) -> np.ndarray:
        """(H, W) float32 light reaching each pixel's surface, before its reflectance (the
        renderer's diffuse factor: 1 for a face square to one lamp of unit irradiance; the room
        bounce alone in a shadow; on the backdrop, the light the backdrop gets); zero with the
        cap on."""
        if self._shaded is None:
            return np.zeros(self.labels.shape, dtype=np.float32)
        return np.asarray(self._shaded.diffuse, dtype=np.float32)

    def radiance(self) -> np.ndarray:
        """(n_bands, H, W) float32 noise-free signal DN of every band at every pixel."""
        with self._lock:
            if self._cube is None:
                if self._shaded is None:
                    self._cube = np.zeros((self._n_bands, *self.labels.shape), dtype=np.float32)
                else:
                    self._cube = self._shaded.cube(self.dn_scale)
            return self._cube


class SimFrameSource:
    """Renders what the camera sees in ``world`` and exposes it on the simulated sensor.

    ``camera_model``: any object with ``width``, ``height``, ``bit_depth``, ``bands_nm``,
    ``fwhm_nm``, ``layout`` (n × n band indices) and optionally ``full_scale``.
    ``materials_of_build``: ``f(satellite, build) -> materials`` or a mapping
    ``{(satellite, build): materials}`` / ``{satellite: {build: materials}}``.
    ``gain`` in :meth:`capture` is a linear analog gain factor (1.0 = unity).
    ``blur_threshold_px`` and ``max_sub_exposures``: see the module docstring.
    """

    def __init__(
        self, world: Any, camera_model: Any, materials_of_build: MaterialsOfBuild,
        sensor_params: SensorParams | None = None, seed: int = 0, scene_params: SceneParams | None = None,
        threads: int | None = None, blur_threshold_px: float = 0.5, max_sub_exposures: int = 15,
    ) -> None:
        if not blur_threshold_px > 0 or max_sub_exposures < 1:
            raise SceneError("blur threshold must be > 0 px and max_sub_exposures >= 1")
        self.world = world
        self.blur_threshold_px = float(blur_threshold_px)
        self.max_sub_exposures = int(max_sub_exposures)
        m = camera_model
        try:
            width, height = int(m.width), int(m.height)
            bands, fwhm, layout = tuple(m.bands_nm), tuple(m.fwhm_nm), tuple(tuple(r) for r in m.layout)
            full_scale = int(getattr(m, "full_scale", (1 << int(m.bit_depth)) - 1))
        except (AttributeError, TypeError) as exc:
            raise SceneError(f"camera model lacks a field the simulator needs: {exc}") from None
        self.n_bands = len(bands)
        self.scene = Scene(width, height, bands, fwhm, layout,
                           scene_params or SceneParams(threads=threads))
        try:
            self.sensor = Sensor(width, height, layout, bands, fwhm, full_scale, sensor_params, seed, threads)
        except ValueError as exc:
            raise SceneError(str(exc)) from None
        self._materials_of_build = materials_of_build
        self._lock = threading.Lock()
        self._truth: FrameTruth | None = None
        self._no_labels = np.zeros((height, width), dtype=np.uint8)
        self._no_labels.flags.writeable = False
        self._panel: np.ndarray | None = None  # the white panel's per-pixel pattern, made when first seen

    @property
    def band_response(self) -> np.ndarray:
        """Electrons/s per band for a white diffuser at unit irradiance (lamp spectrum × QE × optics)."""
        return self.scene.lamp_spectrum * self.sensor.band_gain

    def materials(self, satellite: str, build: str) -> list[str]:
        src = self._materials_of_build
        if callable(src):
            return list(src(satellite, build))
        for key in ((satellite, build), (satellite.lower(), build.upper())):
            if key in src:
                return list(src[key])
        for s in (satellite, satellite.lower()):
            if s in src and isinstance(src[s], Mapping):
                for b in (build, build.upper()):
                    if b in src[s]:
                        return list(src[s][b])
        raise SceneError(f"no material list for satellite {satellite!r} build {build!r}")

    @property
    def rim_px(self) -> float:
        """Radius of the mockup's bounding sphere in sensor pixels: the farthest any of it
        is from the rotation axes (both pass through its centre)."""
        return self.scene.params.fill * min(self.scene.width, self.scene.height)

    def motion_px(self, poses: Sequence[Any]) -> float:
        """Path length of the rim, in sensor pixels, through successive ``poses``."""
        deg = sum(math.hypot(b.azimuth_deg - a.azimuth_deg, b.tilt_deg - a.tilt_deg)
                  for a, b in itertools.pairwise(poses))
        return self.rim_px * math.radians(deg)

    def sub_exposures(self, motion_px: float) -> int:
        """Renders to average for ``motion_px`` of motion: 1 up to the threshold, else about
        one per pixel, odd (the middle one is mid-exposure), at most ``max_sub_exposures``."""
        if not motion_px > self.blur_threshold_px:
            return 1
        k = min(self.max_sub_exposures, max(3, math.ceil(motion_px)))
        if k % 2 == 0:
            k = k + 1 if k < self.max_sub_exposures else k - 1
        return k

    def capture(self, exposure_s: float, gain: float = 1.0, *, start_s: float | None = None) -> np.ndarray:
        """One raw frame: uint16 (height, width) mosaic.

        Without ``start_s``: the world as it is at the call. With ``start_s`` (clock time the
        exposure began): the pose at mid-exposure, blurred by the stage's motion over
        ``[start_s, start_s + exposure_s]`` (see the module docstring).
        """
        w = self.world
        with self._lock:
            motion = 0.0
            if start_s is None or not (math.isfinite(exposure_s) and exposure_s > 0):
                poses = [w.pose()]  # (a bad exposure is refused by the sensor below)
            else:
                t0 = float(start_s)
                ends = [w.pose_at(t0), w.pose_at(t0 + exposure_s / 2), w.pose_at(t0 + exposure_s)]
                motion = self.motion_px(ends)
                k = self.sub_exposures(motion)
                step = exposure_s / k
                poses = [ends[1]] if k == 1 else [w.pose_at(t0 + (j + 0.5) * step) for j in range(k)]
            pose = poses[len(poses) // 2]
            lamps = dict(w.lamp_output())
            temp = float(w.sensor_temperature_c)
            sat, build = str(w.satellite), str(w.build)
            spot = float(w.spot_angle_deg)
            cap = bool(w.lens_cap)
            target = str(w.target)
            mats = self.materials(sat, build)
            names = ["background", *mats]
            shaded: Shaded | None = None
            rate: np.ndarray | None = None  # the average over the sub-exposures, if several
            if cap:
                frame = self.sensor.expose(None, exposure_s, gain, temp)
            elif target == "white_panel":
                if self._panel is None:  # per camera, not per frame (~80 ms at 2048²)
                    self._panel = white_panel_pattern(self.band_response, self.sensor.band_map())
                panel = white_panel_rate(self._panel, lamps, w.lamp_info, spot, self.scene.params.lighting)
                frame = self.sensor.expose(panel, exposure_s, gain, temp)
            else:
                # The mockup as it really sits (world.Placement): yaw adds to the turntable's
                # angle, the tilt bias to the stage's, the offset moves it off the axis.
                place = getattr(w, "placement", None)
                yaw = place.yaw_deg if place else 0.0
                bias = place.tilt_bias_deg if place else 0.0
                offset = None
                if place is not None and (place.offset_x_mm or place.offset_y_mm):
                    offset = place.offset_units(self.scene.mount(sat, mats, build).radius)
                for i, p in enumerate(poses):
                    sub = self.scene.render(
                        sat, mats, p.azimuth_deg + yaw, p.tilt_deg + bias, lamps, w.lamp_info, spot,
                        band_gain=self.sensor.band_gain, offset=offset, build=build,
                    )
                    if i == len(poses) // 2:
                        shaded = sub
                    if len(poses) > 1:
                        if rate is None:
                            rate = sub.rate.astype(np.float32, copy=True)
                        else:
                            rate += sub.rate
                assert shaded is not None
                if rate is not None:
                    rate *= np.float32(1.0 / len(poses))
                    rate.flags.writeable = False
                frame = self.sensor.expose(shaded.rate if rate is None else rate, exposure_s, gain, temp)
            self._truth = FrameTruth(
                labels=self._no_labels if shaded is None else shaded.label,
                class_names=names, satellite=sat, build=build,
                azimuth_deg=float(pose.azimuth_deg), tilt_deg=float(pose.tilt_deg), lamps=lamps,
                spot_angle_deg=spot, exposure_s=float(exposure_s), gain=float(gain), temperature_c=temp,
                lens_cap=cap, dn_scale=float(exposure_s) * self.sensor.dn_per_e(gain),
                exposure_start_s=None if start_s is None else float(start_s), motion_px=float(motion),
                sub_exposures=len(poses), _shaded=shaded, _rate=rate, _n_bands=self.n_bands,
            )
            return frame

    def truth(self) -> FrameTruth:
        """Ground truth of the last captured frame."""
        with self._lock:
            if self._truth is None:
                raise RuntimeError("no frame captured yet: call capture() first")
            return self._truth
