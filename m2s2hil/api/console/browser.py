"""The session browser's endpoints: a session's QC report, its integrity check and its export.

None of them changes the session: the report is rendered for the response (nothing is written
into the session folder), the check only reads, and an export is written under
``<data root>/exports/<session>/<layout>/``.
"""

from __future__ import annotations

from typing import Any, Literal

from fastapi import APIRouter
from fastapi.responses import HTMLResponse, Response
from pydantic import BaseModel, ConfigDict

from m2s2hil.daemon.errors import Conflict

from ..common import CONFLICT, CROSS_SITE, NOT_FOUND, Manager, SessionId

router = APIRouter(tags=["session browser"])

REPORT_HEADERS = {
    # The report is one self-contained page: inline style, inline (data:) images, no script.
    "Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'; img-src data:; "
                               "frame-ancestors 'self'",
    "X-Content-Type-Options": "nosniff",
}


class ExportIn(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    layout: Literal["m2s2", "hf", "zarr"] = "m2s2"
    overwrite: bool = False


@router.get("/sessions/{session_id}/report.html", response_class=Response,
            responses={200: {"content": {"text/html": {}}}, **NOT_FOUND, **CONFLICT})
def session_report(mg: Manager, session_id: SessionId) -> HTMLResponse:
    """The session's QC report and contact sheet (HTML, self-contained), rendered for this request."""
    from m2s2hil.analysis.report.session_html import collect_views, render

    with mg.reads.reading(session_id) as store:
        views, summary = collect_views(store, thumb_px=160, compute_missing=True)
        page = render(store, views, summary)
    return HTMLResponse(page, headers=REPORT_HEADERS)


@router.get("/sessions/{session_id}/verify", responses={**NOT_FOUND, **CONFLICT})
def verify_session(mg: Manager, session_id: SessionId) -> dict[str, Any]:
    """Recompute every stored file's sha256 against the journal and the manifest."""
    with mg.reads.reading(session_id) as store:
        problems = store.verify()
        frames = len(store.frames())
    return {"session_id": session_id, "ok": not problems, "frames": frames,
            "problems": [str(p) for p in problems]}


@router.post("/sessions/{session_id}/export", status_code=201,
             responses={**NOT_FOUND, **CONFLICT, **CROSS_SITE})
def export(mg: Manager, session_id: SessionId, body: ExportIn) -> dict[str, Any]:
    """Export the session's frames (``m2s2``: the published layout; ``hf``: a Hugging Face dataset
    with the exact raw values; ``zarr``: a chunked store xarray opens lazily) under
    ``<data root>/exports/<session>/<layout>/``: written beside it and renamed into place when
    complete; while one export of the session and layout runs, another gets 409. A session
    without a frame yet, or one already exported (without ``overwrite``), is 409 too: the
    request is valid, the session's state does not allow it."""
    from m2s2hil.daemon.export_lock import ExportBusy, export_once
    from m2s2hil.store.export import ExportError

    out = mg.root / "exports" / session_id / body.layout
    try:
        with mg.reads.reading(session_id) as store:
            if not store.frames():
                raise Conflict(f"session {session_id} has no frames to export yet")
            # The folder is this session's alone: overwrite starts it afresh.
            result = export_once(store, out, body.layout, overwrite=body.overwrite, fresh=body.overwrite)
    except ExportBusy as exc:
        raise Conflict(str(exc)) from None
    except ExportError as exc:
        if out.exists() and not body.overwrite:
            raise Conflict(str(exc)) from None
        raise
    return {"session_id": session_id, "layout": body.layout, "folder": str(out), "images": result.images,
            "files": len(result.files)}
