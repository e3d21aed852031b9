"""Upper estimates of what a session will write, for the free-space checks made before a
run is admitted (the daemon) and started (the engine)."""

from __future__ import annotations

from m2s2hil.config import RigConfig
from m2s2hil.plan import Sweep


def _raw_bytes(rig: RigConfig) -> int:
    """Upper estimate of a stored raw mosaic (or uint16 dark): uncompressed in the legacy
    format; deflate never needs much more than the sensor's bits per pixel (plus 5 %)."""
    m = rig.camera.model
    if rig.storage.format == "legacy":
        return m.width * m.height * 2
    return int(m.width * m.height * m.bit_depth / 8 * 1.05)


def estimate_frame_bytes(rig: RigConfig, processing: str = "superpixel") -> int:
    """Upper estimate of one frame's files: raw + float32 cube when stored (super-pixel size,
    or full size for the full-resolution methods) + uncompressed RGB preview + headers."""
    m = rig.camera.model
    small = (m.width // m.period) * (m.height // m.period)
    cube_px = small if processing == "superpixel" else m.width * m.height
    stored_cube = (rig.storage.format == "legacy" or rig.storage.cubes
                   or rig.camera.calibration_file is not None)
    return _raw_bytes(rig) + (m.n_bands * cube_px * 4 if stored_cube else 0) + small * 3 + 64 * 1024


def estimate_session_bytes(sweep: Sweep, rig: RigConfig) -> int:
    """Upper estimate of a whole session's frames and darks (the plan expanded on ``rig``)."""
    events = sweep.expand(rig)
    m = rig.camera.model
    frames = sum(e.kind == "frame" for e in events)
    darks = sum(e.kind == "dark" for e in events)
    dark_bytes = m.width * m.height * 4 if rig.storage.format == "legacy" else _raw_bytes(rig)
    return frames * estimate_frame_bytes(rig, sweep.processing) + darks * (dark_bytes + 65536)
