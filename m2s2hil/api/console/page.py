"""The operator console: one page at ``/`` and its script and style, plus the plan estimate its
session form shows before a session is started.

The page, script and style are plain files committed in ``m2s2hil/console/`` (no JavaScript
toolchain, no CDN: the console works offline). They are served without a token (they hold no
data; every call they make carries the token the operator typed in), with a Content Security
Policy that allows only this origin's scripts, styles, images and connections, and
``frame-ancestors 'none'`` so no other page can frame the console and trick a click onto its
emergency stop or jog buttons.
"""

from __future__ import annotations

from importlib import resources
from typing import Any

from fastapi import APIRouter, Body, HTTPException
from fastapi.responses import Response

from m2s2hil.catalog import load_catalog
from m2s2hil.daemon.admission import EXPANDING, check_size, estimate_bytes
from m2s2hil.plan import Sweep, estimate, estimate_continuous

from ..common import CROSS_SITE, Manager
from . import models as cm

open_router = APIRouter(tags=["console"])
router = APIRouter(tags=["console"])

_TYPES = {".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}
# Every script and style sheet in the console folder, read once: a name not in it is a 404, so
# no request can reach another file.
ASSETS: dict[str, str] = {f.name: _TYPES[f.name[f.name.rfind("."):]]
                          for f in resources.files("m2s2hil").joinpath("console").iterdir()
                          if f.name.endswith(tuple(_TYPES))}
SECURITY_HEADERS = {
    "Content-Security-Policy": ("default-src 'none'; script-src 'self'; style-src 'self'; "
                                "img-src 'self' blob: data:; connect-src 'self'; frame-ancestors 'none'; "
                                "base-uri 'none'; form-action 'none'"),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


def _asset(name: str) -> bytes:
    return resources.files("m2s2hil").joinpath("console", name).read_bytes()


@open_router.get("/", response_class=Response, responses={200: {"content": {"text/html": {}}}})
def console_page() -> Response:
    """The operator console (HTML)."""
    return Response(_asset("index.html"), media_type="text/html; charset=utf-8", headers=SECURITY_HEADERS)


@open_router.get("/console/{name}", response_class=Response,
                 responses={200: {"content": {t.split(";")[0]: {} for t in ASSETS.values()}},
                            404: {"description": "No console asset of that name"}})
def console_asset(name: str) -> Response:
    """The console's scripts and style sheet."""
    if name not in ASSETS:
        raise HTTPException(404, f"no console asset named {name!r}")
    return Response(_asset(name), media_type=ASSETS[name], headers=SECURITY_HEADERS)


@router.post("/plans/estimate", response_model=cm.EstimateOut, responses=CROSS_SITE, tags=["sessions"])
def estimate_plan(mg: Manager, sweep: Sweep = Body(...)) -> dict:
    """What a sweep would take (the dry run of ``capture --dry-run``): events, duration estimate and
    its lower bound, disk space. Nothing is created. The same limits as POST /sessions apply,
    checked before the plan is expanded."""
    cfg = mg.rig.config
    check_size(sweep, mg.max_plan_frames)
    with EXPANDING:
        events = sweep.expand(cfg)
        est = (estimate_continuous(sweep, cfg, radius_px=400.0, events=events).as_plan_estimate()
               if sweep.mode == "continuous" else estimate(events, cfg))
    frames = sum(1 for e in events if e.kind == "frame")
    return {"events": len(events), "frames": frames, "darks": len(events) - frames,
            "estimate_s": est.total_s, "lower_bound_s": est.lower_bound_s,
            "physical_floor_s": sweep.physical_floor(cfg).total_s,
            "bytes": estimate_bytes(sweep, cfg, frames), "breakdown": est.breakdown}


@router.get("/catalog")
def catalog() -> dict[str, Any]:
    """What a session can name: satellites and their builds (with materials), lighting conditions,
    elevations (for the session form)."""
    cat = load_catalog()
    return {
        "satellites": {k: {"name": s.name, "builds": {b: list(v.materials) for b, v in s.builds.items()}}
                       for k, s in cat.satellites.items()},
        "lighting": {k: {"name": lt.name, "dataset": lt.dataset} for k, lt in cat.lighting.items()},
        "elevations": list(cat.elevations),
    }
