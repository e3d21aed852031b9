"""Request and response bodies of the REST API (the POST body itself is :class:`m2s2hil.plan.Sweep`)."""

from __future__ import annotations

from typing import Any, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

from m2s2hil.store.layout import SESSION_ID_RE

SESSION_ID_PATTERN = SESSION_ID_RE.pattern

#: Every state a session can be reported in. Engine states, plus ``queued`` (waiting for
#: the rig), ``cancelled`` (left the queue before running), ``created`` (accepted, not yet
#: queued), ``interrupted`` (parked by a daemon shutdown), ``corrupt`` (unreadable journal),
#: ``completed_with_gaps`` (ran to the end, some planned frames skipped and recorded),
#: ``estopped`` (ended by the emergency stop; resumable once the stop is cleared), ``damaged``
#: (the journal failed its integrity check; ``m2s2hil sessions repair``).
SessionState = Literal[
    "created", "queued", "idle", "running", "pausing", "paused", "aborting", "completed", "failed",
    "aborted", "cancelled", "interrupted", "corrupt", "completed_with_gaps", "estopped", "damaged",
]
_STATE_DOC = "One of: " + ", ".join(get_args(SessionState)) + " (see docs/api.md)."


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorBody(_Out):
    detail: str = Field(description="What was wrong with the request, and where.")
    errors: list[dict[str, Any]] | None = Field(default=None, description="Each validation problem.")


class Links(_Out):
    self: str
    events: str
    frames: str


class FaultOut(_Out):
    time_s: float
    fault_class: str
    action: str
    message: str
    event_id: str | None = None
    attempt: int = 1
    device: str | None = None


class SessionStatus(_Out):
    session_id: str
    state: str = Field(description=_STATE_DOC)
    live: bool = Field(description="The session is known to this daemon process (queued, running or "
                                   "finished since it started); otherwise read from the journal.")
    queue_position: int | None = Field(default=None, description="1 = next to run; null when not queued.")
    resumable: bool = Field(default=False, description="Interrupted: POST …/resume queues it again.")
    satellite: str | None = None
    build: str | None = None
    mode: str | None = None
    done: int = 0
    total: int = Field(0, description="Captures planned: lit frames and master darks (see planned_frames).")
    planned_frames: int | None = Field(None, description="Of `total`, the lit frames (what the estimate and "
                                                         "the frame list count).")
    planned_darks: int | None = Field(None, description="Of `total`, the master darks.")
    skipped: int = 0
    progress: float = 0.0
    eta_s: float | None = None
    elapsed_s: float | None = None
    lighting: str | None = None
    elevation: str | None = None
    tilt_deg: float | None = None
    azimuth_deg: float | None = None
    lamps_on: list[int] = Field(default_factory=list)
    last_frame_index: int | None = None
    last_event_id: str | None = None
    faults: list[FaultOut] = Field(default_factory=list)
    fault_count: int = Field(0, description="Every fault met (``faults`` lists the last 50).")
    pause_reason: str | None = None
    error: str | None = None
    efficiency: float | None = None
    created: float | None = None
    updated: float | None = None
    links: Links


class SessionCreated(_Out):
    session_id: str
    url: str
    state: str = Field(description=_STATE_DOC)
    queue_position: int | None = None
    planned_events: int
    links: Links


class SessionPage(_Out):
    items: list[SessionStatus]
    total: int
    offset: int
    limit: int


class FileOut(_Out):
    path: str = Field(description="Relative to the session folder.")
    sha256: str
    bytes: int


class FrameOut(_Out):
    n: int = Field(description="The frame's index in the expanded plan (the {n} of the frame URLs).")
    event_id: str
    time: float
    dark_id: str | None
    files: dict[str, FileOut]
    meta: dict[str, Any]
    preview_url: str | None
    raw_url: str


class FramePage(_Out):
    items: list[FrameOut]
    total: int
    offset: int
    limit: int


class QueueEntry(_Out):
    session_id: str
    position: int
    resume: bool
    queued_at: float


class QueueState(_Out):
    running: str | None
    held: str | None = Field(description="Why the queue is held (no session starts until released).")
    limit: int
    items: list[QueueEntry]
    rig: Literal["running", "starting", "held", "queued", "idle"] = Field(
        "idle", description="What the rig does, for display: a session running; one starting (taken from "
                            "the queue, its engine not yet started); held; sessions waiting; idle.")
    starting: str | None = Field(None, description="The session being started, if any.")


