"""The simulated TOUCAN's frame source: the World's state → a raw mosaic, plus its ground truth.

The camera simulator (USB3 Vision transport) calls :meth:`SimFrameSource.capture` for
every frame; tests and the processing benchmarks call :meth:`SimFrameSource.truth`
to compare what processing recovered with what the scene really was.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from m2s2hil.simulators.scene import Scene, SceneError, SceneParams, Shaded
from m2s2hil.simulators.sensor import Sensor, SensorParams

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
    _shaded: Shaded | None = field(default=None, repr=False)
    _n_bands: int = field(default=10, repr=False)
    _cube: np.ndarray | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def signal(self) -> np.ndarray:
        """(H, W) float32 noise-free signal DN each pixel receives through its own band."""
        if self._shaded is None:
            return np.zeros(self.labels.shape, dtype=np.float32)
        return self._shaded.rate * np.float32(self.dn_scale)

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
    """

    def __init__(
        self, world: Any, camera_model: Any, materials_of_build: MaterialsOfBuild,
        sensor_params: SensorParams | None = None, seed: int = 0, scene_params: SceneParams | None = None,
        threads: int | None = None,
    ) -> None:
        self.world = world
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

    def capture(self, exposure_s: float, gain: float = 1.0) -> np.ndarray:
        """One raw frame of the world as it is now: uint16 (height, width) mosaic."""
        w = self.world
        with self._lock:
            pose = w.pose()
            lamps = dict(w.lamp_output())
            temp = float(w.sensor_temperature_c)
            sat, build = str(w.satellite), str(w.build)
            spot = float(w.spot_angle_deg)
            cap = bool(w.lens_cap)
            mats = self.materials(sat, build)
            names = ["background", *mats]
            if cap:
                shaded = None
                frame = self.sensor.expose(None, exposure_s, gain, temp)
            else:
                shaded = self.scene.render(
                    sat, mats, pose.azimuth_deg, pose.tilt_deg, lamps, w.lamp_info, spot,
                    band_gain=self.sensor.band_gain,
                )
                frame = self.sensor.expose(shaded.rate, exposure_s, gain, temp)
            self._truth = FrameTruth(
                labels=self._no_labels if shaded is None else shaded.label,
                class_names=names, satellite=sat, build=build,
                azimuth_deg=float(pose.azimuth_deg), tilt_deg=float(pose.tilt_deg), lamps=lamps,
                spot_angle_deg=spot, exposure_s=float(exposure_s), gain=float(gain), temperature_c=temp,
                lens_cap=cap, dn_scale=float(exposure_s) * self.sensor.dn_per_e(gain),
                _shaded=shaded, _n_bands=self.n_bands,
            )
            return frame

    def truth(self) -> FrameTruth:
        """Ground truth of the last captured frame."""
        with self._lock:
            if self._truth is None:
                raise RuntimeError("no frame captured yet: call capture() first")
            return self._truth
