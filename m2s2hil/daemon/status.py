"""A session's status snapshot (the body of ``GET /sessions/{id}``): from its engine while it
runs, from its queue entry while it waits, from its journal otherwise."""

from __future__ import annotations

from pathlib import Path

from m2s2hil.drivers.clock import Clock
from m2s2hil.engine.runner import Engine
from m2s2hil.store.errors import SessionCorrupt

from .jobqueue import Job
from .listing import PlannedCounts, open_store

#: Journal states of a session that was accepted or running when its daemon went away.
RESUMABLE = frozenset({"created", "queued", "running", "pausing", "interrupted"})
#: … and those an operator may resume by hand (a paused session is not resumed automatically).
RESUMABLE_BY_HAND = RESUMABLE | {"paused", "estopped", "completed_with_gaps"}
TERMINAL = frozenset({"completed", "failed", "aborted", "cancelled"})

_FROM_ENGINE = ("done", "total", "skipped", "progress", "eta_s", "elapsed_s", "lighting", "elevation",
                "tilt_deg", "azimuth_deg", "last_frame_index", "last_event_id", "pause_reason", "error",
                "efficiency", "mode")


def engine_status(job: Job, engine: Engine) -> dict:
    """The status of a job from its engine (running, or finished in this daemon)."""
    st = engine.status().to_dict()
    out = {k: st[k] for k in _FROM_ENGINE}
    state = job.live_state() or st["state"]
    out.update(session_id=job.session_id, state=state, live=True, queue_position=None,
               lamps_on=list(st["lamps_on"]), faults=list(st["faults"])[-50:], fault_count=st["fault_count"],
               satellite=job.store.sweep.satellite, build=job.store.sweep.build,
               created=job.store.created, resumable=state == "estopped")
    return out


def queued_status(job: Job, position: int | None) -> dict:
    """The status of a job without an engine: queued, or cancelled before it ran."""
    done = len(job.store.completed_event_ids())
    return {
        "session_id": job.session_id, "state": job.final_state or "queued",
        "live": True, "queue_position": position, "resumable": False, "satellite": job.store.sweep.satellite,
        "build": job.store.sweep.build, "mode": job.store.sweep.mode, "done": done, "total": job.planned,
        "progress": done / job.planned if job.planned else 1.0, "created": job.store.created,
        "error": job.error,
    }


def disk_status(root: Path, session_id: str, clock: Clock, planned: PlannedCounts) -> dict:
    """The status of a session no engine of this daemon knows, from its journal."""
    try:
        store = open_store(root, session_id, clock)
    except SessionCorrupt as exc:
        return {"session_id": session_id, "state": "corrupt", "live": False, "error": str(exc)}
    try:
        row = store.journal.session()
        n_planned = planned.of(store)
        done = len(store.completed_event_ids())
        skipped = len(store.skipped_event_ids())
        faults: list[dict] = []
        error = None
        last_finish: dict = {}
        for e in store.events():
            p = e.get("payload") or {}
            if e["kind"] == "fault":
                faults.append({"time_s": float(p.get("clock_s") or 0.0),
                               "fault_class": str(p.get("fault_class", "other")),
                               "action": str(p.get("action", "")), "message": str(p.get("message", "")),
                               "event_id": p.get("event_id"), "attempt": int(p.get("attempt") or 1),
                               "device": p.get("device")})
            elif e["kind"] == "run_finished":
                last_finish = p
                error = p.get("error")
        state = row["state"]
        return {
            "session_id": session_id, "state": state, "live": False, "queue_position": None,
            "resumable": state in RESUMABLE_BY_HAND, "satellite": store.sweep.satellite,
            "build": store.sweep.build, "mode": store.sweep.mode, "done": done, "total": n_planned,
            "skipped": skipped, "progress": (done + skipped) / n_planned if n_planned else 1.0,
            "elapsed_s": last_finish.get("duration_s"), "efficiency": last_finish.get("efficiency"),
            "faults": faults[-50:], "fault_count": len(faults), "error": error, "created": row["created"],
            "updated": row["updated"],
            "eta_s": 0.0 if state == "completed" else None,
        }
    finally:
        store.close()
