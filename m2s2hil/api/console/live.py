"""Live view: an MJPEG stream of the camera while no session owns the rig, its settings and the
newest frame's statistics.

Why MJPEG (``multipart/x-mixed-replace``) and not a WebSocket: every browser shows it in a plain
``<img>``, curl, ffmpeg and VLC record it, it needs no extra server dependency, it passes the
daemon's HTTP security (Host allow-list, token, no state change on GET) unchanged, and a
frame's statistics travel with it as a part header (``X-Live-Stats``, JSON), which the console
reads by consuming the stream with ``fetch`` (so the bearer token works too). Its one cost, no
way back up the same connection, does not matter: settings go up with ``PUT /camera/live``.
"""

from __future__ import annotations

import functools
import json
from collections.abc import AsyncIterator
from typing import Annotated

import cv2
import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from m2s2hil.rig.live_view import LiveFrame, LiveNotice

from ..common import CROSS_SITE
from ..streams import BUSY, ConnectionStream, streams_of
from . import models as cm
from .state import ConsoleDep

router = APIRouter(tags=["live view"])
BOUNDARY = "m2s2hil-frame"


@functools.lru_cache(maxsize=16)  # the same notice goes to every viewer, four times a second
def _notice_jpeg(text: str) -> bytes:
    img = np.full((120, 640, 3), 48, np.uint8)
    for i, line in enumerate([text[k: k + 70] for k in range(0, min(len(text), 280), 70)]):
        cv2.putText(img, line, (10, 28 + 26 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1,
                    cv2.LINE_AA)
    ok, buf = cv2.imencode(".jpg", img)
    return buf.tobytes() if ok else b""


def _notice_part(state: str, reason: str, extra: dict[str, str] | None = None) -> bytes:
    """A part without a frame: the reason drawn as a JPEG, and in its headers (JSON, ASCII)."""
    return _part(_notice_jpeg(reason), {"X-Live-Status": json.dumps({"state": state, "reason": reason}),
                                        "X-Live-Error": json.dumps(reason), **(extra or {})})


def _part(jpeg: bytes, headers: dict[str, str]) -> bytes:
    head = "".join(f"{k}: {v}\r\n" for k, v in headers.items())
    return (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n{head}\r\n"
            ).encode("ascii") + jpeg + b"\r\n"


@router.get("/camera/live.mjpeg", response_class=Response,
            responses={200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}},
                             "description": "JPEG frames; each part has an X-Live-Stats header (JSON)."},
                       **BUSY})
async def live_stream(
    request: Request,
    console: ConsoleDep,
    max_frames: Annotated[int | None, Query(ge=1, le=1_000_000,
                                            description="End after this many frames.")] = None,
) -> Response:
    """The live view: the newest frame whenever the viewer is ready for one. Instead of a frame, a
    notice part (a JPEG of the text, ``X-Live-Status``: ``{"state", "reason"}``, and the reason
    alone as ``X-Live-Error``): ``busy`` while a session owns the rig and ``error`` on a device
    error (about four a second, retried), ``waiting`` every 2 s without a frame (a cold start:
    the stream waits for the camera; after 60 s with neither a frame nor a busy notice, nothing or
    only errors, it ends, saying so).
    The stream's last part says why it ended (``X-Live-End``: ``{"reason", "frames"}``). A viewer
    counts while its connection lasts; beyond the daemon's limit, 503 with Retry-After."""
    streams = streams_of(request)
    if not streams.live.acquire():
        return streams.busy(streams.live)

    async def parts() -> AsyncIterator[bytes]:
        frames = console.live.aframes(max_frames=max_frames)
        sent = 0
        gave_up: str | None = None
        try:
            async for item in frames:
                if isinstance(item, LiveNotice) and item.state == "ended":
                    gave_up = item.reason
                elif isinstance(item, LiveNotice):
                    yield _notice_part(item.state, item.reason)
                else:
                    sent += 1
                    yield _frame_part(item)
        finally:
            await frames.aclose()  # the viewer leaves the count now, not when collected
        if gave_up is not None:
            reason = gave_up
        elif max_frames is not None and sent >= max_frames:
            reason = f"max_frames: the {sent} frame(s) asked for were sent"
        else:
            reason = console.live.stopped_reason or "the live view stopped"
        yield _notice_part("ended", reason, {"X-Live-End": json.dumps({"reason": reason, "frames": sent})})

    return ConnectionStream(parts(), streams.live, send_timeout_s=streams.limits.send_timeout_s,
                            media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                            headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


_last_part: tuple[LiveFrame, bytes] | None = None


def _frame_part(frame: LiveFrame) -> bytes:
    """A frame's part, encoded once for all the viewers that get it."""
    global _last_part
    last = _last_part
    if last is not None and last[0] is frame:
        return last[1]
    part = _part(frame.jpeg, {"X-Live-Stats": json.dumps(frame.stats, separators=(",", ":"))})
    _last_part = (frame, part)
    return part


def _live_out(console: ConsoleDep) -> dict:
    snap = console.live.snapshot()
    s = console.live.settings
    return {"settings": {"exposure_s": round(s.exposure_s, 9), "gain": s.gain, "view": s.view,
                         "axis_x": s.axis_x},
            "viewers": console.live.viewers, "frames_produced": console.live.frames_produced,
            "error": console.live.error, "stats": snap.stats if snap is not None else None,
            "state": console.live.state, "stopped_reason": console.live.stopped_reason,
            "stream_fps": console.camera.stream_fps(s), "fps": _round(console.live.fps, 2),
            "cold_start_s": _round(console.live.cold_start_s, 3),
            "bands_nm": list(console.manager.rig.config.camera.model.bands_nm)}


def _round(x: float | None, nd: int) -> float | None:
    return None if x is None else round(x, nd)


@router.get("/camera/live", response_model=cm.LiveOut)
def live_settings(console: ConsoleDep) -> dict:
    """The live view's settings and the newest frame's statistics (histogram, saturation, focus)."""
    return _live_out(console)


@router.put("/camera/live", response_model=cm.LiveOut, responses=CROSS_SITE)
def update_live(console: ConsoleDep, body: cm.LiveSettingsIn) -> dict:
    """Change exposure, gain, the view (``"rgb"`` or a band index) or the axis overlay; the next
    frame uses them."""
    n_bands = console.manager.rig.config.camera.model.n_bands
    if isinstance(body.view, int) and body.view >= n_bands:
        from m2s2hil.errors import UsageError

        raise UsageError(f"body.view: band {body.view} does not exist (0..{n_bands - 1})")
    console.live.update(**body.model_dump(exclude_none=True))
    return _live_out(console)
