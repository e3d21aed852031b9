"""Compile every numba kernel once, ahead of the first frame (``m2s2hil compile-kernels``).

numba compiles a kernel for each argument type on its first call and keeps the machine code in
its cache (``cache=True``; ``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``). On a new
install that first call is the first frame of the first session: 1–2 minutes of CPU on a
2-core machine for every demosaicing method at both input types (uint16 frames, float32 white
references) and the simulated camera. Running the real code paths once on a tiny frame here
fills the cache with the same signatures, so capture and the tests start warm; tests/numba_cache.py
seeds each test process's private cache from it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

WARM_SIZE = 64  # a multiple of every layout's period; the kernels' types do not depend on it


def _steps(size: int) -> list[tuple[str, Callable[[], object]]]:
    from m2s2hil.config import default_rig
    from m2s2hil.processing.calibration import CameraCalibration
    from m2s2hil.processing.chain import FrameProcessor
    from m2s2hil.processing.dark import MasterDark
    from m2s2hil.processing.demosaic import _registry, get_demosaicer

    rig = default_rig()
    model = rig.camera.model.model_copy(update={"width": size, "height": size})
    rng = np.random.default_rng(0)
    raw = rng.integers(0, model.full_scale + 1, (size, size), dtype=np.uint16)
    raw[0, 0] = model.full_scale  # a clipped pixel: the saturation branches are typed too
    dark = MasterDark(data=np.full((size, size), 8, np.uint16), created="1970-01-01T00:00:00Z",
                      camera_serial="warm-up", n_frames=2, exposure_s=0.01, gain=1.0, temperature_c=25.0,
                      read_noise_dn=2.0)  # a read noise turns the low-light check on
    dim = np.full((size, size), 9, np.uint16)  # below 5x the read noise: the check's slow path
    nb = model.n_bands
    calibration = CameraCalibration(crosstalk=np.eye(nb), white_mosaic=raw.astype(np.float32) + 100.0,
                                     white_reflectance=np.full(nb, 0.98))

    def method(name: str) -> None:
        processor = FrameProcessor(name, model, dark=dark)
        processor.process(raw)
        processor.process(dim)
        FrameProcessor(name, model).process(raw)  # no dark: the raw frame straight in
        FrameProcessor(name, model, dark=dark, calibration=calibration).process(raw)  # float32 white
        demosaicer = get_demosaicer(name, model.layout, (size, size))  # as analysis and references call it
        demosaicer.process(raw)
        demosaicer.process(raw.astype(np.float32))

    def simulator() -> None:
        from m2s2hil.sim_config import build_frame_source, build_world
        from m2s2hil.simulators.clock import VirtualClock

        world = build_world(rig, VirtualClock())
        world.attach_axis("turntable", lambda: 30.0)
        world.attach_axis("tilt", lambda: 15.0)
        for ch in rig.lamp_channels("weak"):
            world.set_lamp(ch, True)
        build_frame_source(rig, world, model=model).capture(0.005)

    return [*((f"demosaic {m}", lambda m=m: method(m)) for m in _registry()), ("simulated camera", simulator)]


def compile_kernels(size: int = WARM_SIZE, progress: Callable[[str, float], None] | None = None) -> float:
    """Run each kernel's real call path once; returns the seconds it took (≈ 0 when the cache is warm)."""
    t0 = time.perf_counter()
    for name, step in _steps(size):
        t = time.perf_counter()
        step()
        if progress is not None:
            progress(name, time.perf_counter() - t)
    return time.perf_counter() - t0
