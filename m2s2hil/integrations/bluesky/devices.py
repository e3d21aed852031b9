"""The opened rig as ophyd-async devices: two axes, the lamp presets, the camera.

ophyd-async rather than ophyd: its devices are asyncio-native (the RunEngine's own loop), its
soft signals need no EPICS or other control system, and it is where bluesky's device work goes.
Every device wraps the one :class:`~m2s2hil.rig.operations.RigOps` over the opened
:class:`~m2s2hil.rig.opened.Rig` (the engine's own motion, lamp and safety logic: tolerance
check on the read-back, lamp warm-up bookkeeping); the blocking driver calls run in a worker
thread so the event loop keeps serving. No device logic is copied here.

- :class:`RigAxis` (``turntable``, ``tilt``): ``set(deg)`` returns a status that completes once
  the read-back is within the rig file's ``tolerance_deg`` (else it fails with the driver's
  ``MoveNotVerified``); targets outside ``min_deg..max_deg`` fail before anything moves.
- :class:`LampPresets`: ``set("directional")`` switches the preset's lamps (rig file
  ``[lighting]``), verified by the relay board's read-back.
- :class:`M2S2Camera`: a triggerable detector with ``exposure_s`` and ``gain`` signals. Each
  trigger snaps one frame and writes it through the session store with the engine's frame
  stages (:class:`~m2s2hil.engine.frames.FrameStages`: same metadata, cube, preview, truth
  labels as ``capture``), dark-subtracted with the session's master dark for its (exposure,
  gain) from the engine's :class:`~m2s2hil.engine.darks.SessionDarks` (taken by the plan
  beforehand, loaded from the store, or captured on demand; retaken when the sensor drifted,
  as in ``capture``; :mod:`.darks` runs those steps); ``read()`` gives the event id and the
  scalars, and the raw mosaic as an external ``STREAM:`` key whose stream resource names the
  stored TIFF and its sha256.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

from bluesky.protocols import StreamAsset
from event_model import compose_stream_resource
from ophyd_async.core import (
    AsyncStatus,
    StandardReadable,
    StandardReadableFormat,
    soft_signal_r_and_setter,
    soft_signal_rw,
)

from m2s2hil.engine.darks import SessionDarks
from m2s2hil.engine.exposure import CameraControl
from m2s2hil.engine.frames import CapturedFrame, FrameStages
from m2s2hil.errors import UsageError
from m2s2hil.integrations.bluesky.darks import run_step
from m2s2hil.integrations.documents import FRAME_SCALARS, TIFF, _frame_values, raw_data_key
from m2s2hil.plan import CaptureEvent
from m2s2hil.rig.opened import AxisRole, Rig
from m2s2hil.rig.operations import RigOps
from m2s2hil.store.session import SessionStore


class OutOfLimits(UsageError):
    """A target outside the axis's soft limits (rig file ``min_deg``/``max_deg``)."""


class RigAxis(StandardReadable):
    """One rotary axis as a bluesky movable (see the module docstring)."""

    def __init__(self, ops: RigOps, role: AxisRole, name: str = "") -> None:
        self._ops, self._role = ops, role
        cfg = ops.rig.config.axes[role]
        self.low, self.high = cfg.min_deg, cfg.max_deg
        with self.add_children_as_readables(StandardReadableFormat.HINTED_SIGNAL):
            self.readback, self._set_readback = soft_signal_r_and_setter(float, units="deg")
        with self.add_children_as_readables(StandardReadableFormat.CONFIG_SIGNAL):
            self.tolerance_deg = soft_signal_rw(float, initial_value=cfg.tolerance_deg, units="deg")
            self.low_limit_deg = soft_signal_rw(float, initial_value=cfg.min_deg, units="deg")
            self.high_limit_deg = soft_signal_rw(float, initial_value=cfg.max_deg, units="deg")
        self.setpoint = soft_signal_rw(float, units="deg")
        super().__init__(name=name or role)

    @AsyncStatus.wrap
    async def set(self, value: float) -> None:
        target = float(value)
        if not self.low <= target <= self.high:
            raise OutOfLimits(f"{self.name}: {target} deg is outside {self.low}..{self.high} deg")
        await self.setpoint.set(target)
        # RigOps.move checks the read-back against tolerance_deg and raises MoveNotVerified
        await asyncio.to_thread(self._ops.move, self._role, target)
        self._set_readback(float(await asyncio.to_thread(self._ops.axis(self._role).position)))

    async def stop(self, success: bool = True) -> None:
        await asyncio.to_thread(self._ops.axis(self._role).stop)


class LampPresets(StandardReadable):
    """The rig file's lighting presets as one settable device; the lamps lit as its reading."""

    def __init__(self, ops: RigOps, name: str = "lamps") -> None:
        self._ops = ops
        cfg = ops.rig.config
        self.presets = {p: frozenset(cfg.lamps[n].channel for n in names)
                        for p, names in cfg.lighting.items()}
        with self.add_children_as_readables(StandardReadableFormat.HINTED_SIGNAL):
            self.preset, self._set_preset = soft_signal_r_and_setter(str, initial_value="")
        with self.add_children_as_readables():
            self.lamps_on, self._set_lamps_on = soft_signal_r_and_setter(str, initial_value="")
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def set(self, value: str) -> None:
        if value not in self.presets:
            raise UsageError(f"{self.name}: no lighting preset {value!r}; known: {', '.join(self.presets)}")
        await asyncio.to_thread(self._ops.set_lamps, self.presets[value])
        self._set_preset(value)
        self._set_lamps_on(",".join(self._ops.lamp_names()))


