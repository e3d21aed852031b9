"""Exposure for the capture engine: the camera's (exposure, gain) setting and automatic exposure.

:class:`CameraControl` configures the camera only when the setting changes and snaps with a
timeout of the exposure plus ``snap_timeout_s``; after a fault or a pause the engine calls
:meth:`CameraControl.forget` so the next capture re-commands the setting.

:class:`ExposureMeter` meters once per lighting condition when the sweep asks for it
(:func:`m2s2hil.engine.exposure_search.find_exposure`), records the result as a journal event
``auto_exposure`` and reuses it for every later frame of that condition; a resumed session
restores the results from the journal instead of metering again.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from m2s2hil.config import CameraModel
from m2s2hil.drivers.interfaces import SplitSnap
from m2s2hil.engine.exposure_search import ExposureResult, find_exposure
from m2s2hil.plan import AutoExposureSettings, CaptureEvent, Sweep
from m2s2hil.plan.model import bracket_exposure
from m2s2hil.rig.opened import Rig
from m2s2hil.store.session import SessionStore

log = logging.getLogger(__name__)


class CameraControl:
    """The camera's current (exposure, gain) as last commanded, and snaps with a timeout."""

    def __init__(self, rig: Rig, snap_timeout_s: float) -> None:
        self.rig = rig  # the camera is looked up on the rig at each call
        self.snap_timeout_s = snap_timeout_s
        self._setting: tuple[float, float] | None = None

    def configure(self, exposure_s: float, gain: float) -> None:
        if self._setting != (exposure_s, gain):
            self.rig.camera.configure(exposure_s=exposure_s, gain=gain)
            self._setting = (exposure_s, gain)

    def forget(self) -> None:
        """The camera's setting is no longer trusted (fault, pause): command it again next time."""
        self._setting = None

    def snap(self, exposure_s: float) -> Any:
        return self.rig.camera.snap(timeout=exposure_s + self.snap_timeout_s)

    def snap_then(self, exposure_s: float, after_exposure: Callable[[], object]) -> Any:
        """A snap that calls ``after_exposure`` once the exposure has ended and before the frame
        is read out (the stage heads for the next pose during the readout). A camera that cannot
        split its snap (:class:`~m2s2hil.drivers.interfaces.SplitSnap`) snaps, then calls it.
        The frame is read even when ``after_exposure`` raises, so no stale frame is left for
        the next trigger (its error is raised after)."""
        cam = self.rig.camera
        if not isinstance(cam, SplitSnap):
            frame = cam.snap(timeout=exposure_s + self.snap_timeout_s)
            after_exposure()
            return frame
        cam.trigger()
        # The exposure began no later than the trigger's acknowledgement.
        self.rig.clock.sleep(exposure_s)
        try:
            after_exposure()
        finally:
            frame = cam.read_triggered(timeout=exposure_s + self.snap_timeout_s)
        return frame


class ExposureMeter:
    """The exposure of each capture: the planned one, or the metered one per lighting condition."""

    def __init__(self, sweep: Sweep, store: SessionStore, camera: CameraControl, model: CameraModel) -> None:
        self.sweep = sweep
        self.store = store
        self.camera = camera
        self.model = model
        self.results: dict[str, ExposureResult] = {}  # lighting -> metered exposure

    def restore(self) -> None:
        """Reload the results journaled by an earlier run of this session."""
        if not self.sweep.auto_exposure:
            return
        for rec in self.store.events():
            if rec.get("kind") == "auto_exposure":
                p = rec.get("payload") or {}
                try:
                    self.results[p["lighting"]] = ExposureResult(
                        float(p["exposure_s"]), float(p["level_dn"]), int(p["frames"]),
                        tuple(tuple(h) for h in p.get("history", [])), bool(p["converged"]), p.get("limited"),
                    )
                except (KeyError, TypeError, ValueError):
                    log.warning("ignoring a malformed auto_exposure record: %r", p)

    def needs_metering(self, ev: CaptureEvent) -> bool:
        return bool(self.sweep.auto_exposure) and ev.lighting not in self.results

    def exposure(self, ev: CaptureEvent) -> tuple[float, ExposureResult | None]:
        """``(exposure_s, result)``; ``result`` is None without auto exposure. Meters if needed; a
        bracket member takes its factor × the metered exposure, within the camera's limits."""
        if not self.sweep.auto_exposure:
            return ev.exposure_s, None
        assert ev.lighting is not None
        res = self.results.get(ev.lighting)
        if res is None:
            res = self._meter(ev)
            self.results[ev.lighting] = res
            self.store.record_event("auto_exposure", {"lighting": ev.lighting, "event_id": ev.event_id,
                                                      **res.to_dict()})
        if ev.bracket_member:
            return bracket_exposure(res.exposure_s, ev.exposure_factor), res
        return res.exposure_s, res

    def _meter(self, ev: CaptureEvent) -> ExposureResult:
        ae = self.sweep.exposure
        assert isinstance(ae, AutoExposureSettings)  # only metered when the sweep asks for it
        model = self.model

        def measure(t: float) -> np.ndarray:
            t = round(t, 6)
            self.camera.configure(t, ev.gain)
            return self.camera.snap(t).data

        res = find_exposure(
            measure, full_scale=model.full_scale, start_s=ev.exposure_s, min_s=ae.min_s, max_s=ae.max_s,
            # aim a little under the limit and accept the first frame within ~8 % below it
            limit=ae.target_fraction, aim=ae.target_fraction * 0.967, accept_low=ae.target_fraction * 0.922,
            percentile=ae.percentile, max_frames=ae.max_iterations,
        )
        return ExposureResult(round(res.exposure_s, 6), res.level, res.frames, res.history, res.converged,
                              res.limited)
