"""What happens to a frame after the snap: its metadata, the processing and storage stages.

The engine thread builds each frame's metadata (:meth:`FrameStages.meta`) and the simulator's
truth, then hands a :class:`CapturedFrame` to the :class:`~m2s2hil.engine.pipeline.Pipeline`, whose
threads run :meth:`FrameStages.process` (dark subtraction + demosaicing with
``processing.chain.FrameProcessor``, one per master dark; then the QC hook; then an RGB
preview) and :meth:`FrameStages.write` (``store.write_frame``).

Frame metadata (``meta`` of each stored frame): ``exposure_s`` and ``gain`` as the camera
reported them, ``temperature_c``, ``pose`` (read-back of both axes), ``lamps_on``
(channels) and ``lamp_names``, ``timestamp`` (wall), ``clock_s`` (engine clock),
``host_wall``, ``device_timestamp_s``, ``host_time_s``, ``block_id``, ``dark_id`` and
``dark`` (its provenance), ``attempt`` (1 + failed tries of this capture),
``qc`` (the hook's result), ``saturated_fraction``, ``processing_warnings``; with auto
exposure ``auto_exposure``; in continuous mode ``continuous`` (angle at mid-exposure, its
error to the mark, measured speed, blur in degrees and pixels). The QC hook is
``qc(processed_frame, event, meta) -> score``; its result is ``meta["qc"]``, a failure is
``meta["qc_error"]`` (the frame is kept). The store adds what it owns (session, event,
``processing_method``, ``software_version``, ``rig_digest``, storage format, cube recipe) and
encodes the whole once (m2s2hil.store.frame_meta); those keys are never set here.

On a simulated rig the simulator's label map is stored with the frame as its
``truth_labels`` file (``store.frame(id).files["truth_labels"]``, a checksummed PNG) and
``meta["truth"]`` holds the class names and the simulator's pose.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from m2s2hil.engine.darks import Dark
from m2s2hil.plan import CaptureEvent, Sweep
from m2s2hil.processing.display import false_colour
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore

log = logging.getLogger(__name__)

QcHook = Callable[[Any, CaptureEvent, dict], Any]


@dataclass
class CapturedFrame:
    """What the camera thread hands to the processing stage."""

    data: np.ndarray
    meta: dict
    processor: Any
    truth: Any = None


@dataclass
class FrameToStore:
    """What the processing stage hands to the storage stage."""

    raw: np.ndarray
    cube: np.ndarray | None
    preview: np.ndarray | None
    meta: dict
    truth: Any = None
    extra: dict[str, np.ndarray] | None = None  # more arrays stored with the frame (the QC hook's)


class FrameStages:
    """Per-frame metadata and truth (engine thread), processing and storage (pipeline threads)."""

    def __init__(self, rig: Rig, store: SessionStore, sweep: Sweep, ops: RigOps, *, qc: QcHook | None,
                 save_truth: bool, processor_factory: Callable[..., Any] | None) -> None:
        self.rig = rig
        self.store = store
        self.sweep = sweep
        self.ops = ops
        self.qc = qc
        bind = getattr(qc, "bind", None)
        if callable(bind):  # a hook that checks frames against the session (the twin's) learns it here
            bind(sweep, rig.config)
        self.save_truth = save_truth
        self.processor_factory = processor_factory
        self._processors: dict[str | None, Any] = {}  # dark id -> frame processor

    def processor(self, dark: Dark | None) -> Any:
        """The frame processor for frames with this dark (built once per dark)."""
        key = dark.dark_id if dark is not None else None
        proc = self._processors.get(key)
        if proc is None:
            factory = self.processor_factory
            if factory is None:
                from m2s2hil.processing.chain import FrameProcessor

                factory = FrameProcessor
            kw: dict[str, Any] = {"dark": dark.master if dark is not None else None}
            if self.rig.calibration is not None:  # crosstalk, white reference, real layout
                kw["calibration"] = self.rig.calibration
            proc = factory(self.sweep.processing, self.rig.config.camera.model, **kw)
            self._processors[key] = proc
        return proc

    def meta(self, ev: CaptureEvent, frame: Any, exposure: float, dark: Dark | None, t_clock: float,
             t_wall: float, attempt: int) -> dict:
        """The frame's metadata at capture time (the processing stage adds its own)."""
        pose = self.ops.pose()
        return {
            "exposure_s": float(frame.exposure_s or exposure),
            "planned_exposure_s": ev.exposure_s,
            "gain": float(frame.gain),
            "temperature_c": float(frame.temperature_c),
            "pose": {"turntable_deg": pose["turntable"], "tilt_deg": pose["tilt"]},
            "lamps_on": sorted(self.ops.lit),
            "lamp_names": self.ops.lamp_names(),
            "lamp_on_s": self.ops.lamp_ages(),
            "timestamp": t_wall,  # the engine clock's wall time (synthetic on a virtual clock)
            "host_wall": time.time(),  # the computer's own wall time, for provenance
            "clock_s": t_clock,
            "host_time_s": float(frame.host_time_s),
            "device_timestamp_s": float(frame.timestamp_s),
            "block_id": int(frame.block_id),
            "pixel_format": frame.pixel_format,
            "dark_id": dark.dark_id if dark is not None else None,
            "dark": dark.master.provenance() if dark is not None else None,
            "mode": self.sweep.mode,
            "attempt": attempt,
            "simulated": bool(self.rig.simulated),
        }

    def truth(self) -> Any:
        """The simulator's label map and pose for the frame just taken (None on a real rig)."""
        if not self.save_truth:
            return None
        src = self.rig.frame_source
        if src is None:
            return None
        t = src.truth()
        labels = getattr(t, "labels", None)
        if labels is None:
            return None
        return {"labels": np.array(labels, copy=True), "class_names": list(getattr(t, "class_names", [])),
                "azimuth_deg": float(getattr(t, "azimuth_deg", math.nan)),
                "tilt_deg": float(getattr(t, "tilt_deg", math.nan))}

    def process(self, ev: CaptureEvent, cap: CapturedFrame) -> FrameToStore:
        """Processing stage (pipeline thread): cube, QC hook, preview."""
        meta = dict(cap.meta)
        pf = cap.processor.process(cap.data)
        cube = np.array(pf.cube, copy=True)  # the processor may reuse its output buffers
        sat = getattr(pf, "saturated_mask", None)
        meta["saturated_fraction"] = float(np.mean(sat)) if sat is not None else None
        meta["processing_warnings"] = [str(w) for w in getattr(pf, "warnings", ())]
        calibration = (getattr(pf, "info", None) or {}).get("calibration")
        if calibration is not None:
            meta["calibration"] = calibration
        if self.qc is not None and ev.bracket_member:
            # Its lit faces clip by design (it is there for the shadows): the pose's own frame is
            # the one checked, and a flag here would only tell the operator what was planned.
            meta["qc"] = None
            meta["qc_skipped"] = f"bracket member (x{ev.exposure_factor:g}): the pose's own frame is checked"
        elif self.qc is not None:
            try:
                meta["qc"] = jsonable(self.qc(pf, ev, meta))
            except Exception as exc:  # a QC bug must not lose the frame; it is recorded
                log.exception("QC hook failed on %s", ev.event_id)
                meta["qc"] = None
                meta["qc_error"] = f"{type(exc).__name__}: {exc}"
        white = calibrated_white(cap.processor)
        preview = rgb_preview(cube, self.rig.config.camera.model.bands_nm, white=white)
        files = getattr(self.qc, "frame_files", None)  # e.g. the twin's projected labels
        extra = files(ev) if callable(files) and "qc" in meta and meta["qc"] is not None else None
        return FrameToStore(cap.data, cube, preview, meta, cap.truth, extra or None)

    def write(self, ev: CaptureEvent, p: FrameToStore) -> Any:
        """Storage stage (pipeline thread): the frame's files and record."""
        if p.truth is None:
            return self.store.write_frame(ev, p.raw, p.cube, p.preview, p.meta, extra=p.extra)
        # Simulation: the label map is stored as the frame's "truth_labels" file (checksummed
        # and committed with it); the rest of the truth that is small goes into the metadata.
        meta = {**p.meta, "truth": {k: v for k, v in p.truth.items() if k != "labels"}}
        return self.store.write_frame(ev, p.raw, p.cube, p.preview, meta,
                                      extra={**(p.extra or {}), "truth_labels": p.truth["labels"]})


