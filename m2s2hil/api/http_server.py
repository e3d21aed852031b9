"""The HTTP server's own limits: how long a client may take to send its request headers, how long
an idle keep-alive connection stays open, how large the headers may be, how many connections
at once.

uvicorn has a keep-alive timeout but none for the request headers: a client that sends one
header byte every few seconds (slowloris) holds its connection, and its file descriptor, for
ever, and any byte cancels the keep-alive timer. :class:`HeaderDeadlineProtocol` (uvicorn's h11
protocol with one timer more) gives every request a deadline for its complete headers,
counted from when the connection opens or the previous response ended; bytes that trickle in
do not extend it. A client past it gets ``408 Request Timeout`` and the connection closes.

The close is staged (RFC 9112 section 9.6): the server shuts its sending side, then reads and
drops whatever the client still sends for a short linger before closing. Closing at once while
the client is still sending makes the kernel answer with a reset, and a reset can discard the
408 before the client has read it.
"""

from __future__ import annotations

import asyncio
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol

_TIMEOUT_408 = b"HTTP/1.1 408 Request Timeout\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
_LINGER_S = 2.0  # how long a timed-out client's late bytes are read and dropped before the close


class HeaderDeadlineProtocol(H11Protocol):
    """h11 with a deadline for each request's headers (see the module docstring)."""

    header_timeout_s: float = 10.0
    _deadline: asyncio.TimerHandle | None = None
    _cycle_seen: object = None
    _lingering: bool = False

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._lingering:
            return  # after the 408: read so the kernel sends no reset, and drop
        super().data_received(data)

    def handle_events(self) -> None:
        super().handle_events()
        if self.cycle is not None and self.cycle is not self._cycle_seen:  # a request's headers are in
            self._cycle_seen = self.cycle
            self._disarm()

    def on_response_complete(self) -> None:
        self._arm()  # before the next request (a pipelined one, parsed below, disarms it again)
        super().on_response_complete()

    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.header_timeout_s, self._headers_late)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _headers_late(self) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        self.transport.write(_TIMEOUT_408)
        if not self.transport.can_write_eof():
            self.transport.close()
            return
        self._lingering = True
        self.transport.write_eof()
        self._deadline = self.loop.call_later(_LINGER_S, self.transport.close)


def protocol_with_header_timeout(seconds: float) -> type[HeaderDeadlineProtocol]:
    return type("HeaderDeadlineProtocol", (HeaderDeadlineProtocol,), {"header_timeout_s": seconds})


def server_limits(*, header_timeout_s: float, keep_alive_s: float, max_header_bytes: int,
                  max_connections: int) -> dict[str, Any]:
    """``uvicorn.Config`` keyword arguments for these limits (beyond ``max_connections`` uvicorn
    answers 503 itself)."""
    return {"http": protocol_with_header_timeout(header_timeout_s), "timeout_keep_alive": keep_alive_s,
            "h11_max_incomplete_event_size": max_header_bytes, "limit_concurrency": max_connections}
