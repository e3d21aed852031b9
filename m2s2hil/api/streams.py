"""Long-lived responses (the live view's MJPEG, the sessions' SSE) counted by their connections.

A stream holds a slot from the moment it is accepted until its connection is gone, whatever
ends it: the client disconnects (or half-closes its socket, which the server reads as the
same), the stream ends, or the client stops reading and one send waits longer than
``send_timeout_s`` (a stalled or vanished peer whose TCP window is full). Each limit comes from
the daemon's settings (:class:`StreamLimits`); a client beyond it gets 503 with
``Retry-After`` at once instead of a connection that never sends a byte.

Why not Starlette's ``StreamingResponse`` over a plain generator: a sync generator runs in the
thread pool (40 threads, shared with every plain ``def`` endpoint), so 40 viewers starve the
whole API and a disconnect leaves the generator, and its viewer count, to the garbage
collector. Here the body is an async iterator, waited for without a thread, and closed
explicitly when the connection goes.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import anyio
from fastapi import Request
from fastapi.responses import Response
from sse_starlette import EventSourceResponse
from sse_starlette.sse import SendTimeoutError
from starlette.types import Receive, Scope, Send

from . import models as m
from .common import Responses, error_response

log = logging.getLogger("m2s2hil.api.streams")


@dataclass(frozen=True)
class StreamLimits:
    """How many streams of each kind the daemon serves at once, and how long one send may wait."""

    live_viewers: int = 64
    sse_subscribers: int = 512
    send_timeout_s: float = 15.0
    retry_after_s: int = 5


class Slots:
    """A counted limit (thread-safe: ``/camera/live`` reads it from the thread pool)."""

    def __init__(self, what: str, limit: int) -> None:
        self.what = what
        self.limit = limit
        self._count = 0
        self._lock = threading.Lock()

    @property
    def count(self) -> int:
        return self._count

    def acquire(self) -> bool:
        with self._lock:
            if self._count >= self.limit:
                return False
            self._count += 1
            return True

    def release(self) -> None:
        with self._lock:
            self._count = max(0, self._count - 1)


class Streams:
    """The application's stream slots (``app.state.streams``)."""

    def __init__(self, limits: StreamLimits | None = None) -> None:
        self.limits = limits or StreamLimits()
        self.live = Slots("live-view viewers", self.limits.live_viewers)
        self.sse = Slots("event-stream subscribers", self.limits.sse_subscribers)

    def busy(self, slots: Slots) -> Response:
        """503 for a stream beyond its limit."""
        return error_response(503, f"this daemon already serves {slots.limit} {slots.what} (its limit); "
                                   f"try again in {self.limits.retry_after_s} s",
                              headers={"Retry-After": str(self.limits.retry_after_s)})


#: The 503 a stream endpoint documents.
BUSY: Responses = {503: {"model": m.ErrorBody,
                         "description": "The daemon already serves as many streams of this kind as it is "
                                        "configured to; Retry-After says when to try again.",
                         "headers": {"Retry-After": {"schema": {"type": "integer"},
                                                     "description": "Seconds to wait."}}}}


def streams_of(request: Request) -> Streams:
    streams = getattr(request.app.state, "streams", None)
    if streams is None:  # an application made without create_app's limits
        streams = request.app.state.streams = Streams()
    return streams


async def _close(body: Any) -> None:
    aclose = getattr(body, "aclose", None)
    if aclose is not None:
        with contextlib.suppress(RuntimeError):  # already closing: it ends by itself
            await aclose()


class ConnectionStream(Response):
    """Chunks of ``body`` for as long as the connection lasts; ``slot`` is released when it goes
    (the caller acquired it)."""

    def __init__(self, body: AsyncIterator[bytes], slot: Slots, *, send_timeout_s: float, media_type: str,
                 headers: dict[str, str] | None = None) -> None:
        self.body_iterator = body
        self.slot = slot
        self.send_timeout_s = send_timeout_s
        self.status_code = 200
        self.media_type = media_type
        self.background = None
        self.init_headers(headers)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._until_disconnect, receive, tg.cancel_scope)
                try:
                    await self._stream(send)
                except TimeoutError:  # the server closes a connection whose response did not end
                    log.info("dropped one of the %s: it stopped reading", self.slot.what)
                tg.cancel_scope.cancel()
        finally:
            await _close(self.body_iterator)
            self.slot.release()

    async def _stream(self, send: Send) -> None:
        with anyio.fail_after(self.send_timeout_s):
            await send({"type": "http.response.start", "status": self.status_code,
                        "headers": self.raw_headers})
        async for chunk in self.body_iterator:
            with anyio.fail_after(self.send_timeout_s):
                await send({"type": "http.response.body", "body": chunk, "more_body": True})
        with anyio.fail_after(self.send_timeout_s):
            await send({"type": "http.response.body", "body": b"", "more_body": False})

    @staticmethod
    async def _until_disconnect(receive: Receive, scope: anyio.CancelScope) -> None:
        while (await receive())["type"] != "http.disconnect":
            pass
        scope.cancel()


class SlotEventSource(EventSourceResponse):
    """Server-Sent Events holding ``slot`` until the connection goes (sse-starlette watches for the
    disconnect and drops a client whose send takes longer than ``send_timeout``)."""

    def __init__(self, slot: Slots, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.slot = slot

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        except SendTimeoutError:
            log.info("dropped one of the %s: it stopped reading", self.slot.what)
        except BaseExceptionGroup as group:
            rest = group.subgroup(lambda e: not isinstance(e, SendTimeoutError))
            if rest is not None:
                raise rest from None
            log.info("dropped one of the %s: it stopped reading", self.slot.what)
        finally:
            await _close(self.body_iterator)
            self.slot.release()