def qc_number(v: Any) -> float | None:
    """The QC hook's result as one score (a number, or a dict's ``score``), for events."""
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return float(v)
    if isinstance(v, dict):
        s = v.get("score")
        return float(s) if isinstance(s, (int, float)) else None
    return None


def jsonable(v: Any) -> Any:
    """``v`` with numpy scalars made Python numbers and tuples made lists (for the metadata)."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    return v


def calibrated_white(processor: Any) -> np.ndarray | None:
    """A white reference's signal per band when the processor flat-fields with one (its cubes are then
    reflectance: the white reads its own reflectance), else None (the preview uses grey world)."""
    cal = getattr(processor, "calibration", None)
    if cal is None or getattr(cal, "white_mosaic", None) is None:
        return None
    refl = getattr(cal, "white_reflectance", None)
    return np.ones(1) if refl is None else np.atleast_1d(np.asarray(refl, dtype=np.float64))


def rgb_preview(cube: np.ndarray | None, bands_nm: tuple[float, ...],
                white: np.ndarray | None = None) -> np.ndarray | None:
    """8-bit sRGB preview (``processing.display.false_colour``): bands nearest 640/550/470 nm,
    white-balanced (grey world, or ``white``: a white reference's signal per band), sRGB curve."""
    if cube is None or cube.ndim != 3:
        return None
    if cube.shape[0] != len(bands_nm):  # (H, W, bands)
        cube = np.moveaxis(cube, -1, 0)
    if white is not None and np.size(white) == 1:  # one reflectance for every band
        white = np.full(len(bands_nm), float(np.ravel(white)[0]))
    return false_colour(cube, bands_nm, white=white)
