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

from m2s2hil.rig.live_view import LiveFrame

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
    """The live view: the newest frame whenever the viewer is ready for one. While a session owns
    the rig the stream carries a notice frame (``X-Live-Error``) instead, about four a second.
    A viewer counts while its connection lasts; beyond the daemon's limit, 503 with Retry-After."""
    streams = streams_of(request)
    if not streams.live.acquire():
        return streams.busy(streams.live)

    async def parts() -> AsyncIterator[bytes]:
        frames = console.live.aframes(max_frames=max_frames)
        try:
            async for item in frames:
                if isinstance(item, str):
                    yield _part(_notice_jpeg(item), {"X-Live-Error": json.dumps(item)})
                else:
                    yield _frame_part(item)
        finally:
            await frames.aclose()  # the viewer leaves the count now, not when collected

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
    return {"settings": {"exposure_s": s.exposure_s, "gain": s.gain, "view": s.view, "axis_x": s.axis_x},
            "viewers": console.live.viewers, "frames_produced": console.live.frames_produced,
            "error": console.live.error, "stats": snap.stats if snap is not None else None,
            "bands_nm": list(console.manager.rig.config.camera.model.bands_nm)}


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
