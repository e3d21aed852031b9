"""A frame's cube when it is read: the stored one, or computed from raw + dark (+ calibration).

Sessions in the ``compressed`` format store no cube by default: the default super-pixel cube
is recomputed bit-identically from the raw mosaic and the master dark in a few ms (the
frame's ``meta["cube"]`` names the recipe and method, m2s2hil.store.frame_meta). A cube is
stored when the rig says ``[storage] cubes = true`` (slow methods), in the legacy format,
and when the frame was calibrated (the calibration file lives outside the session, so the
cube could not be recomputed from the session alone).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from m2s2hil.errors import M2S2Error
from m2s2hil.store.frame_files import decode_tiff


class CubeUnavailable(M2S2Error):
    """A cube that is neither stored nor computable from what the session holds."""


def cube_is_stored(storage: Any, meta: dict) -> bool:
    """Whether ``write_frame`` stores the cube it is given (see the module docstring)."""
    return storage.format == "legacy" or bool(storage.cubes) or meta.get("calibration") is not None


def master_dark(store: Any, dark_id: str) -> Any:
    """The session's master dark ``dark_id`` as processing uses it (uint16 whole DN)."""
    rec = next((d for d in store.darks() if d.dark_id == dark_id), None)
    if rec is None:
        raise CubeUnavailable(f"session {store.session_id} has no dark {dark_id!r}")
    return master_dark_of(store, rec)


def master_dark_of(store: Any, rec: Any) -> Any:
    """The master dark of the journal's dark record ``rec``, with the provenance it was stored with."""
    from m2s2hil.processing.dark import MasterDark

    data = np.clip(np.rint(store.load_dark(rec.dark_id)), 0, 65535).astype(np.uint16)
    m = rec.meta
    temperature = m.get("temperature_c")
    return MasterDark(data=data, created=str(m.get("created", "")),
                      camera_serial=str(m.get("camera_serial", "unknown")), n_frames=rec.n_frames,
                      exposure_s=rec.exposure_s, gain=rec.gain,
                      temperature_c=float("nan") if temperature is None else float(temperature),
                      reduce=rec.reduce,
                      read_noise_dn=m.get("read_noise_dn"))


class CubeComputer:
    """Frame processors per (method, dark), kept for the store's lifetime (their buffers are
    reused; a lock serialises them, as FrameProcessor is not thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._procs: dict[tuple[str, str | None], Any] = {}

    def _processor(self, store: Any, method: str, dark_id: str | None) -> Any:
        from m2s2hil.processing.chain import FrameProcessor

        key = (method, dark_id)
        proc = self._procs.get(key)
        if proc is None:
            dark = master_dark(store, dark_id) if dark_id else None
            if len(self._procs) >= 4:
                self._procs.clear()
            proc = self._procs[key] = FrameProcessor(method, store.rig.camera.model, dark=dark)
        return proc

    def read(self, store: Any, event_id: str) -> np.ndarray:
        fr = store.frame(event_id)
        if "cube" in fr.files:
            cube, _ = decode_tiff(store.read_file(fr.files["cube"]))
            return cube
        recipe = fr.meta.get("cube") or {}
        if recipe.get("calibrated") or fr.meta.get("calibration") is not None:
            raise CubeUnavailable(f"{store.session_id}/{event_id}: calibrated frame without its stored cube")
        method = str(recipe.get("method") or fr.meta.get("processing_method") or store.sweep.processing)
        raw, _ = decode_tiff(store.read_file(fr.files["raw"]))  # read_raw would look the frame up again
        with self._lock:
            proc = self._processor(store, method, fr.dark_id)
            return np.array(proc.process(raw).cube, dtype=np.float32, copy=True)
