"""Simulated frames with their ground truth, for model-selection studies and tests.

``simulated_frames`` renders scenes with the simulator's frame source (``simulators/frames.py``:
the same renderer and sensor model the simulated rig's camera uses) without the engine, which
makes a sweep over every satellite × build × lighting × tilt take seconds: per scene it exposes
so the object's brightest band peaks near ``PEAK_FRACTION`` of full scale (from the frame's own
noise-free signal, as an auto-exposure would), takes two lens-capped frames as the master dark
and extracts the super-pixel cube with ``processing.FrameProcessor`` — the engine's own path.
The label map is reduced to the cube grid by ``loading.labels_to_cube``.

Conditions for the robustness benchmark (``benchmarks/bench_robustness.py``): ``peak_fraction``
(0.02–2: above 1 the brightest band clips), ``spot_angle_deg`` (the spotlight's incidence),
``temperature_c`` (dark current), ``read_noise_e`` (sensor noise) and ``fill`` (the mockup's
bounding radius as a fraction of the frame side); None keeps the rig's value. ``bracket`` takes
each pose again at that many times the exposure (up to ``MAX_EXPOSURE_S``) and merges the two
(``processing.bracket``): the cube reads like the first frame with its shadows lifted out of
the noise (a factor above 1) or its clipped bands read from the shorter frame (below 1), and its
masks are where both clipped. Each frame also
carries the processor's ``saturated`` mask (True where a band clipped) and ``band_saturated``,
which bands.

``visible_materials(gt)``: materials covering at least ``VISIBLE_FRACTION`` of the object and
``VISIBLE_PIXELS`` pixels of the cube — a material hidden behind the body, or a few pixels at the
rim, cannot be found by anything looking at the image and is not counted.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.evaluation.loading import labels_to_cube
from m2s2hil.catalog import load_catalog
from m2s2hil.config import load_rig
from m2s2hil.processing.bracket import merge_bracket
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.processing.mosaic import MosaicLayout, cell_mean
from m2s2hil.processing.stability import band_saturation
from m2s2hil.sim_config import build_frame_source, build_world
from m2s2hil.simulators.clock import VirtualClock

MAX_EXPOSURE_S = 2.0  # the study's cap on a frame's exposure (the plan allows 5 s: plan.model)
VISIBLE_FRACTION = 0.005
VISIBLE_PIXELS = 20
PEAK_FRACTION = 0.6
LIGHTINGS = ("weak", "strong", "directional")
BUILDS = ("B1", "B2", "B3")
ELEVATIONS = ("E0", "E1", "E2")


@dataclass(frozen=True)
class SimFrame:
    satellite: str
    build: str
    lighting: str
    elevation: str
    azimuth_deg: float
    cube: np.ndarray  # float32 (bands, h, w), dark-subtracted super-pixel cube
    gt: np.ndarray  # int (h, w) class ids: 0 background, i = materials[i - 1]
    materials: tuple[str, ...]
    exposure_s: float
    saturated: np.ndarray | None = None  # bool (h, w): a band clipped (processing's saturated_mask)
    band_saturated: np.ndarray | None = None  # bool (bands, h, w): which bands (stability.band_saturation)
    # float32 (h, w): the light reaching each pixel's surface, the renderer's truth (FrameTruth.irradiance),
    # averaged over the cube's cells; a small part of the light on the object's well-lit faces is a shadow
    irradiance: np.ndarray | None = None

    @property
    def name(self) -> str:
        return f"{self.satellite}_{self.build}_{self.lighting}_{self.elevation}_{self.azimuth_deg:g}"


def visible_materials(gt: np.ndarray) -> int:
    """Materials (ids > 0) covering ≥ VISIBLE_FRACTION of the object and ≥ VISIBLE_PIXELS pixels."""
    counts = np.bincount(np.asarray(gt).ravel())[1:]
    total = counts.sum()
    if total == 0:
        return 0
    return int(np.count_nonzero((counts >= VISIBLE_PIXELS) & (counts >= VISIBLE_FRACTION * total)))


def simulated_frames(
    *,
    satellites: Sequence[str] | None = None,
    builds: Sequence[str] = BUILDS,
    lightings: Sequence[str] = LIGHTINGS,
    elevations: Sequence[str] = ELEVATIONS,
    azimuths: Sequence[float] = (30.0, 200.0),
    size: int = 512,
    seed: int = 0,
    skip: Sequence[str] = (),
    peak_fraction: float = PEAK_FRACTION,
    spot_angle_deg: float | None = None,
    temperature_c: float | None = None,
    read_noise_e: float | None = None,
    fill: float | None = None,
    bracket: float | None = None,
) -> Iterator[SimFrame]:
    """One frame per satellite × build × lighting × elevation × azimuth on a ``size``² sensor;
    frames whose ``name`` is in ``skip`` are not rendered (a cache has them). The condition
    keywords are described in the module docstring."""
    if not 0 < peak_fraction <= 10:
        raise AnalysisInputError("peak_fraction", f"must lie in (0, 10], got {peak_fraction}")
    if fill is not None and not 0 < fill < 1:
        raise AnalysisInputError("fill", f"must lie in (0, 1), got {fill}")
    if bracket is not None and not (0 < bracket <= 1000 and bracket != 1):
        problem = f"must lie in (0, 1000] and not be 1 (the second exposure over the first), got {bracket}"
        raise AnalysisInputError("bracket", problem)
    cfg = load_rig(None)
    if read_noise_e is not None:
        sensor = cfg.simulation.sensor.model_copy(update={"read_noise_e": float(read_noise_e)})
        cfg = cfg.model_copy(update={"simulation": cfg.simulation.model_copy(update={"sensor": sensor})})
    cat = load_catalog()
    model = cfg.camera.model.model_copy(update={"width": int(size), "height": int(size)})
    clock = VirtualClock()
    # the simulated rig's own world and frame source
    world = build_world(cfg, clock, spot_angle_deg=spot_angle_deg, sensor_temperature_c=temperature_c)
    pose = {"az": 0.0, "tilt": 0.0}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: pose["tilt"])
    src = build_frame_source(cfg, world, seed=seed, model=model)
    if fill is not None:
        src.scene.params = replace(src.scene.params, fill=float(fill))
    layout = MosaicLayout.from_camera(model)
    full = float(model.full_scale)

    def develop(raw: np.ndarray, exposure: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The super-pixel cube of ``raw`` less a master of two lens-capped frames at its exposure,
        the processor's clipping mask and which bands clipped (the engine's own path)."""
        world.set_lens_cap(True)
        darks = [src.capture(exposure) for _ in range(2)]
        world.set_lens_cap(False)
        dark = build_master_dark(darks, exposure_s=exposure, gain=1.0,
                                 temperature_c=world.sensor_temperature_c)
        done = FrameProcessor("superpixel", model, dark=dark).process(raw)
        return (np.array(done.cube, dtype=np.float32, copy=True),
                np.array(done.saturated_mask, dtype=bool, copy=True),
                band_saturation(raw >= model.full_scale, "superpixel", layout))

    skipped = set(skip)
    for light in lightings:
        for lamp in cfg.lamps.values():
            world.set_lamp(lamp.channel, False)
        for ch in cfg.lamp_channels(light):
            world.set_lamp(ch, True)
        clock.advance(cfg.warmup_s(light) + 5.0)  # lamps at full output
        for sat in satellites or list(cat.satellites):
            for build in builds:
                world.mount(sat, build)
                materials = tuple(cat.build(sat, build).materials)
                for elev in elevations:
                    pose["tilt"] = float(cfg.elevations[elev])
                    for az in azimuths:
                        name = f"{sat}_{build}_{light}_{elev}_{float(az):g}"
                        if name in skipped:
                            continue
                        pose["az"] = float(az)
                        world.set_lens_cap(False)
                        src.capture(0.005)
                        truth = src.truth()
                        peak = float(np.percentile(truth.signal()[truth.labels > 0], 99.5))
                        exposure = min(MAX_EXPOSURE_S, 0.005 * peak_fraction * full / max(peak, 1e-6))
                        raw = src.capture(exposure)
                        labels = np.array(src.truth().labels, copy=True)
                        irr = src.truth().irradiance()
                        cube, sat_mask, by_band = develop(raw, exposure)
                        if bracket is not None:  # the same pose again, longer or shorter, merged per band
                            other = min(MAX_EXPOSURE_S, exposure * bracket)
                            cube2, _, by_band2 = develop(src.capture(other), other)
                            merged = merge_bracket([cube, cube2], [exposure, other], [by_band, by_band2])
                            cube, by_band = merged.cube, merged.clipped
                            sat_mask = by_band.any(axis=0)
                        gt = labels_to_cube(labels, cube.shape[1:])
                        yield SimFrame(sat, build, light, elev, float(az), cube, gt, materials, exposure,
                                       sat_mask, by_band, cell_mean(irr[np.newaxis], layout.n)[0])
