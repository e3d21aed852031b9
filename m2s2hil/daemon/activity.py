"""The daemon's activity log: what happened on the rig, who did it and from where.

One bounded ring (the last :data:`CAPACITY` entries, in memory: the journals stay the record of
each session) of what an operator wants to open from the console's fault count: faults and
retries, sessions' state changes, their ends and failures, the queue's holds, and every
operator action that changed something (a jog, lamps, a session submitted, the emergency stop),
each with who sent it (the console tab's own id, ``X-M2S2HIL-Client``, when it sends one; whether
it carried the bearer token) and from where (client address, ``Origin``). Entries are numbered
(``seq``, from 1, never reused in a daemon's life), so a client polls ``since=<last seq>`` and
knows when the ring no longer reaches back that far (``gap``).

It also keeps the clients seen recently (:meth:`ActivityLog.clients`): which of them only watch
and which act, so a console can say "another client jogged the turntable 5 s ago".

No FastAPI here: the HTTP side (``api/routes/activity.py``) records requests into it, the
session manager the engines' events.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from m2s2hil.engine.state import EngineEvent, FaultRecorded, SessionFinished, StateChanged

CAPACITY = 1000
#: Clients forgotten after this long without a request.
CLIENT_TTL_S = 600.0

Kind = Literal["action", "fault", "retry", "state", "session", "queue", "daemon"]
Level = Literal["info", "warning", "error"]
#: Fault-policy actions that give up the frame, park or end the run; the others ("retry",
#: "reconnect", "home+retry", …) try again.
GIVE_UP_ACTIONS = frozenset({"skip", "suspend", "abort", "teardown"})


@dataclass(frozen=True)
class Actor:
    """Who sent a request and from where (as much as the request says)."""

    address: str | None = None
    client: str | None = None  # the client's own id (X-M2S2HIL-Client), when it sends one
    origin: str | None = None
    authenticated: bool = False  # it carried the daemon's bearer token
    user_agent: str | None = None

    @property
    def key(self) -> str:
        """One client: its own id when it sends one, else its address and user agent."""
        return self.client or f"{self.address or '?'} {self.user_agent or ''}".strip()


@dataclass(frozen=True)
class Activity:
    seq: int
    wall: float  # epoch seconds
    kind: Kind
    level: Level
    message: str
    session_id: str | None = None
    actor: Actor | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if self.actor is not None:
            d["actor"]["key"] = self.actor.key
        return d


@dataclass
class _Client:
    actor: Actor
    first_seen: float
    last_seen: float
    requests: int = 0
    last_action: str | None = None
    last_action_at: float | None = None


class ActivityLog:
    def __init__(self, capacity: int = CAPACITY) -> None:
        self._lock = threading.Lock()
        self._ring: deque[Activity] = deque(maxlen=capacity)
        self._seq = 0
        self._clients: dict[str, _Client] = {}

    # -- writing -------------------------------------------------------------------------
    def record(self, kind: Kind, message: str, *, level: Level = "info", session_id: str | None = None,
               actor: Actor | None = None, **details: Any) -> Activity:
        with self._lock:
            self._seq += 1
            entry = Activity(self._seq, time.time(), kind, level, message, session_id, actor, details)
            self._ring.append(entry)
            return entry

    def observe(self, session_id: str, ev: EngineEvent) -> None:
        """An engine's event (subscribed by the session manager): faults, retries, state changes and
        the session's end; frames and progress are not activity."""
        if isinstance(ev, FaultRecorded):
            f = ev.fault
            retry = f.action not in GIVE_UP_ACTIONS
            where = f" ({f.device})" if f.device else ""
            self.record("retry" if retry else "fault",
                        f"{f.fault_class} fault{where}: {f.message} → {f.action}"
                        + (f" (attempt {f.attempt})" if retry else ""),
                        level="warning" if retry or f.action == "skip" else "error", session_id=session_id,
                        fault_class=f.fault_class, action=f.action, attempt=f.attempt, device=f.device,
                        event_id=f.event_id)
        elif isinstance(ev, StateChanged):
            why = f" ({ev.reason})" if ev.reason else ""
            self.record("state", f"session {session_id}: {ev.old.value} → {ev.new.value}{why}",
                        session_id=session_id, old=ev.old.value, new=ev.new.value, reason=ev.reason)
        elif isinstance(ev, SessionFinished):
            st = ev.state.value
            level: Level = "error" if st == "failed" else "warning" if st != "completed" else "info"
            err = f": {ev.error}" if ev.error else ""
            self.record("session", f"session {session_id} {st}: {ev.done}/{ev.total} stored, "
                        f"{ev.skipped} skipped{err}", level=level, session_id=session_id, state=st,
                        done=ev.done, total=ev.total, skipped=ev.skipped, error=ev.error)

    def seen(self, actor: Actor, action: str | None = None) -> None:
        """A request from ``actor``; ``action`` when it changed something (e.g. ``POST /rig/stop``)."""
        now = time.time()
        with self._lock:
            c = self._clients.get(actor.key)
            if c is None:
                if len(self._clients) >= 256:  # bounded: forget the stalest first
                    self._forget_stale(now)
                    if len(self._clients) >= 256:
                        del self._clients[min(self._clients, key=lambda k: self._clients[k].last_seen)]
                c = self._clients[actor.key] = _Client(actor, now, now)
            c.actor, c.last_seen = actor, now
            c.requests += 1
            if action is not None:
                c.last_action, c.last_action_at = action, now

    def _forget_stale(self, now: float) -> None:
        for k in [k for k, c in self._clients.items() if now - c.last_seen > CLIENT_TTL_S]:
            del self._clients[k]

    # -- reading -------------------------------------------------------------------------
    @property
    def last_seq(self) -> int:
        return self._seq

    def since(self, seq: int = 0, *, limit: int = 200, kinds: set[str] | None = None,
              session_id: str | None = None) -> tuple[list[Activity], int, bool]:
        """Entries after ``seq`` (oldest first, at most ``limit``: the earliest ones, so a client
        paging misses none), the seq to ask from next time, and whether some after ``seq`` are gone."""
        with self._lock:
            items = [a for a in self._ring if a.seq > seq]
            newest = self._seq
        # gap: the ring no longer reaches back to seq, or seq is from before this daemon started
        gap = (bool(items) and items[0].seq > seq + 1) or seq > newest
        out: list[Activity] = []
        next_seq = newest
        for a in items:
            if (kinds is None or a.kind in kinds) and (session_id is None or a.session_id == session_id):
                if len(out) == limit:
                    next_seq = a.seq - 1  # the next page starts at this one
                    break
                out.append(a)
        return out, next_seq, gap

    def clients(self, me: Actor | None, *, window_s: float = 60.0) -> dict[str, Any]:
        """The clients seen within ``window_s``, and which of them acted within it; ``me`` (the
        asking client) is marked and not counted among the others."""
        now = time.time()
        with self._lock:
            self._forget_stale(now)
            rows = list(self._clients.values())
        mine = me.key if me is not None else None
        out = []
        for c in sorted(rows, key=lambda c: -c.last_seen):
            if now - c.last_seen > window_s:
                continue
            ago = None if c.last_action_at is None else round(now - c.last_action_at, 1)
            acted = ago is not None and ago <= window_s
            out.append({"key": c.actor.key, "you": c.actor.key == mine, "address": c.actor.address,
                        "client": c.actor.client, "origin": c.actor.origin,
                        "authenticated": c.actor.authenticated, "user_agent": c.actor.user_agent,
                        "last_seen_s": round(now - c.last_seen, 1), "requests": c.requests,
                        "controlling": acted, "last_action": c.last_action,
                        "last_action_s": ago})
        others = [r for r in out if not r["you"]]
        return {"window_s": window_s, "others_connected": len(others),
                "others_controlling": sum(1 for r in others if r["controlling"]), "clients": out}
