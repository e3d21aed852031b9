"""Synthetic sessions: ``POST /synthetic`` renders the paper's synthetic domain of one build
(m2s2hil.daemon.synth_jobs), and the session routes (``routes/sessions.py``) serve it like a
capture session: status, the event stream, abort, the listing."""

from __future__ import annotations

import asyncio
import weakref
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Body, Response
from pydantic import BaseModel, ConfigDict, Field

from m2s2hil.catalog import load_catalog
from m2s2hil.daemon.manager import SessionManager
from m2s2hil.daemon.synth_jobs import SynthJobs, control_stored, disk_status
from m2s2hil.twin.synth import DEFAULT_SIZE, SynthPlan

from .. import models as m
from ..common import CONFLICT, CROSS_SITE, Manager, links
from ..sse import POLL_S, _msg, parse_last_event_id

router = APIRouter(tags=["synthetic"])

_SERVICES: weakref.WeakKeyDictionary[SessionManager, SynthJobs] = weakref.WeakKeyDictionary()


def jobs_of(mg: SessionManager) -> SynthJobs:
    """The manager's synthetic renders (made on first use: the manager knows nothing of them)."""
    svc = _SERVICES.get(mg)
    if svc is None:
        svc = _SERVICES.setdefault(mg, SynthJobs(mg, queue_limit=mg.queue_limit,
                                                 keep_finished=mg.keep_finished))
    return svc


def _names() -> dict[str, list[str]]:
    """The catalog's canonical names, for the schema (the catalog checks them, aliases too)."""
    cat = load_catalog()
    return {"satellite": list(cat.satellites),
            "build": sorted({b for sat in cat.satellites.values() for b in sat.builds}),
            "light": list(cat.lighting), "tilt": [*cat.elevations, *cat.synthetic_elevations]}


_NAMES: dict[str, Any] = _names()  # JSON values for json_schema_extra
Elevation = Annotated[str, Field(pattern=r"^[Ee][0-9]$", json_schema_extra={"enum": _NAMES["tilt"]})]


class SynthBody(BaseModel):
    """What to render: one build, the preset whose lamps light it, elevations, azimuth grid, size."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"satellite": "hubble", "build": "B2"},
        {"satellite": "voyager", "build": "B3", "tilts": ["E0", "E3"], "azimuth_step_deg": 30, "size": 256}]})

    satellite: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z][A-Za-z0-9 _-]*$",
                           json_schema_extra={"enum": _NAMES["satellite"]},
                           description="A catalog satellite.")
    build: str = Field(pattern=r"^[Bb][0-9]$", json_schema_extra={"enum": _NAMES["build"]},
                       description="A build of it.")
    light: str = Field("strong", min_length=1, max_length=32, pattern=r"^[A-Za-z][A-Za-z_-]*$",
                       json_schema_extra={"enum": _NAMES["light"]},
                       description="The lighting preset whose lamps light the renders.")
    tilts: list[Elevation] = Field(
        default_factory=list, max_length=8,
        description="Elevations; empty: the rig's (E0–E2) and the synthetic-only E3.")
    azimuth_step_deg: float = Field(10.0, ge=1.0, le=360.0, description="Azimuth step (the paper: 10°).")
    size: int = Field(DEFAULT_SIZE, ge=16, le=2048, description="Image side in pixels (512: a HIL cube's).")


@router.post("/synthetic", status_code=202, response_model=m.SessionCreated,
             responses={429: {"model": m.ErrorBody, "description": "Too many renders wait."},
                        507: {"model": m.ErrorBody, "description": "Not enough free space for the views."},
                        **CONFLICT, **CROSS_SITE})
def create_synthetic(mg: Manager, response: Response, body: Annotated[SynthBody, Body()]) -> dict:
    """Render the synthetic domain of one build (an RGB render, ten band renders and the mask
    per pose) as a session of kind ``synthetic``; follow it at ``url`` and its ``events`` like a
    capture session. It needs no rig: it starts at once, beside a capture, one render at a time."""
    plan = SynthPlan(satellite=body.satellite, build=body.build, light=body.light,
                     elevations=tuple(body.tilts), azimuth_step_deg=body.azimuth_step_deg, size=body.size)
    job = jobs_of(mg).submit(plan)
    url = f"/sessions/{job.session_id}"  # relative: never built from the Host header
    response.headers["Location"] = url
    st = jobs_of(mg).status(job.session_id) or {}
    state = st.get("state", job.state)
    return {"session_id": job.session_id, "url": url, "state": state,
            "queue_position": st.get("queue_position") if state == "queued" else None,
            "planned_events": job.planned, "links": links(job.session_id)}


# ---------------------------------------------------------------- for the session routes
async def status_of(mg: SessionManager, session_id: str) -> dict[str, Any] | None:
    """The status of a synthetic session (live here, or from its journal); None for any other."""
    live = jobs_of(mg).status(session_id)
    if live is not None or mg.job(session_id) is not None:  # a capture session this daemon knows
        return live
    return await asyncio.to_thread(disk_status, mg.root, session_id)


def live_status(mg: SessionManager, session_id: str) -> dict[str, Any] | None:
    """The status of a synthetic session this daemon renders or rendered (no disk read)."""
    return jobs_of(mg).status(session_id)


def control_of(mg: SessionManager, session_id: str, action: str) -> dict[str, Any] | None:
    """pause / resume / abort of a synthetic session (daemon.synth_jobs); None for any other."""
    out = jobs_of(mg).control(session_id, action)
    if out is not None or mg.job(session_id) is not None:
        return out
    return control_stored(mg.root, session_id, action)


def events_of(mg: SessionManager, session_id: str, last_event_id: str | None
              ) -> AsyncIterator[dict[str, Any]] | None:
    """The event stream of a synthetic session this daemon knows; None otherwise (a journal
    replay, as for any session no engine here runs)."""
    svc = jobs_of(mg)
    if svc.job(session_id) is None:
        return None
    return _stream(mg, svc, session_id, last_event_id)


async def _stream(mg: SessionManager, svc: SynthJobs, session_id: str,
                  last_event_id: str | None) -> AsyncIterator[dict[str, Any]]:
    cursor = parse_last_event_id(last_event_id)
    last = cursor.seq if cursor is not None and cursor.run in (0, 1) else 0  # a render is run 1
    mg.metrics.sse_delta(+1)
    try:
        while True:
            evs, finished = svc.events_since(session_id, last)
            if evs:
                if evs[0][0] > last + 1:
                    yield _msg("gap", {"session_id": session_id, "first_missing": last + 1,
                                       "last_missing": evs[0][0] - 1, "run": 1})
                for seq, kind, data in evs:
                    yield _msg(kind, {**data, "run": 1}, f"1-{seq}")
                    last = seq
                continue
            if finished:
                return
            await asyncio.sleep(POLL_S)  # a client that leaves cancels this generator
    finally:
        mg.metrics.sse_delta(-1)
