"""A frame's cube when it is read: the stored one, or computed from raw + dark (+ calibration).

Sessions in the ``compressed`` format store no cube by default: the default super-pixel cube
is recomputed bit-identically from the raw mosaic and the master dark in a few ms (the
frame's ``meta["cube"]`` names the recipe and method, m2s2hil.store.frame_meta). A cube is
stored when the rig says ``[storage] cubes = true`` (slow methods), in the legacy format,
and when the frame was calibrated (the calibration file lives outside the session, so the
cube could not be recomputed from the session alone).

A stored master dark is rebuilt as processing uses it in one place, :func:`master_dark_from`:
for computed cubes, for a resumed run's darks (m2s2hil.engine.darks) and for the analysis
loader, which reads the dark's file without the journal.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from m2s2hil.errors import M2S2Error
from m2s2hil.store.frame_files import decode_tiff

if TYPE_CHECKING:
    from m2s2hil.config import StorageConfig
    from m2s2hil.processing.chain import FrameProcessor
    from m2s2hil.processing.dark import MasterDark
    from m2s2hil.store.records import DarkRecord, FrameRecord
    from m2s2hil.store.session import SessionStore


class CubeUnavailable(M2S2Error):
    """A cube that is neither stored nor computable from what the session holds."""


def cube_is_stored(storage: StorageConfig, meta: Mapping[str, Any]) -> bool:
    """Whether ``write_frame`` stores the cube it is given (see the module docstring)."""
    return storage.format == "legacy" or bool(storage.cubes) or meta.get("calibration") is not None


def master_dark_from(pixels: np.ndarray, meta: Mapping[str, Any]) -> MasterDark:
    """A stored master dark as processing uses it (uint16 whole DN), with the provenance it
    was stored with: ``meta`` is its metadata (the journal's, or its TIFF's description, which
    hold the same); what an older or exported dark lacks takes the neutral default."""
    from m2s2hil.processing.dark import MasterDark

    def given(key: str, default: Any) -> Any:
        value = meta.get(key)
        return default if value is None else value

    data = np.clip(np.rint(pixels), 0, 65535).astype(np.uint16)
    return MasterDark(data=data, created=str(given("created", "")),
                      camera_serial=str(given("camera_serial", "unknown")),
                      n_frames=int(given("n_frames", 1)), exposure_s=float(given("exposure_s", 0.0)),
                      gain=float(given("gain", 1.0)), temperature_c=float(given("temperature_c", math.nan)),
                      reduce=given("reduce", "mean"),
                      temperature_spread_c=float(given("temperature_spread_c", 0.0)),
                      read_noise_dn=meta.get("read_noise_dn"))


def master_dark_of(store: SessionStore, rec: DarkRecord) -> MasterDark:
    """The master dark of the journal's dark record ``rec`` (:func:`master_dark_from`; the
    journal's columns for the setting it was taken at)."""
    return master_dark_from(store.load_dark(rec.dark_id),
                            {**rec.meta, "n_frames": rec.n_frames, "exposure_s": rec.exposure_s,
                             "gain": rec.gain, "reduce": rec.reduce})


def master_dark(store: SessionStore, dark_id: str) -> MasterDark:
    """The session's master dark ``dark_id`` as processing uses it (uint16 whole DN)."""
    rec = next((d for d in store.darks() if d.dark_id == dark_id), None)
    if rec is None:
        raise CubeUnavailable(f"session {store.session_id} has no dark {dark_id!r}")
    return master_dark_of(store, rec)


class CubeComputer:
    """Frame processors per (method, dark), kept for the store's lifetime (their buffers are
    reused; a lock serialises them, as FrameProcessor is not thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._procs: dict[tuple[str, str | None], FrameProcessor] = {}

    def _processor(self, store: SessionStore, method: str, dark_id: str | None) -> FrameProcessor:
        from m2s2hil.processing.chain import FrameProcessor

        key = (method, dark_id)
        proc = self._procs.get(key)
        if proc is None:
            dark = master_dark(store, dark_id) if dark_id else None
            if len(self._procs) >= 4:
                self._procs.clear()
            proc = self._procs[key] = FrameProcessor(method, store.rig.camera.model, dark=dark)
        return proc

    def read(self, store: SessionStore, event_id: str) -> np.ndarray:
        """The frame's cube: the stored one, else :meth:`compute`."""
        fr = store.frame(event_id)
        if "cube" in fr.files:
            cube, _ = decode_tiff(store.read_file(fr.files["cube"]))
            return cube
        return self.compute(store, fr)

    def compute(self, store: SessionStore, fr: FrameRecord) -> np.ndarray:
        """The frame's cube computed from raw + dark with its recipe, stored cube or not."""
        recipe = fr.meta.get("cube") or {}
        if recipe.get("calibrated") or fr.meta.get("calibration") is not None:
            raise CubeUnavailable(f"{store.session_id}/{fr.event_id}: calibrated frame without its "
                                  "stored cube")
        method = str(recipe.get("method") or fr.meta.get("processing_method") or store.sweep.processing)
        raw, _ = decode_tiff(store.read_file(fr.files["raw"]))  # read_raw would look the frame up again
        with self._lock:
            proc = self._processor(store, method, fr.dark_id)
            return np.array(proc.process(raw).cube, dtype=np.float32, copy=True)
