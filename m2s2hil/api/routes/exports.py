"""Exports as jobs with their progress, and an exported folder as a download (a zip).

``POST /sessions/{id}/export/jobs`` answers at once (202) with the job; ``GET
/exports/jobs/{job_id}`` follows it (phase, elapsed time, result or error) until it is ``done``,
when its ``download_url`` streams ``GET /sessions/{id}/export/{layout}.zip`` (the folder under
``<data root>/exports/<id>/<layout>/``, as an attachment). The synchronous ``POST
/sessions/{id}/export`` stays for scripts.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Path
from fastapi.responses import Response, StreamingResponse

from m2s2hil.daemon.export_jobs import zip_chunks

from ..common import CONFLICT, CROSS_SITE, NOT_FOUND, Manager, SessionId
from ..models import ExportJobIn, ExportJobOut, ExportJobs

router = APIRouter(tags=["session browser"])
JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{12}$", description="As returned by POST …/export/jobs.")]
Layout = Literal["m2s2", "hf", "zarr"]


@router.post("/sessions/{session_id}/export/jobs", status_code=202, response_model=ExportJobOut,
             responses={**NOT_FOUND, **CONFLICT, **CROSS_SITE})
def start_export(mg: Manager, session_id: SessionId, body: ExportJobIn) -> dict:
    """Start exporting the session (``layout``: m2s2, hf or zarr) in the background; 409 while an
    export of the same session and layout runs, or when the session has no frame yet."""
    return mg.exports.start(session_id, body.layout, overwrite=body.overwrite).to_dict()


@router.get("/exports/jobs", response_model=ExportJobs)
def list_exports(mg: Manager) -> dict:
    """This daemon's recent export jobs, newest first (the last 32)."""
    return {"items": mg.exports.items()}


@router.get("/exports/jobs/{job_id}", response_model=ExportJobOut, responses=NOT_FOUND)
def get_export(mg: Manager, job_id: JobId) -> dict:
    """An export job: ``state`` running, done or failed; ``phase``; ``elapsed_s``; ``result`` (folder,
    images, files) or ``error``; ``download_url`` once done."""
    job = mg.exports.get(job_id)
    if job is None:
        raise HTTPException(404, f"no export job {job_id} (this daemon keeps the last 32)")
    return job.to_dict()


@router.get("/sessions/{session_id}/export/{layout}.zip", response_class=Response,
            responses={200: {"content": {"application/zip": {}}}, **NOT_FOUND})
def download_export(mg: Manager, session_id: SessionId, layout: Layout) -> StreamingResponse:
    """The session's export in ``layout`` as a zip (stored, produced while it is sent)."""
    folder = mg.exports.out_dir(session_id, layout)
    if not folder.is_dir():
        with mg.reads.reading(session_id):  # 404 for an unknown session first
            pass
        raise HTTPException(404, f"session {session_id} has no {layout} export: start one with "
                                 f"POST /sessions/{session_id}/export/jobs")
    name = f"{session_id}-{layout}"
    return StreamingResponse(zip_chunks(folder, name), media_type="application/zip",
                             headers={"Content-Disposition": f'attachment; filename="{name}.zip"',
                                      "Cache-Control": "no-store"})
