"""The twin's camera: the simulator's mockup meshes projected at a frame's recorded pose, for
a placement of the mockup on the rig, at low resolution.

A :class:`Placement` is what registration estimates (``m2s2hil.twin.registration``): the
mockup's centre off the turntable axis (mm, in the turntable's frame at azimuth 0: x to the
camera's right, y away from it), its yaw at azimuth 0, the tilt stage's bias, and a scale
(the camera's distance and the lens, as a factor on the simulator's nominal fill). It is the
same model the simulated rig perturbs (``simulators.world.Placement``), so a placement the
rig file sets is the one registration should find.

:class:`TwinCamera` renders, at ``size`` px on the long side: the mockup's fractional
silhouette (supersampled, so that it moves smoothly with the parameters, which the
optimiser needs), its label map, and its shaded view under given lamps (the scene renderer
itself, for the photometric checks). Observed frames come in as processed cubes;
:func:`observed_mask` is the one foreground rule (a spectrum's distance from the
backdrop's).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import cv2
import numpy as np

from m2s2hil.catalog import load_catalog
from m2s2hil.simulators.raster import rasterize
from m2s2hil.simulators.scene import MountedScene, Scene, SceneParams, Shaded

#: The bench's mockup size (bounding-sphere diameter, mm): the simulated rig's default too
#: (``[simulation.mount] diameter_mm``). An assumption: the printed mockups are about 16 cm.
DIAMETER_MM = 160.0


@dataclass(frozen=True)
class Placement:
    """How the mockup sits: offset (mm), yaw and tilt bias (°), scale (1: nominal)."""

    dx_mm: float = 0.0
    dy_mm: float = 0.0
    yaw_deg: float = 0.0
    tilt_bias_deg: float = 0.0
    scale: float = 1.0

    @classmethod
    def from_vector(cls, v: Sequence[float] | np.ndarray) -> Placement:
        return cls(*(float(x) for x in v))

    def vector(self) -> np.ndarray:
        return np.array([self.dx_mm, self.dy_mm, self.yaw_deg, self.tilt_bias_deg, self.scale])

    def as_dict(self) -> dict[str, float]:
        return {k: round(float(v), 4) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Placement:
        keys = ("dx_mm", "dy_mm", "yaw_deg", "tilt_bias_deg", "scale")
        return cls(**{k: float(d[k]) for k in keys if k in d})


NOMINAL = Placement()


def backdrop_noise(cube: np.ndarray) -> tuple[float, float]:
    """The backdrop's spectrum norm and its noise norm (``observed_mask``'s border statistics)."""
    arr = np.asarray(cube, dtype=np.float32)
    border = np.concatenate([arr[:, 0, :], arr[:, 1:, 0], arr[:, 1:, -1]], axis=1)
    bg = np.median(border, axis=1)
    sigma = 1.4826 * np.median(np.abs(border - bg[:, None]), axis=1)
    return float(np.linalg.norm(bg)), float(np.linalg.norm(sigma))


def observed_mask(cube: np.ndarray, *, contrast: float = 0.12, noise_norm: float | None = None) -> np.ndarray:
    """(H, W) bool foreground of a processed cube ``(bands, H, W)``: pixels whose spectrum
    differs from the backdrop's by more than ``contrast`` of its norm (or than its noise).
    The backdrop is
    uniform on the bench (a diffuse sheet, ``simulators.shading``), so its spectrum is the
    median of the frame's top, left and right borders (the stand leaves at the bottom). Dark
    filaments and shadows are darker than the backdrop, so they count, which Otsu on
    brightness alone misses."""
    arr = np.asarray(cube, dtype=np.float32)
    border = np.concatenate([arr[:, 0, :], arr[:, 1:, 0], arr[:, 1:, -1]], axis=1)
    bg = np.median(border, axis=1)
    # The backdrop's noise per band (MAD): a dim backdrop's distance is mostly noise, whose
    # norm over 10 bands is about sqrt(Σσ²) ± 0.7σ; 1.7·sqrt(Σσ²) keeps false pixels rare.
    sigma = 1.4826 * np.median(np.abs(border - bg[:, None]), axis=1)
    # ``noise_norm``: a noise-free render (the twin's prediction of a frame) given the frame's noise.
    noise = float(np.linalg.norm(sigma)) if noise_norm is None else float(noise_norm)
    threshold = max(contrast * float(np.linalg.norm(bg)), 1.7 * noise)
    if not threshold > 0:
        return np.zeros(arr.shape[1:], dtype=bool)
    diff = arr - bg[:, None, None]
    dist = np.sqrt(np.einsum("bhw,bhw->hw", diff, diff))
    mask = (dist > threshold).astype(np.uint8)
    # Sensor noise and hot pixels leave isolated specks: drop components of under 3 px (an
    # opening would also erase the struts one pixel wide).
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.zeros(n, dtype=bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= 3
    return keep[lab]


def coverage_of(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A boolean mask area-averaged to ``shape`` (H, W): fractional coverage, float32."""
    m = np.asarray(mask, dtype=np.float32)
    if m.shape == shape:
        return m
    return cv2.resize(m, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


class TwinCamera:
    """The twin's view of the rig for a camera ``model`` (bands, layout, aspect) at ``size`` px."""

    def __init__(self, model: Any, size: int = 96, *, diameter_mm: float = DIAMETER_MM,
                 supersample: int = 2, fill: float | None = None,
                 meshes: Mapping[tuple[str, str], Any] | None = None) -> None:
        w, h = int(model.width), int(model.height)
        self.width = int(size) if w >= h else max(8, round(size * w / h))
        self.height = int(size) if h >= w else max(8, round(size * h / w))
        self.model = model
        self.diameter_mm = float(diameter_mm)
        self.supersample = int(supersample)
        params = SceneParams(threads=1) if fill is None else SceneParams(fill=fill, threads=1)
        self.scene = Scene(self.width, self.height, model.bands_nm, model.fwhm_nm, model.layout, params)
        # The lab's meshes the rig file names (``sim_config.mesh_mockups``): the twin must be
        # the mockup the simulated camera renders, or its labels are another object's.
        self.meshes: dict[tuple[str, str], Any] = dict(meshes or {})
        self.scene.meshes.update(self.meshes)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def mounted(self, satellite: str, build: str) -> MountedScene:
        b = load_catalog().build(satellite, build)
        return self.scene.mount(b.satellite, b.materials, b.key)

    def px_per_mm(self) -> float:
        """Frame pixels (at this camera's size) per millimetre at nominal scale."""
        return 2.0 * self.scene.params.fill * min(self.width, self.height) / self.diameter_mm

    def _offset(self, mounted: MountedScene, p: Placement) -> np.ndarray:
        # As simulators.world.Placement.offset_units: the offset in the object frame, yaw undone.
        k = 2.0 * mounted.radius / self.diameter_mm
        c, s = math.cos(math.radians(p.yaw_deg)), math.sin(math.radians(p.yaw_deg))
        x, y = p.dx_mm * k, p.dy_mm * k
        return np.array([c * x + s * y, -s * x + c * y, 0.0])

    def _screen(self, mounted: MountedScene, az: float, tilt: float, p: Placement, ss: int) -> np.ndarray:
        rot = Scene.rotation(az + p.yaw_deg, tilt + p.tilt_bias_deg)
        s = self.scene.scale(mounted) * p.scale * ss
        cam = (mounted.vertices + self._offset(mounted, p)) @ rot.T
        cx, cy = self.width * ss / 2.0, self.height * ss / 2.0
        return np.column_stack([cx + s * cam[:, 0], cy - s * cam[:, 1], cam[:, 2]])

    def coverage(self, mounted: MountedScene, az: float, tilt: float, p: Placement = NOMINAL) -> np.ndarray:
        """(H, W) float32 fractional silhouette of the mockup and its stand."""
        ss = self.supersample
        scr = self._screen(mounted, az, tilt, p, ss)
        depth, _, _ = rasterize(scr, None, mounted.triangles, mounted.tri_label, self.height * ss,
                                self.width * ss, 1)
        cov = np.isfinite(depth).astype(np.float32)
        if ss == 1:
            return cov
        return cov.reshape(self.height, ss, self.width, ss).mean(axis=(1, 3))

    def labels(self, mounted: MountedScene, az: float, tilt: float, p: Placement = NOMINAL,
               shape: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W) uint8 label map (index into ``mounted.class_names``), at ``shape`` if given."""
        h, w = shape or self.shape
        rot = Scene.rotation(az + p.yaw_deg, tilt + p.tilt_bias_deg)
        s = self.scene.params.fill * min(w, h) / mounted.radius * p.scale
        cam = (mounted.vertices + self._offset(mounted, p)) @ rot.T
        scr = np.column_stack([w / 2.0 + s * cam[:, 0], h / 2.0 - s * cam[:, 1], cam[:, 2]])
        _, _, label = rasterize(scr, mounted.normals @ rot.T, mounted.triangles, mounted.tri_label, h, w, 1)
        assert label is not None
        return label

    def shaded(self, mounted: MountedScene, az: float, tilt: float, p: Placement,
               lamp_output: Mapping[int, float], lamp_info: Mapping[int, Any], spot_angle_deg: float,
               band_gain: np.ndarray | None = None) -> Shaded:
        """The scene renderer's view (labels, shading) at this placement; scale is ignored
        (the photometric checks compare ratios inside the silhouette)."""
        off = [float(v) for v in self._offset(mounted, p)]
        return self.scene.render(mounted.satellite, mounted.materials, az + p.yaw_deg, tilt + p.tilt_bias_deg,
                                 lamp_output, lamp_info, spot_angle_deg, band_gain=band_gain, offset=off,
                                 build=mounted.build)

    @cached_property
    def sensor_band_gain(self) -> np.ndarray:
        """Electrons/s per unit radiance per band of the simulator's default sensor: the
        twin's photometric model of the camera (a real rig would calibrate it)."""
        from m2s2hil.simulators.sensor import Sensor

        m = self.model
        sensor = Sensor(8, 8, m.layout, m.bands_nm, m.fwhm_nm, int(m.full_scale))
        return np.asarray(sensor.band_gain, dtype=np.float64)


class MaskPredictor:
    """What :func:`observed_mask` would make of a frame of the twin: the mask's own bias.

    The mask rule keeps what stands out from the backdrop: it counts an edge pixel the mockup
    only partly covers when that part is bright enough, loses a shadowed or dark part, and,
    on a mosaic sensor's superpixel cube, sees each band a fraction of a pixel off. A fit of
    silhouettes to masks reads all of that as a placement (a larger scale, a yaw). The twin
    predicts it: its shaded frame under the frame's lamps and exposure, at the sensor's size
    through the mosaic and the superpixel cube (or, for a large sensor, every band at the
    cube's size), through the same rule with the frame's noise. Exact on the simulated rig,
    whose shading the twin shares; on a real rig as good as the twin's photometry.
    """

    def __init__(self, model: Any, lamp_info: Mapping[int, Any], *, spot_angle_deg: float = 45.0,
                 sensor_params: Any = None, diameter_mm: float = DIAMETER_MM,
                 meshes: Mapping[tuple[str, str], Any] | None = None, max_render: int = 1024) -> None:
        from m2s2hil.simulators.sensor import Sensor

        self.model = model
        self.lamp_info = dict(lamp_info)
        self.spot_angle_deg = float(spot_angle_deg)
        self.sensor = Sensor(8, 8, model.layout, model.bands_nm, model.fwhm_nm, int(model.full_scale),
                             sensor_params)
        self.layout = np.asarray(model.layout, dtype=np.int64)
        n = self.layout.shape[0]
        w, h = int(model.width), int(model.height)
        # A sensor up to ``max_render`` px is rendered whole, mosaic and superpixel emulated;
        # a larger one at its superpixel cube's size, every band at every pixel.
        self.mosaic = max(w, h) <= max_render
        side = max(w, h) if self.mosaic else max(w, h) // n
        self.twin = TwinCamera(model, side, diameter_mm=diameter_mm, supersample=1, meshes=meshes)
        self._cells = n
        self._side, self._diameter, self._meshes = side, diameter_mm, meshes
        self._scaled: dict[float, TwinCamera] = {}

    def _cube(self, sh: Shaded, dn_scale: float) -> np.ndarray:
        if not self.mosaic:
            return sh.cube(dn_scale)
        n = self._cells
        h, w = sh.rate.shape
        cells = (np.asarray(sh.rate, dtype=np.float32) * np.float32(dn_scale))[: h - h % n, : w - w % n]
        cells = cells.reshape(h // n, n, w // n, n)
        nb = int(self.layout.max()) + 1
        out = np.empty((nb, h // n, w // n), np.float32)
        for b in range(nb):
            pos = np.argwhere(self.layout == b)
            out[b] = np.mean([cells[:, r, :, c] for r, c in pos], axis=0)
        return out

    def _camera(self, scale: float) -> TwinCamera:
        """The twin's camera at ``scale`` (the renderer's scale is its fill: one camera a scale)."""
        key = round(float(scale), 5)
        if key == 1.0:
            return self.twin
        if key not in self._scaled:
            if len(self._scaled) > 64:
                self._scaled.clear()
            self._scaled[key] = TwinCamera(self.model, self._side, diameter_mm=self._diameter, supersample=1,
                                           fill=SceneParams().fill * key, meshes=self._meshes)
        return self._scaled[key]

    def coverage(self, mounted: MountedScene, az: float, tilt: float, p: Placement,
                 lamps_on: Sequence[int], exposure_s: float, gain: float, noise_norm: float,
                 backdrop_norm: float, shape: tuple[int, int]) -> np.ndarray:
        """The mask coverage (at ``shape``) a frame of this pose and light would give."""
        twin = self._camera(p.scale)
        m = twin.scene.mount(mounted.satellite, mounted.materials, mounted.build)
        lit = {ch: 1.0 for ch in lamps_on if ch in self.lamp_info}
        sh = twin.shaded(m, az, tilt, p, lit, self.lamp_info, self.spot_angle_deg,
                         band_gain=self.sensor.band_gain)
        pred = self._cube(sh, float(exposure_s) * self.sensor.dn_per_e(gain))
        bg_pred, _ = backdrop_noise(pred)
        # The frame's noise, scaled by the predicted backdrop to the observed one (a twin
        # whose photometry is a little off still gets the frame's signal-to-noise).
        noise = noise_norm * (bg_pred / backdrop_norm if backdrop_norm > 0 else 1.0)
        mask = observed_mask(pred, noise_norm=noise)
        if mask.shape == shape:
            return mask.astype(np.float32)
        return (coverage_of(mask, shape) >= 0.5).astype(np.float32)  # as Observation.from_cube keeps it
