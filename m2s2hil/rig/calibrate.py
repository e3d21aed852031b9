"""Calibration captures an operator makes before a sweep: darks, the white reference, the mosaic phase.

- :func:`capture_dark_library`: lens capped, N frames at every (exposure, gain) a sweep uses,
  reduced to master darks and put in a :class:`~m2s2hil.processing.dark.DarkLibrary`.
- :func:`capture_white_reference`: N frames of a white panel filling the view under the capture
  lighting, averaged and dark-subtracted, checked (no saturated pixel, enough signal, a field
  even enough to correct) and written to the camera's calibration file with its provenance.
  A failed check writes nothing.
- :func:`check_mosaic_phase`: one frame, the duplicated mosaic positions compared
  (:func:`~m2s2hil.processing.stability.check_phase`): a readout offset or a wrong layout shows.

The lens cap and the white panel are the operator's to put on; ``rig.cap_lens`` does it on a
simulated rig (and calls the rig's hook on a real one). All functions expect an idle rig: the
caller holds it (the daemon refuses them while a session runs).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.errors import UsageError
from m2s2hil.plan import Sweep
from m2s2hil.processing.calibration import CameraCalibration, load_calibration, save_calibration
from m2s2hil.processing.dark import DarkLibrary, MasterDark, build_master_dark
from m2s2hil.processing.demosaic import get_demosaicer
from m2s2hil.processing.mosaic import MosaicLayout
from m2s2hil.processing.stability import check_phase, phase_warning
from m2s2hil.rig.opened import Rig

#: White reference acceptance: no more than this fraction of saturated raw pixels …
MAX_SATURATED_FRACTION = 0.0
#: … a median level of at least this fraction of full scale (below, shot noise dominates the gain) …
MIN_LEVEL_FRACTION = 0.2
#: … and, per band, the dimmest 8×8 block of the field at least this fraction of the brightest
#: (a panel that does not fill the view, or a shadow across it, fails here).
MIN_UNIFORMITY = 0.5


class CalibrationCaptureError(UsageError):
    """A calibration capture that cannot be made or failed its checks (nothing was written)."""


@dataclass(frozen=True)
class WhiteCheck:
    saturated_fraction: float
    level_fraction: float
    uniformity: list[float]  # per band: dimmest / brightest block mean
    problems: list[str]

    @property
    def ok(self) -> bool:
        return not self.problems


def sweep_exposures(sweep: Sweep, rig: Rig) -> list[tuple[float, float]]:
    """The (exposure, gain) pairs whose darks a sweep takes, in plan order."""
    seen: dict[tuple[float, float], None] = {}
    for ev in sweep.expand(rig.config):
        if ev.kind == "dark":
            seen[(float(ev.exposure_s), float(ev.gain))] = None
    return list(seen)


def _snaps(rig: Rig, n: int, exposure_s: float, gain: float) -> tuple[np.ndarray, list[float]]:
    rig.camera.configure(exposure_s=exposure_s, gain=gain)
    timeout = exposure_s + rig.config.camera.timeout_s
    frames, temps = [], []
    for _ in range(n):
        f = rig.camera.snap(timeout=timeout)
        frames.append(f.data)
        temps.append(float(f.temperature_c))
    return np.stack(frames), temps


def _master_dark(rig: Rig, n: int, exposure_s: float, gain: float) -> MasterDark:
    """``n`` frames (the lens capped by the caller) reduced as the rig file's processing says."""
    proc = rig.config.processing
    stack, temps = _snaps(rig, n, exposure_s, gain)
    return build_master_dark(stack, reduce=proc.dark_reduce, exposure_s=exposure_s, gain=gain,
                             temperature_c=temps, camera=rig.config.camera.model.name,
                             tolerance_c=proc.dark_temperature_tolerance_c)


def capture_dark_library(rig: Rig, library: DarkLibrary, exposures: list[tuple[float, float]], *,
                         n_frames: int | None = None) -> list[dict[str, Any]]:
    """Master darks for every (exposure, gain); returns their provenance (one entry each)."""
    if not exposures:
        raise CalibrationCaptureError("no exposure to take darks at")
    proc = rig.config.processing
    n = n_frames or proc.dark_frames
    out: list[dict[str, Any]] = []
    rig.cap_lens(True)
    try:
        for exposure_s, gain in exposures:
            master = _master_dark(rig, n, exposure_s, gain)
            path = library.put(master)
            entry = master.provenance()
            entry["file"] = path.name
            out.append(entry)
    finally:
        rig.cap_lens(False)
    return out


