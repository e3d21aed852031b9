"""A session's stored frames: the list, each frame's preview and its raw mosaic."""

from __future__ import annotations

from fastapi import APIRouter, Response

from m2s2hil.store.frame_files import decode_image, encode_png, image_media_type

from .. import models as m
from ..common import CONFLICT, NOT_FOUND, FrameN, Limit, Manager, Offset, SessionId

router = APIRouter(tags=["frames"])


@router.get("/sessions/{session_id}/frames", response_model=m.FramePage, responses={**NOT_FOUND, **CONFLICT})
def list_frames(mg: Manager, session_id: SessionId, offset: Offset = 0, limit: Limit = 50) -> dict:
    """Stored frames in plan order, with their files (sha256) and metadata."""
    recs, total = mg.reads.frames(session_id, offset=offset, limit=limit)
    items = []
    for r in recs:
        base = f"/sessions/{session_id}/frames/{r.index}"
        items.append({"n": r.index, "event_id": r.event_id, "time": r.time, "dark_id": r.dark_id,
                      "files": {k: f.model_dump() for k, f in r.files.items()}, "meta": r.meta,
                      "preview_url": f"{base}/preview" if "preview" in r.files else None,
                      "raw_url": f"{base}/raw"})
    return {"items": items, "total": total, "offset": offset, "limit": limit}


@router.get("/sessions/{session_id}/frames/{n}/preview", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}, "image/png": {}},
                             "description": "8-bit RGB preview as stored: JPEG, or PNG in legacy sessions."},
                       **NOT_FOUND, **CONFLICT})
def frame_preview(mg: Manager, session_id: SessionId, n: FrameN) -> Response:
    """The frame's RGB preview (bands nearest 640/550/470 nm), the stored file checked against its sha256."""
    data, path = mg.reads.frame_file(session_id, n, "preview")
    return Response(data, media_type=image_media_type(path), headers={"Cache-Control": "max-age=3600"})


@router.get("/sessions/{session_id}/frames/{n}/preview.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "8-bit RGB preview as PNG."},
                       **NOT_FOUND, **CONFLICT})
def frame_preview_png(mg: Manager, session_id: SessionId, n: FrameN) -> Response:
    """The frame's RGB preview as PNG, for clients that expect one (a JPEG preview is converted)."""
    data, path = mg.reads.frame_file(session_id, n, "preview")
    if image_media_type(path) != "image/png":
        data = encode_png(decode_image(data))
    return Response(data, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


@router.get("/sessions/{session_id}/frames/{n}/raw", response_class=Response,
            responses={200: {"content": {"image/tiff": {}}, "description": "Raw mosaic, uint16 TIFF."},
                       **NOT_FOUND, **CONFLICT})
def frame_raw(mg: Manager, session_id: SessionId, n: FrameN) -> Response:
    """The stored raw mosaic TIFF (metadata JSON in its ImageDescription), checked against its sha256."""
    data, _ = mg.reads.frame_file(session_id, n, "raw")
    return Response(data, media_type="image/tiff",
                    headers={"Content-Disposition": f'attachment; filename="{session_id}-{n}.raw.tiff"'})
