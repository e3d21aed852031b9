"""``m2s2_sweep``: an M2S2 sweep as a bluesky plan over the devices of :mod:`.devices`.

The sweep's frame events come from the same expansion as ``capture``
(:meth:`m2s2hil.plan.Sweep.expand`: same event ids, snake order, cable-wrap-aware azimuths);
for each one the plan sets the lamp preset, the tilt, then the turntable (the engine's order),
sets exposure and gain, triggers the camera and reads every device into the ``primary`` stream.
The frames land in the session the camera's store holds, through the engine's frame stages.
Dark frames are not taken by this plan: its frames carry no ``dark_id`` (see the docs page).
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp

from m2s2hil.catalog import load_catalog
from m2s2hil.integrations.bluesky.devices import LampPresets, M2S2Camera, RigAxis
from m2s2hil.integrations.documents import camera_start_metadata
from m2s2hil.plan import Sweep


def m2s2_sweep(sat: str, build: str, light: str | list[str], *, turntable: RigAxis, tilt: RigAxis,
               lamps: LampPresets, camera: M2S2Camera, sweep: Sweep | None = None,
               md: dict[str, Any] | None = None) -> Generator[Any, Any, str]:
    """Capture satellite ``sat`` build ``build`` under lighting ``light`` (one or several presets).

    ``sweep`` overrides the rest of the sweep (tilts, azimuth step, ...); its satellite, build
    and lighting are replaced by the arguments. Returns the run's uid."""
    lights = [light] if isinstance(light, str) else list(light)
    base = sweep or Sweep(satellite=sat, build=build, lighting=lights)
    sw = base.model_copy(update={"satellite": sat, "build": build, "lighting": lights})
    load_catalog().build(sat, build)  # an unknown satellite or build fails before anything moves
    store = camera.store
    rig = camera.rig
    events = [ev for ev in sw.expand(rig.config) if ev.kind == "frame"]
    detectors = [camera, turntable, tilt, lamps]
    meta = {"plan_name": "m2s2_sweep", "plan_args": {"sat": sat, "build": build, "light": lights},
            "session_id": store.session_id, "satellite": sat, "build": build,
            "sweep": sw.model_dump(mode="json"), "num_points": len(events),
            **camera_start_metadata(rig.config.camera.model), **(md or {})}
    rig.mount(sat, build)

    @bpp.stage_decorator(detectors)
    @bpp.run_decorator(md=meta)
    def inner() -> Generator[Any, Any, str]:
        for ev in events:
            yield from bps.mv(lamps, ev.lighting)
            yield from bps.mv(tilt, ev.tilt_deg)
            yield from bps.mv(turntable, ev.azimuth_deg)
            yield from bps.mv(camera.exposure_s, ev.exposure_s, camera.gain, ev.gain)
            camera.prepare_event(ev)
            yield from bps.trigger_and_read(detectors)
        return store.session_id

    try:
        return (yield from inner())
    finally:
        # every exit path leaves the rig safe: lamps off, motion stopped
        rig.safe()