def check_white(mean_raw: np.ndarray, white: np.ndarray, rig: Rig) -> WhiteCheck:
    """The checks of the module docstring on the averaged raw frames and the dark-subtracted mean."""
    model = rig.config.camera.model
    full = model.full_scale
    sat = float(np.count_nonzero(mean_raw >= full) / mean_raw.size)
    level = float(np.median(mean_raw) / full)
    cube = get_demosaicer("superpixel", model, white.shape).process(white.astype(np.float32))
    _, h, w = cube.shape
    bh, bw = max(1, h // 8), max(1, w // 8)
    blocks = cube[:, : bh * 8, : bw * 8].reshape(cube.shape[0], 8, bh, 8, bw).mean(axis=(2, 4))
    hi = blocks.max(axis=(1, 2))
    uni = [float(b.min() / m) if m > 0 else 0.0 for b, m in zip(blocks, hi, strict=True)]
    problems: list[str] = []
    if sat > MAX_SATURATED_FRACTION:
        problems.append(f"{100 * sat:.3f} % of the pixels are saturated: shorten the exposure or lower "
                        "the gain")
    if level < MIN_LEVEL_FRACTION:
        problems.append(f"median level {100 * level:.0f} % of full scale is below "
                        f"{100 * MIN_LEVEL_FRACTION:.0f} %: lengthen the exposure or light the panel")
    worst = int(np.argmin(uni))
    if uni[worst] < MIN_UNIFORMITY:
        problems.append(
            f"the field is uneven: in band {model.bands_nm[worst]:g} nm the dimmest part is "
            f"{100 * uni[worst]:.0f} % of the brightest (needs ≥ {100 * MIN_UNIFORMITY:.0f} %): "
            "make the panel fill the view and light it evenly")
    return WhiteCheck(sat, level, uni, problems)


def capture_white_reference(
    rig: Rig, calibration_path: Path, *, exposure_s: float, gain: float = 1.0, n_frames: int = 16,
    reflectance: float | list[float] = 0.99, lighting: str | None = None, library: DarkLibrary | None = None,
) -> tuple[WhiteCheck, dict[str, Any]]:
    """Average ``n_frames`` of the white panel, subtract a dark at the same setting (from
    ``library`` when it has one within tolerance, else taken now with the lens capped), check,
    and write the calibration file (keeping its layout and crosstalk). Returns the check and the
    provenance written; raises :class:`CalibrationCaptureError` when a check fails. The panel is
    in view and the preset's lamps on only during the capture."""
    rig.show_white_panel(True)
    try:
        return _capture_white(rig, calibration_path, exposure_s=exposure_s, gain=gain, n_frames=n_frames,
                              reflectance=reflectance, lighting=lighting, library=library)
    finally:
        rig.show_white_panel(False)
        if lighting is not None:
            rig.lights.set(())


def _capture_white(
    rig: Rig, calibration_path: Path, *, exposure_s: float, gain: float, n_frames: int,
    reflectance: float | list[float], lighting: str | None, library: DarkLibrary | None,
) -> tuple[WhiteCheck, dict[str, Any]]:
    model = rig.config.camera.model
    if lighting is not None:
        if lighting not in rig.config.lighting:
            raise CalibrationCaptureError(f"no lighting preset {lighting!r}")
        rig.lights.set(rig.config.lamp_channels(lighting))
        warm = rig.config.warmup_s(lighting)
        if warm > 0:
            rig.clock.sleep(warm)
    stack, temps = _snaps(rig, n_frames, exposure_s, gain)
    mean_raw = stack.mean(axis=0, dtype=np.float64)
    temp = float(np.mean(temps))
    proc = rig.config.processing
    dark = None
    dark_source = "taken now"
    if library is not None:
        try:
            dark = library.get(exposure_s, gain, temp, proc.dark_temperature_tolerance_c,
                               shape=tuple(mean_raw.shape))  # type: ignore[arg-type]
            dark_source = f"library: {dark.created}"
        except Exception:
            dark = None
    if dark is None:
        rig.cap_lens(True)
        try:
            dark = _master_dark(rig, proc.dark_frames, exposure_s, gain)
        finally:
            rig.cap_lens(False)
    white = np.clip(mean_raw - dark.data.astype(np.float64), 0.0, None).astype(np.float32)
    check = check_white(mean_raw, white, rig)
    if not check.ok:
        raise CalibrationCaptureError("white reference refused: " + "; ".join(check.problems))
    existing = rig.calibration
    if existing is None and calibration_path.exists():
        existing = load_calibration(calibration_path, model)
    base = existing or CameraCalibration(source=str(calibration_path))
    refl = np.atleast_1d(np.asarray(reflectance, dtype=np.float64))
    calib = dataclasses.replace(base, source=str(calibration_path), white_mosaic=white,
                                white_reflectance=refl)
    provenance = {
        "captured_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "exposure_s": exposure_s, "gain": gain, "n_frames": n_frames, "temperature_c": temp,
        "lighting": lighting, "lamps_on": sorted(rig.lights.state()),
        "dark": {"source": dark_source, "sha256": dark.sha256(), "n_frames": dark.n_frames},
        "camera": model.name, "rig_digest": rig.config.digest,
        "checks": dataclasses.asdict(check),
    }
    save_calibration(calibration_path, calib, bands_nm=list(model.bands_nm), provenance=provenance)
    return check, provenance


def check_mosaic_phase(rig: Rig, *, exposure_s: float, gain: float = 1.0) -> dict[str, Any]:
    """One frame; which mosaic origin makes the duplicated band positions agree best."""
    t0 = time.perf_counter()
    stack, _ = _snaps(rig, 1, exposure_s, gain)
    layout = (MosaicLayout.from_pattern(rig.calibration.layout)
              if rig.calibration is not None and rig.calibration.layout is not None
              else MosaicLayout.from_camera(rig.config.camera.model))
    res = check_phase(stack[0], layout)
    return {
        "offset": list(res.offset), "cost_nominal": res.cost_nominal, "cost_best": res.cost_best,
        "conclusive": res.conclusive, "suspect": res.suspect,
        "message": phase_warning(res) or ("the mosaic phase matches the layout" if res.conclusive else
                                          "inconclusive: the scene is too uniform across bands; "
                                          "use a coloured target"),
        "layout": layout.describe(), "elapsed_ms": round(1e3 * (time.perf_counter() - t0), 1),
        "cost_map": [list(row) for row in res.cost],  # cost of every origin shift (the phase cost map)
    }
