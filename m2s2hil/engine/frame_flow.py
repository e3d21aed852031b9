"""The pipeline's side of a run: captured frames in, their outcomes out.

A frame the steps yield is submitted (in flight from then on, event ``Captured``); an
outcome comes back from the storage thread: stored (done, event ``FrameStored``) or failed
at a stage, which goes through the one fault policy (:class:`~m2s2hil.engine.recovery.Recovery`)
like a capture's fault: skipped, failed the run, or captured again (requeued). A batch whose
outcomes ask for a suspension returns the reason once every outcome of it is accounted for,
and the runner parks.
"""

from __future__ import annotations

from collections.abc import Callable

from m2s2hil.engine.frames import CapturedFrame, FrameStages, qc_number
from m2s2hil.engine.messages import FrameCaptured
from m2s2hil.engine.pipeline import Pipeline
from m2s2hil.engine.recovery import Recovery, Verdict
from m2s2hil.engine.schedule import UnitSchedule
from m2s2hil.engine.state import Captured, FrameStored
from m2s2hil.plan import CaptureEvent

#: Publishes an engine event: ``publish(EventClass, **fields)``.
Publish = Callable[..., None]


class FrameFlow:
    """Submits frames to ``pipeline`` and acts on what comes back."""

    def __init__(self, pipeline: Pipeline, frames: FrameStages, schedule: UnitSchedule, recovery: Recovery,
                 publish: Publish, progress: Callable[[], None]) -> None:
        self.pipeline = pipeline
        self.frames = frames
        self.schedule = schedule
        self.recovery = recovery
        self._publish = publish
        self._progress = progress

    def submit(self, msg: FrameCaptured) -> None:
        ev, meta = msg.event, msg.meta
        processor = self.frames.processor(msg.dark)
        self.schedule.submitted(ev)
        self.pipeline.submit(ev, CapturedFrame(msg.data, meta, processor, msg.truth))
        self._publish(Captured, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                      elevation=ev.elevation, azimuth_deg=meta["pose"]["turntable_deg"],
                      tilt_deg=meta["pose"]["tilt_deg"], exposure_s=meta["exposure_s"])

    def collect(self, *, final: bool = False) -> str | None:
        """Consume the outcomes so far; the reason to suspend, if one asked for it. Raises the
        error of an outcome whose policy fails the run (``final``: at teardown, no back-off)."""
        suspend: str | None = None
        for o in self.pipeline.results():
            ev: CaptureEvent = o.key
            self.schedule.settled(ev)
            if o.ok:
                rec = o.result
                self.schedule.mark_done(ev)
                self._publish(
                    FrameStored, event_id=ev.event_id, index=ev.index, lighting=ev.lighting,
                    elevation=ev.elevation, azimuth_deg=ev.nominal_azimuth_deg,
                    exposure_s=rec.meta.get("exposure_s") if rec else None,
                    path=rec.files["raw"].path if rec and "raw" in rec.files else None,
                    qc_score=qc_number(rec.meta.get("qc")) if rec else None,
                )
                self._progress()
                pause = self.recovery.policy.qc_pause_reason(rec.meta.get("qc"), ev.event_id) if rec else None
                suspend = suspend or pause
                continue
            assert o.error is not None
            res = self.recovery.handle_stored(o.error, ev, o.stage, final=final)
            if res.verdict is Verdict.SKIPPED:
                self._progress()
            elif res.verdict is Verdict.ABORT:
                raise res.error
            else:  # retry / reconnect / suspend: capture it again
                self.schedule.requeue_failed(ev)
                if res.verdict is Verdict.SUSPEND:
                    suspend = suspend or res.reason
        return suspend
