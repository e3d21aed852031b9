"""Snapshots: test frames taken outside sessions, with their metadata, downloadable."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Path, Query
from fastapi.responses import FileResponse, Response

from m2s2hil.rig.snapshots import (
    FILES,
    SnapshotNotFound,
    list_snapshots,
    save_snapshot,
    snapshot_file,
    snapshot_meta,
)

from ..common import CONFLICT, CROSS_SITE, Manager
from . import models as cm
from .state import ConsoleDep, device_errors

router = APIRouter(tags=["snapshots"])
SnapshotId = Annotated[str, Path(pattern=r"^[0-9]{8}T[0-9]{6}-[0-9a-f]{6}$", max_length=32)]


@router.post("/snapshots", status_code=201, responses={**CONFLICT, **CROSS_SITE})
def take_snapshot(mg: Manager, console: ConsoleDep, body: cm.SnapshotIn) -> dict[str, Any]:
    """One frame at the live view's exposure and gain (or those given), stored under
    ``<data root>/snapshots/<id>/`` (raw TIFF, metadata JSON, preview PNG); never in a session."""
    s = console.live.settings
    exposure = body.exposure_s or s.exposure_s
    gain = body.gain if body.gain is not None else s.gain
    with (mg.busy.claim("snapshot", "a snapshot"), mg.guard.manual_access("a snapshot") as rig,
          device_errors("the snapshot")):
        console.camera.release(rig)
        rig.camera.configure(exposure_s=exposure, gain=gain)
        frame = rig.camera.snap(timeout=exposure + rig.config.camera.timeout_s)
        meta = save_snapshot(mg.root, rig, frame, body.note)
    return {**meta, "files": {name: f"/snapshots/{meta['id']}/{name}" for name in FILES}}


@router.get("/snapshots")
def get_snapshots(mg: Manager, limit: Annotated[int, Query(ge=1, le=500)] = 50) -> dict[str, Any]:
    """The newest snapshots first, with their metadata."""
    return {"items": list_snapshots(mg.root, limit)}


@router.get("/snapshots/{snapshot_id}", responses={404: {"description": "No such snapshot."}})
def get_snapshot(mg: Manager, snapshot_id: SnapshotId) -> dict[str, Any]:
    try:
        return snapshot_meta(mg.root, snapshot_id)
    except SnapshotNotFound as exc:
        raise HTTPException(404, str(exc)) from None


@router.get("/snapshots/{snapshot_id}/{name}", response_class=Response,
            responses={200: {"content": {t: {} for t in FILES.values()}},
                       404: {"description": "No such file."}})
def download_snapshot(mg: Manager, snapshot_id: SnapshotId,
                      name: Literal["raw.tiff", "preview.png", "meta.json"]) -> FileResponse:
    """A snapshot's file (as an attachment, named after the snapshot)."""
    try:
        path = snapshot_file(mg.root, snapshot_id, name)
    except SnapshotNotFound as exc:
        raise HTTPException(404, str(exc)) from None
    return FileResponse(path, media_type=FILES[name], filename=f"{snapshot_id}-{name}")
