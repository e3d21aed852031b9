"""The master darks of a capture session, as the engine uses them.

- *dark* events: lens cap on (``rig.cap_lens``), N frames, master dark
  (``processing.dark.build_master_dark``), ``store.write_dark``; the cap comes off whatever
  happens to the snaps.
- every frame at an (exposure, gain) reuses that setting's dark: one taken in this run, one
  the store already holds (a resumed session loads it), or one captured on demand (e.g. for
  an exposure that auto exposure chose).
- the lens cap on a real rig (a camera not simulated in this process, ``rig.lens_needs_operator``):
  nothing here can put it on or check it, so the operator does, and is trusted. Before a dark
  the run parks at a safe boundary (lamps off, motion stopped) with the pause reason
  :data:`LENS_CAP_REASON` until the operator confirms the cap is on (``Engine.confirm_lens``);
  planned darks (taken first, back to back) share one capping, and before the next lit unit
  the run parks again with :data:`LENS_UNCAP_REASON`. The darks ask for it by yielding
  :class:`~m2s2hil.engine.messages.LensRequest` (the runner parks). A dark needed in the
  middle of a lit unit (auto exposure, a temperature retake) is capped and uncapped on its
  own (counted in :attr:`SessionDarks.lens_cycles`), and the steps then capture the unit from
  its start: its lamps and pose were given up while parked. A simulated camera's lens is
  capped by ``rig.cap_lens`` with no one asked.
- temperature: when the sensor has drifted beyond
  ``processing.dark_temperature_tolerance_c`` from a dark's temperature, the dark is
  retaken under a new id (``<planned id>/t<n>``) and the planned id is aliased to it, so
  later frames at that setting use the fresh one.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from m2s2hil.engine.exposure import CameraControl
from m2s2hil.engine.messages import DarkStored, LensRequest, StepGen
from m2s2hil.plan import CaptureEvent, Sweep, dark_event, dark_event_id
from m2s2hil.rig.opened import Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.records import DarkRecord
from m2s2hil.store.session import SessionStore

log = logging.getLogger(__name__)

#: The pause reasons of a real rig waiting for the operator (``EngineStatus.pause_reason``).
LENS_CAP_REASON = "lens_cap: put the lens cap on"
LENS_UNCAP_REASON = "lens_cap: take the lens cap off"


def lens_reason(capped: bool) -> str:
    """The pause reason while the run waits for the operator to cap (True) or uncap the lens."""
    return LENS_CAP_REASON if capped else LENS_UNCAP_REASON


@dataclass(frozen=True)
class Dark:
    """A master dark and the id it is stored under."""

    dark_id: str
    master: Any  # processing.dark.MasterDark

    @property
    def temperature_c(self) -> float:
        return float(self.master.temperature_c)


class SessionDarks:
    """Darks by id, with the alias from a planned dark id to the id of its retake.

    The capturing methods are steps (generators of
    :data:`~m2s2hil.engine.messages.StepMessage`, their return value the dark): each dark
    stored yields :class:`~m2s2hil.engine.messages.DarkStored`; on a real rig
    (``rig.lens_needs_operator``) the cap is asked for with
    :class:`~m2s2hil.engine.messages.LensRequest`, else the rig caps its own (simulated) lens.
    """

    def __init__(self, rig: Rig, store: SessionStore, sweep: Sweep, ops: RigOps,
                 camera: CameraControl) -> None:
        self.rig = rig
        self.store = store
        self.sweep = sweep
        self.ops = ops
        self.camera = camera
        self._darks: dict[str, Dark] = {}
        self._alias: dict[str, str] = {}  # planned dark id -> id of a retaken dark
        #: Darks taken in the middle of a lit unit under the operator's cap: each parked the
        #: run twice (lamps off, pose forgotten), so the steps start that unit again.
        self.lens_cycles = 0

    def for_setting(self, exposure_s: float, gain: float) -> StepGen[Dark | None]:
        """The dark for frames at this setting (None when the sweep takes no darks)."""
        if self.sweep.dark.frames <= 0:
            return None
        did = dark_event_id(exposure_s, gain)
        did = self._alias.get(did, did)
        if did in self._darks:
            return self._darks[did]
        rec = self.store.dark_for(exposure_s, gain)
        if rec is not None:
            return self.load(rec)
        return (yield from self.capture(dark_event(exposure_s, gain, self.sweep.dark.frames)))

    def load(self, rec: DarkRecord) -> Dark:
        """A dark the store holds (as the store rebuilds it for computed cubes, provenance and all)."""
        from m2s2hil.store.cubes import master_dark_of

        if rec.reduce not in ("mean", "median"):
            raise ValueError(f"dark {rec.dark_id}: unknown reduction {rec.reduce!r} in the journal")
        dark = self._darks[rec.dark_id] = Dark(rec.dark_id, master_dark_of(self.store, rec))
        self._alias[dark_event_id(rec.exposure_s, rec.gain)] = rec.dark_id
        return dark

    def capture(self, ev: CaptureEvent) -> StepGen[Dark]:
        """Take, build and store the dark of ``ev`` (or load it if the session has it already)."""
        from m2s2hil.processing.dark import build_master_dark

        if ev.event_id in self.store.completed_event_ids():
            rec = next(d for d in self.store.darks() if d.dark_id == ev.event_id)
            return self.load(rec)
        cam = self.rig.camera
        operator = self.rig.lens_needs_operator
        if operator:
            # Real rig: the run parks until the operator confirms the cap. It stays on after
            # the dark (the next planned dark needs it too); the next lit unit asks for it
            # off, or a failed dark's retry finds it still on.
            yield LensRequest(True)
        else:
            self.rig.cap_lens(True)
            self.ops.lens_capped = True
        try:
            self.camera.configure(ev.exposure_s, ev.gain)
            frames = [self.camera.snap(ev.exposure_s) for _ in range(ev.n_frames)]
        finally:
            if not operator:  # a simulated cap comes off after the dark
                self.rig.cap_lens(False)
                self.ops.lens_capped = False
        master = build_master_dark(
            [f.data for f in frames], reduce=self.sweep.dark.reduce, exposure_s=ev.exposure_s, gain=ev.gain,
            temperature_c=[f.temperature_c for f in frames], camera=cam.serial or cam.name,
            tolerance_c=self.rig.config.processing.dark_temperature_tolerance_c,
        )
        del frames
        meta = {**master.provenance(), "clock_s": self.rig.clock.monotonic()}
        self.store.write_dark(ev, master.data, meta=meta)
        dark = self._darks[ev.event_id] = Dark(ev.event_id, master)
        base = dark_event_id(ev.exposure_s, ev.gain)
        if ev.event_id != base:
            self._alias[base] = ev.event_id
        yield DarkStored(ev)
        if ev.index < 0 and operator:
            # Not a planned dark: taken in the middle of a lit unit, whose lamps and pose the
            # parking gave up. Cap off; the steps capture the unit again (it finds this dark).
            yield LensRequest(False)
            self.lens_cycles += 1
        return dark

    def check_temperature(self, dark: Dark | None, exposure_s: float, gain: float,
                          temperature_c: float) -> StepGen[Dark | None]:
        """``dark``, or a retake of it when the sensor is now at a different temperature."""
        if dark is None:
            return None
        tol = self.rig.config.processing.dark_temperature_tolerance_c
        if abs(dark.temperature_c - temperature_c) <= tol or math.isnan(dark.temperature_c):
            return dark
        base = dark_event_id(exposure_s, gain)
        n = sum(1 for d in self._darks if d.startswith(base))
        ev = dark_event(exposure_s, gain, self.sweep.dark.frames).model_copy(
            update={"event_id": f"{base}/t{n}"})
        log.info("sensor at %.1f °C, dark %s at %.1f °C: retaking", temperature_c, dark.dark_id,
                 dark.temperature_c)
        return (yield from self.capture(ev))