class DeviceState(_Out):
    name: str
    kind: Literal["motion", "relay", "camera"]
    protocol: str
    port: str
    health: Literal["ok", "error", "busy"] = Field(
        description="busy: a session owns the device; state is the engine's last read-back.")
    state: dict[str, Any]
    error: str | None = None
    recent_faults: int = 0


class RigState(_Out):
    name: str
    simulated: bool
    digest: str
    session_id: str | None = Field(description="The session that owns the rig, if any.")
    held: str | None
    devices: list[DeviceState]


class StopReport(_Out):
    safe: bool = Field(description="Lamps read back off and no axis reports motion.")
    lamps_on: list[int]
    moving: dict[str, bool]
    session_id: str | None = Field(description="The session aborted by the stop, if one was running.")
    session_state: str | None
    held: str = Field(description="The queue is held until POST /queue/release.")
    errors: list[str]
    elapsed_s: float


class Health(_Out):
    status: Literal["ok", "degraded"]
    version: str
    rig: str
    simulated: bool
    data_root_writable: bool
    running: str | None
    queued: int
    held: str | None
    uptime_s: float




class ActivityActor(_Out):
    key: str = Field(description="One client: its X-M2S2HIL-Client id, else its address and user agent.")
    address: str | None
    client: str | None = Field(description="The X-M2S2HIL-Client header it sent, if any.")
    origin: str | None
    authenticated: bool = Field(description="It carried the daemon's bearer token.")
    user_agent: str | None


class ActivityEntry(_Out):
    seq: int
    wall: float = Field(description="Epoch seconds.")
    kind: Literal["action", "fault", "retry", "state", "session", "queue", "daemon"]
    level: Literal["info", "warning", "error"]
    message: str
    session_id: str | None
    actor: ActivityActor | None = Field(description="Who sent the request (operator actions only).")
    details: dict[str, Any]


class ActivityPage(_Out):
    items: list[ActivityEntry]
    last_seq: int = Field(description="Pass as ?since= next time.")
    newest_seq: int
    gap: bool = Field(description="Entries after `since` are no longer kept (the ring holds the last 1000).")


class ActivityClient(_Out):
    key: str
    you: bool = Field(description="The client asking.")
    address: str | None
    client: str | None
    origin: str | None
    authenticated: bool
    user_agent: str | None
    last_seen_s: float
    requests: int
    controlling: bool = Field(description="It changed something within the window.")
    last_action: str | None = Field(description="Its last state change, e.g. 'POST /rig/axes/turntable/jog'.")
    last_action_s: float | None


class ActivityClients(_Out):
    window_s: float
    others_connected: int
    others_controlling: int
    clients: list[ActivityClient]


class ExportJobOut(_Out):
    job_id: str
    session_id: str
    layout: Literal["m2s2", "hf", "zarr"]
    state: Literal["running", "done", "failed"]
    phase: Literal["starting", "exporting", "done", "failed"]
    started: float
    finished: float | None
    elapsed_s: float
    frames: int | None = Field(description="Frames the session had when the export started.")
    done: int = Field(0, description="Frames exported so far (updated at most every 0.5 s).")
    total: int | None = Field(None, description="Frames the export writes (as ``frames``).")
    fraction: float = Field(0.0, description="done / total, 0–1 (1 once done).")
    result: dict[str, Any] | None = Field(description="folder, images, files, once done.")
    error: str | None
    url: str
    download_url: str | None = Field(description="The export as a zip, once done.")


class ExportJobs(_Out):
    items: list[ExportJobOut]


class BusyItem(_Out):
    key: str = Field(description="snapshot, darks, white, phase, or export:<session>:<layout>.")
    what: str
    since_s: float
    started: float
    detail: dict[str, Any]


class BusyOut(_Out):
    items: list[BusyItem]


class ExportJobIn(BaseModel):
    # strict: "true" or 1 for a boolean is refused, as the schema says
    model_config = ConfigDict(extra="forbid", strict=True)
    layout: Literal["m2s2", "hf", "zarr"] = "m2s2"
    overwrite: bool = Field(False, description="Replace an earlier export of this session and layout.")
