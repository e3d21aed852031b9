"""``m2s2_sweep``: an M2S2 sweep as a bluesky plan over the devices of :mod:`.devices`.

The sweep's events come from the same expansion as ``capture``
(:meth:`m2s2hil.plan.Sweep.expand`: same event ids, darks first, snake order, cable-wrap-aware
azimuths). The planned master darks are taken first, lamps off, by the engine's own
:class:`~m2s2hil.engine.darks.SessionDarks` (``camera.darks``: lens capped, N frames, master
dark, ``store.write_dark``; a dark the session already holds is loaded, not retaken); on a real
rig, where only the operator can cap the lens, the plan stops before anything moves with
:class:`~m2s2hil.integrations.bluesky.darks.LensCapNeeded` unless the session holds every
planned dark already. For each frame event the plan then sets the lamp preset, the tilt, then
the turntable (the engine's order), sets exposure and gain, triggers the camera (which
subtracts that setting's dark and records its ``dark_id`` and provenance) and reads every device
into the ``primary`` stream. The frames land in the session the camera's store holds, through
the engine's frame stages.
"""

from __future__ import annotations

import asyncio
from collections.abc import Generator
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp

from m2s2hil.catalog import load_catalog
from m2s2hil.integrations.bluesky.darks import LensCapNeeded, lens_cap_message, run_step
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
    planned = sw.expand(rig.config)
    events = [ev for ev in planned if ev.kind == "frame"]
    done_ids = store.completed_event_ids()
    darks = [ev for ev in planned if ev.kind == "dark" and ev.event_id not in done_ids]
    if darks and rig.lens_needs_operator:
        raise LensCapNeeded(lens_cap_message(f"m2s2_sweep of session {store.session_id} "
                                             f"({len(darks)} master dark(s) to take)"))
    detectors = [camera, turntable, tilt, lamps]
    meta = {"plan_name": "m2s2_sweep", "plan_args": {"sat": sat, "build": build, "light": lights},
            "session_id": store.session_id, "satellite": sat, "build": build,
            "sweep": sw.model_dump(mode="json"), "num_points": len(events),
            **camera_start_metadata(rig.config.camera.model), **(md or {})}
    rig.mount(sat, build)

    @bpp.stage_decorator(detectors)
    @bpp.run_decorator(md=meta)
    def inner() -> Generator[Any, Any, str]:
        for dark in darks:  # first, before any lamp is on (capture's order); a simulated lens caps itself
            done = yield from bps.wait_for([lambda ev=dark: asyncio.to_thread(
                run_step, camera.darks.capture(ev), rig)])
            done[0].result()  # a failed dark fails the plan
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