class M2S2Camera(StandardReadable):
    """The camera as a bluesky detector whose frames go into a session (see the module docstring)."""

    def __init__(self, stages: FrameStages, darks: SessionDarks, name: str = "camera") -> None:
        self._stages = stages
        self._darks = darks
        self._store: SessionStore = stages.store
        m = stages.rig.config.camera.model
        self._shape = (m.height, m.width)
        self._event: CaptureEvent | None = None
        self._last: Any = None  # the FrameRecord of the last trigger
        self._assets: list[StreamAsset] = []
        self._n = 0
        with self.add_children_as_readables(StandardReadableFormat.CONFIG_SIGNAL):
            self.exposure_s = soft_signal_rw(float, initial_value=0.01, units="s")
            self.gain = soft_signal_rw(float, initial_value=0.0)
        super().__init__(name=name)

    @property
    def store(self) -> SessionStore:
        """The session its frames go into."""
        return self._store

    @property
    def rig(self) -> Rig:
        return self._stages.rig

    @property
    def darks(self) -> SessionDarks:
        """The session's master darks, as the engine keeps them (the plan takes the planned ones)."""
        return self._darks

    def prepare_event(self, event: CaptureEvent) -> None:
        """The sweep event the next trigger captures (its id names the frame in the session)."""
        self._event = event

    @AsyncStatus.wrap
    async def stage(self) -> None:
        self._n = 0

    @AsyncStatus.wrap
    async def unstage(self) -> None:
        self._event = None

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        ev = self._event
        if ev is None:
            raise UsageError(f"{self.name}: trigger without a sweep event (call prepare_event first)")
        exposure, gain = await self.exposure_s.get_value(), await self.gain.get_value()
        self._last = await asyncio.to_thread(self._capture, ev, exposure, gain)
        self._event = None

    def _capture(self, ev: CaptureEvent, exposure: float, gain: float) -> Any:
        # the steps of StopAndGoSteps._capture_frame after the move, in its order
        st, darks, rig = self._stages, self._darks, self._stages.rig
        dark = run_step(darks.for_setting(exposure, gain), rig)
        darks.camera.configure(exposure, gain)
        t_clock, t_wall = rig.clock.monotonic(), rig.clock.wall()
        frame = darks.camera.snap(exposure)
        truth = st.truth()
        dark = run_step(darks.check_temperature(dark, exposure, gain, frame.temperature_c), rig)
        meta = st.meta(ev, frame, exposure, dark, t_clock, t_wall, 1)
        cap = CapturedFrame(frame.data, meta, st.processor(dark), truth)
        return st.write(ev, st.process(ev, cap))

    async def describe(self) -> dict[str, Any]:
        keys = {f"{self.name}_{k}": {"source": f"m2s2hil:{self.name}", "dtype": d, "shape": [],
                                     **({"dtype_numpy": n} if n else {})}
                for k, (d, n) in _scalar_types().items()}
        keys[f"{self.name}_raw"] = raw_data_key(f"m2s2hil:{self.name}", *self._shape)
        return keys

    async def read(self) -> dict[str, Any]:
        fr = self._last
        if fr is None:
            return {}
        values = {**_frame_values(fr.meta), "event_id": fr.event_id}
        self._n += 1
        rec = fr.files["raw"]
        bundle = compose_stream_resource(
            mimetype=TIFF, uri=(self._store.path / rec.path).resolve().as_uri(), data_key=f"{self.name}_raw",
            parameters={"sha256": rec.sha256, "path": rec.path})
        self._assets = [("stream_resource", bundle.stream_resource_doc),
                        ("stream_datum", bundle.compose_stream_datum(indices={"start": 0, "stop": 1}))]
        return {f"{self.name}_{k}": {"value": v, "timestamp": fr.time} for k, v in values.items()}

    async def collect_asset_docs(self, index: int | None = None) -> AsyncIterator[StreamAsset]:
        for asset in self._assets:
            yield asset
        self._assets = []

    async def get_index(self) -> int:
        return self._n


def _scalar_types() -> dict[str, tuple[str, str]]:
    from m2s2hil.integrations.documents import SCALARS

    return {k: SCALARS[k] for k in FRAME_SCALARS}


@dataclass(frozen=True)
class RigDevices:
    turntable: RigAxis
    tilt: RigAxis
    lamps: LampPresets
    camera: M2S2Camera


def rig_devices(rig: Rig, store: SessionStore, *, save_truth: bool = True) -> RigDevices:
    """The four devices over one opened rig and one session: one RigOps, one FrameStages, one
    SessionDarks, built as the engine builds them (``make_steps``: the processing the sweep
    names, the rig's snap timeout; no capture-time QC)."""
    ops = RigOps(rig)
    stages = FrameStages(rig, store, store.sweep, ops, qc=None, save_truth=save_truth, processor_factory=None)
    darks = SessionDarks(rig, store, store.sweep, ops, CameraControl(rig, rig.config.camera.timeout_s))
    return RigDevices(RigAxis(ops, "turntable"), RigAxis(ops, "tilt"), LampPresets(ops),
                      M2S2Camera(stages, darks))
