"""The satellite scene seen by the simulated camera.

A mounted mockup (satellite + the build's materials) is a triangle mesh with a label
per triangle. For a pose, the mesh is rotated by the turntable azimuth about the
vertical axis and by the tilt stage about the camera's horizontal axis, projected
orthographically and rasterised (depth, normal, label); the lamps then shade it.

Both steps are cached: the rasterised geometry per (mount, pose) and the shading per
(geometry, lamp state), so frames at an unchanged pose cost nothing here.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from m2s2hil.simulators.geometry import concat, rot_x, rot_z
from m2s2hil.simulators.materials import GRID_NM, MaterialTable, band_average, material_table
from m2s2hil.simulators.mockups import MOCKUPS, Mockup, mockup, part_materials, stand
from m2s2hil.simulators.raster import rasterize
from m2s2hil.simulators.shading import LightingParams, light_frame, lights_from_lamps, radiance_cube, shade

# Object frame (z up, camera along +y) to camera frame (x right, y up, z towards the camera).
OBJECT_TO_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class SceneError(ValueError):
    """A scene that cannot be built (unknown satellite, empty build, bad camera model)."""


@dataclass(frozen=True)
class SceneParams:
    """Scene parameters (all assumptions about the bench; configurable)."""

    fill: float = 0.45  # the mockup's bounding sphere radius, as a fraction of the smaller frame side
    lamp_cct_k: float = 5000.0  # LED bars and spotlight: 5000 K (paper); spectrum ~ a blackbody at this CCT
    lighting: LightingParams = field(default_factory=LightingParams)
    threads: int | None = None  # render threads (default: up to 2)


@dataclass(frozen=True)
class MountedScene:
    satellite: str
    materials: tuple[str, ...]
    class_names: tuple[str, ...]  # ("background", *materials): label i ↔ class_names[i]
    part_materials: dict[str, str]  # part name → material key
    vertices: np.ndarray  # (N, 3) object frame, centred on the mockup
    normals: np.ndarray
    triangles: np.ndarray
    tri_label: np.ndarray  # (M,) uint8
    radius: float  # bounding-sphere radius of the mockup (stand excluded)
    table: MaterialTable
    build: str | None = None  # picks the mockup's part map for this build (Hubble B2 ≠ B3)
    source: str = ""  # the lab's mesh it was loaded from (Scene.meshes); "": the built-in mockup


@dataclass(frozen=True)
class Shaded:
    """One rendered view: labels and the shading factors that make up its radiance."""

    label: np.ndarray  # (H, W) uint8 index into class_names
    diffuse: np.ndarray  # (H, W) float32 irradiance factor D
    specular: np.ndarray  # (H, W) float32 specular factor S
    rate: np.ndarray  # (H, W) float32 band_gain[b]·(rho·D + spec·S) for each pixel's mosaic band b
    band_gain: np.ndarray  # (n_bands,) the per-band factor used for ``rate``
    mount: MountedScene

    def cube(self, scale: float = 1.0) -> np.ndarray:
        """(n_bands, H, W) float32: every band at every pixel, ``scale`` × the units of ``rate``."""
        t = self.mount.table
        return radiance_cube(self.label, self.diffuse, self.specular, t.rho, t.spec, self.band_gain, scale)


def planck(nm: np.ndarray, cct_k: float) -> np.ndarray:
    lam = np.asarray(nm, dtype=np.float64) * 1e-9
    c2 = 1.438776877e-2
    return lam**-5 / np.expm1(c2 / (lam * cct_k))


class Scene:
    """Renders mounted mockups for a camera of ``width`` × ``height`` with an n × n MSFA ``layout``."""

    def __init__(
        self, width: int, height: int, bands_nm: Sequence[float], fwhm_nm: Sequence[float],
        layout: Sequence[Sequence[int]], params: SceneParams | None = None,
    ) -> None:
        self.width, self.height = int(width), int(height)
        self.bands_nm = tuple(float(b) for b in bands_nm)
        self.fwhm_nm = tuple(float(f) for f in fwhm_nm)
        self.layout = np.asarray(layout, dtype=np.int64)
        self.params = params or SceneParams()
        nb = len(self.bands_nm)
        n = self.layout.shape[0] if self.layout.ndim == 2 else 0
        if self.width <= 0 or self.height <= 0:
            raise SceneError(f"sensor size {self.width}x{self.height} must be positive")
        if len(self.fwhm_nm) != nb:
            raise SceneError(f"{len(self.fwhm_nm)} FWHM values for {nb} bands")
        if n == 0 or self.layout.shape != (n, n):
            raise SceneError(f"MSFA layout must be a square n x n array, got shape {self.layout.shape}")
        if self.layout.min() < 0 or self.layout.max() >= nb:
            raise SceneError(f"MSFA layout names bands outside 0..{nb - 1}")
        # Relative spectral irradiance of the lamps per band, 1.0 at 560 nm.
        spd = planck(GRID_NM, self.params.lamp_cct_k)
        self.lamp_spectrum = band_average(spd, self.bands_nm, self.fwhm_nm) / planck(np.array([560.0]),
                                                                                    self.params.lamp_cct_k)[0]
        self._lock = threading.Lock()
        self._mounts: dict[tuple[str, tuple[str, ...], str | None], MountedScene] = {}
        # (satellite, build) → the lab's mesh mockup (simulators.meshes), used instead of the
        # built-in one when a render names that build; set before the first render.
        self.meshes: dict[tuple[str, str], Mockup] = {}
        self._geom_key: tuple | None = None
        self._geom: tuple | None = None
        self._shade_key: tuple | None = None
        self._shaded: Shaded | None = None

    # -- mounting --------------------------------------------------------------------
    def mount(self, satellite: str, materials: Sequence[str], build: str | None = None) -> MountedScene:
        sat = satellite.strip().lower()
        lab_mesh = self.meshes.get((sat, build.strip().upper())) if build else None
        if lab_mesh is None and sat not in MOCKUPS:
            raise SceneError(f"no mockup model for satellite {satellite!r}; known: {', '.join(MOCKUPS)}")
        mats = tuple(materials)
        if not mats:
            raise SceneError(f"build of {satellite!r} has no materials")
        if len(set(mats)) != len(mats):
            raise SceneError(f"build of {satellite!r} lists a material twice: {list(mats)}")
        if len(mats) > 254:
            raise SceneError("too many materials for a uint8 label map")
        key = (sat, mats, build)
        with self._lock:
            if key in self._mounts:
                return self._mounts[key]
        try:
            table = material_table(mats, self.bands_nm, self.fwhm_nm)
        except KeyError as exc:
            raise SceneError(str(exc)) from None
        m = lab_mesh or mockup(sat)
        chosen = part_materials(m, mats, build)
        primary = "pro_silver" if "pro_silver" in mats else mats[0]
        sat_mesh = concat(p.mesh for p in m.parts)
        lo, hi = sat_mesh.vertices.min(axis=0), sat_mesh.vertices.max(axis=0)
        centre = (lo + hi) / 2.0
        radius = float(np.linalg.norm(sat_mesh.vertices - centre, axis=1).max())
        top = np.asarray(m.stand_top, dtype=np.float64)
        stand_mesh = stand(top, top[2] - 4.0 * radius, radius / 1.3)
        meshes = [p.mesh for p in m.parts] + [stand_mesh]
        labels = [*(1 + mats.index(c) for c in chosen), 1 + mats.index(primary)]
        mesh = concat(meshes)
        tri_label = np.concatenate([np.full(me.n_triangles, lab, dtype=np.uint8)
                                    for me, lab in zip(meshes, labels, strict=True)])
        mounted = MountedScene(
            satellite=sat, materials=mats, class_names=("background", *mats),
            part_materials={p.name: c for p, c in zip(m.parts, chosen, strict=True)} | {"stand": primary},
            vertices=mesh.vertices - centre, normals=mesh.normals, triangles=mesh.triangles,
            tri_label=tri_label, radius=radius, table=table, build=build,
            source=lab_mesh.name if lab_mesh else "",
        )
        with self._lock:
            self._mounts[key] = mounted
        return mounted

    # -- projection ------------------------------------------------------------------
    def scale(self, mounted: MountedScene) -> float:
        """Pixels per object unit: the bounding sphere spans ``2·fill`` of the smaller side."""
        return self.params.fill * min(self.width, self.height) / mounted.radius

    @staticmethod
    def rotation(azimuth_deg: float, tilt_deg: float) -> np.ndarray:
        """Object → camera rotation: turntable about the vertical, then the tilt stage."""
        return rot_x(tilt_deg) @ OBJECT_TO_CAMERA @ rot_z(azimuth_deg)

    def _geometry(self, mounted: MountedScene, az: float, tilt: float,
                  offset: tuple[float, ...] = (0.0, 0.0, 0.0)) -> tuple:
        key = (mounted.satellite, mounted.materials, mounted.build, round(az, 4), round(tilt, 4), offset)
        if key == self._geom_key and self._geom is not None:
            return self._geom
        rot = self.rotation(az, tilt)
        s = self.scale(mounted)
        cx, cy = self.width / 2.0, self.height / 2.0
        cam = (mounted.vertices + np.asarray(offset)) @ rot.T
        scr = np.column_stack([cx + s * cam[:, 0], cy - s * cam[:, 1], cam[:, 2]])
        nrm = mounted.normals @ rot.T
        depth, normals, label = rasterize(scr, nrm, mounted.triangles, mounted.tri_label, self.height,
                                          self.width, self.params.threads)
        geom = (depth, normals, label, (cx, cy), s, rot)
        self._geom_key, self._geom = key, geom
        return geom

    def _shadow_map(self, mounted: MountedScene, rot: np.ndarray, spot_dir: np.ndarray, s: float,
                    offset: tuple[float, ...] = (0.0, 0.0, 0.0)) -> tuple:
        lmat = light_frame(spot_dir)
        ss = s * self.params.lighting.shadow_scale
        hs = max(8, round(self.height * self.params.lighting.shadow_scale))
        ws = max(8, round(self.width * self.params.lighting.shadow_scale))
        lv = (mounted.vertices + np.asarray(offset)) @ (lmat @ rot).T
        scr = np.column_stack([ws / 2.0 + ss * lv[:, 0], hs / 2.0 - ss * lv[:, 1], lv[:, 2]])
        smap, _, _ = rasterize(scr, None, mounted.triangles, mounted.tri_label, hs, ws, self.params.threads)
        return smap, lmat, ws / 2.0, hs / 2.0, ss

    # -- rendering -------------------------------------------------------------------
    def render(
        self, satellite: str, materials: Sequence[str], azimuth_deg: float, tilt_deg: float,
        lamp_output: Mapping[int, float], lamp_info: Mapping[int, Any], spot_angle_deg: float = 45.0,
        band_gain: Sequence[float] | np.ndarray | None = None, offset: Sequence[float] | None = None,
        build: str | None = None,
    ) -> Shaded:
        """Render one view. ``rate`` is in units of ``band_gain`` × relative radiance
        (``lamp_spectrum[b]`` × reflectance × irradiance factor); without ``band_gain`` it is
        the relative radiance itself. ``offset``: the mockup moved by this (object frame,
        scene units) off the rotation axes (a mockup mounted off the turntable axis).
        ``build``: the build's key, for mockups with a part map per build (``Mockup.builds``).
        """
        off = (0.0, 0.0, 0.0) if offset is None else tuple(round(float(v), 6) for v in offset)
        if not (math.isfinite(azimuth_deg) and math.isfinite(tilt_deg)):
            raise SceneError(f"pose must be finite, got azimuth {azimuth_deg}, tilt {tilt_deg}")
        mounted = self.mount(satellite, materials, build)
        gain = self.lamp_spectrum.copy()
        if band_gain is not None:
            bg = np.asarray(band_gain, dtype=np.float64)
            if bg.shape != gain.shape:
                raise SceneError(f"band_gain has {bg.size} values for {gain.size} bands")
            gain = gain * bg
        lights = lights_from_lamps(lamp_output, lamp_info, spot_angle_deg, self.params.lighting)
        with self._lock:
            geom_key = (mounted.satellite, mounted.materials, mounted.build, round(azimuth_deg, 4),
                        round(tilt_deg, 4), off)
            key = (geom_key, lights.key, gain.tobytes())
            if key == self._shade_key and self._shaded is not None:
                return self._shaded
            depth, nrm, label, centre, s, rot = self._geometry(mounted, azimuth_deg, tilt_deg, off)
            shadow = None
            if lights.spot_dir is not None:
                shadow = self._shadow_map(mounted, rot, lights.spot_dir, s, off)
            t = mounted.table
            d, sp, rate = shade(
                label, depth, nrm, centre, s, lights, shadow, t.rho, t.spec, t.shininess,
                gain.astype(np.float32), self.layout, self.params.lighting.backdrop_factor,
                self.params.threads,
            )
            for a in (label, d, sp, rate):
                a.flags.writeable = False  # shared by the cache and every truth handed out
            shaded = Shaded(label=label, diffuse=d, specular=sp, rate=rate, band_gain=gain, mount=mounted)
            self._shade_key, self._shaded = key, shaded
            return shaded
