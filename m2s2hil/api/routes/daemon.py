"""The daemon itself: liveness (open, no token) and Prometheus metrics (guarded)."""

from __future__ import annotations

import os
import time

from fastapi import APIRouter, Response

from m2s2hil.daemon.prometheus import CONTENT_TYPE
from m2s2hil.store.folder import software_version

from .. import models as m
from ..common import Manager

router = APIRouter(tags=["daemon"])
#: Routes that need no token: liveness probes (container orchestrators, load balancers) carry none.
open_router = APIRouter(tags=["daemon"])


@router.get("/metrics", response_class=Response,  # not PlainTextResponse: errors stay documented as JSON
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus text format."}})
def metrics(mg: Manager) -> Response:
    """Prometheus metrics: frames, faults by class, queue depths, session durations."""
    return Response(mg.metrics.render(), media_type=CONTENT_TYPE)


@open_router.get("/healthz", response_model=m.Health)
def healthz(mg: Manager) -> dict:
    """Liveness and a one-line summary; needs no token."""
    writable = os.access(mg.root, os.W_OK)
    q = mg.queue()
    return {"status": "ok" if writable and not q["held"] else "degraded", "version": software_version(),
            "rig": mg.rig.config.rig.name, "simulated": bool(mg.rig.simulated),
            "data_root_writable": writable, "running": q["running"], "queued": len(q["items"]),
            "held": q["held"], "uptime_s": max(0.0, time.time() - mg.started_at)}
