"""Simulated frames with their ground truth, for model-selection studies and tests.

``simulated_frames`` renders scenes with the simulator's frame source (``simulators/frames.py``:
the same renderer and sensor model the simulated rig's camera uses) without the engine, which
makes a sweep over every satellite × build × lighting × tilt take seconds: per scene it exposes
so the object's brightest band peaks near ``PEAK_FRACTION`` of full scale (from the frame's own
noise-free signal, as an auto-exposure would), takes two lens-capped frames as the master dark
and extracts the super-pixel cube with ``processing.FrameProcessor`` — the engine's own path.
The label map is reduced to the cube grid by ``loading.labels_to_cube``.

``visible_materials(gt)``: materials covering at least ``VISIBLE_FRACTION`` of the object and
``VISIBLE_PIXELS`` pixels of the cube — a material hidden behind the body, or a few pixels at the
rim, cannot be found by anything looking at the image and is not counted.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from m2s2hil.analysis.evaluation.loading import labels_to_cube
from m2s2hil.catalog import load_catalog
from m2s2hil.config import load_rig
from m2s2hil.processing.chain import FrameProcessor
from m2s2hil.processing.dark import build_master_dark
from m2s2hil.sim_config import build_frame_source, build_world
from m2s2hil.simulators.clock import VirtualClock

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
) -> Iterator[SimFrame]:
    """One frame per satellite × build × lighting × elevation × azimuth on a ``size``² sensor;
    frames whose ``name`` is in ``skip`` are not rendered (a cache has them)."""
    cfg = load_rig(None)
    cat = load_catalog()
    model = cfg.camera.model.model_copy(update={"width": int(size), "height": int(size)})
    clock = VirtualClock()
    world = build_world(cfg, clock)  # the simulated rig's own world and frame source
    pose = {"az": 0.0, "tilt": 0.0}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: pose["tilt"])
    src = build_frame_source(cfg, world, seed=seed, model=model)
    full = float(model.full_scale)
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
                        exposure = min(2.0, 0.005 * PEAK_FRACTION * full / max(peak, 1e-6))
                        raw = src.capture(exposure)
                        labels = np.array(src.truth().labels, copy=True)
                        world.set_lens_cap(True)
                        darks = [src.capture(exposure) for _ in range(2)]
                        world.set_lens_cap(False)
                        dark = build_master_dark(darks, exposure_s=exposure, gain=1.0,
                                                 temperature_c=world.sensor_temperature_c)
                        cube = FrameProcessor("superpixel", model, dark=dark).process(raw).cube
                        cube = np.array(cube, dtype=np.float32, copy=True)
                        gt = labels_to_cube(labels, cube.shape[1:])
                        yield SimFrame(sat, build, light, elev, float(az), cube, gt, materials, exposure)
