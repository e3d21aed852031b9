"""Calibration captures: the dark library over the exposures a sweep uses, the white reference
(checked, written to the calibration file with its provenance) and the mosaic phase check.

Each needs an idle rig (409 while a session owns it) and runs once at a time (409 while the same
capture runs: a second click does not run it twice, :mod:`m2s2hil.daemon.busy`). On a real rig
the operator confirms the lens cap (darks) or the white panel (white reference) in the request;
a simulated rig caps its own lens and puts its own panel in view.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter

from m2s2hil.config import RigConfig
from m2s2hil.daemon.admission import EXPANDING, check_size
from m2s2hil.errors import UsageError
from m2s2hil.rig.calibrate import (
    capture_dark_library,
    capture_white_reference,
    check_mosaic_phase,
    sweep_exposures,
)

from ..common import CONFLICT, CROSS_SITE, Manager
from . import models as cm
from .state import ConsoleDep, check_camera_range, device_errors

router = APIRouter(tags=["calibration"])


@router.get("/calibration")
def get_calibration(console: ConsoleDep) -> dict[str, Any]:
    """Where the calibration file is, what its white reference was captured with, the dark library."""
    path = console.calibration_path
    named = console.manager.rig.config.camera.calibration_file is not None
    out: dict[str, Any] = {"file": str(path), "exists": path.is_file(), "white_reference": None,
                           "named_in_rig_file": named,
                           "white_default_lighting": white_default_lighting(console.manager.rig.config)}
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            out["white_reference"] = doc.get("white_reference")
        except (OSError, ValueError) as exc:
            out["error"] = f"unreadable calibration file: {exc}"
    try:
        out["darks"] = console.darks.entries() if console.darks.root.is_dir() else []
    except UsageError as exc:
        out["darks"] = []
        out["error"] = str(exc)
    return out


@router.post("/calibration/darks", status_code=201, responses={**CONFLICT, **CROSS_SITE})
def take_darks(mg: Manager, console: ConsoleDep, body: cm.DarksIn) -> dict[str, Any]:
    """Master darks at every (exposure, gain) given, or that the plan in ``plan`` uses."""
    if not mg.rig.simulated and not body.lens_capped:
        raise UsageError("body.lens_capped: put the lens cap on and confirm it (lens_capped: true)")
    with (mg.busy.claim("darks", "a dark capture"), mg.guard.manual_access("taking darks") as rig,
          device_errors("the dark capture")):
        console.camera.release(rig)
        if body.exposures:
            pairs = [(e.exposure_s, e.gain) for e in body.exposures]
        elif body.plan is not None:
            check_size(body.plan, mg.max_plan_frames)  # before expanding it
            with EXPANDING:
                pairs = sweep_exposures(body.plan, rig)
            check_camera_range(pairs)
        else:
            raise UsageError("body: give exposures ([[exposure_s, gain], …]) or a plan")
        entries = capture_dark_library(rig, console.darks, pairs, n_frames=body.n_frames)
    return {"library": str(console.darks.root), "darks": entries}


def white_default_lighting(cfg: RigConfig) -> str | None:
    """The preset a white reference should default to: the one with the most lamps and no
    spotlight (a directional lamp lights a panel unevenly, and the uniformity check refuses it)."""
    even = [(len(lamps), name) for name, lamps in cfg.lighting.items()
            if lamps and all(cfg.lamps[n].kind != "spotlight" for n in lamps if n in cfg.lamps)]
    return max(even)[1] if even else None


@router.post("/calibration/white", status_code=201, responses={**CONFLICT, **CROSS_SITE})
def take_white(mg: Manager, console: ConsoleDep, body: cm.WhiteIn) -> dict[str, Any]:
    """Average the white panel, check it (no saturation, enough signal, an even field), and write
    it to the calibration file; a failed check (422) writes nothing. Without ``lighting`` the
    lamps are switched to ``white_default_lighting`` (``GET /calibration``: the preset with the
    most lamps and no spotlight), not left as they happen to be."""
    lighting = body.lighting or white_default_lighting(mg.rig.config)
    if not mg.rig.simulated and not body.panel_in_place:
        raise UsageError("body.panel_in_place: put the white panel in view and confirm it")
    with (mg.busy.claim("white", "a white reference capture"),
          mg.guard.manual_access("the white reference") as rig, device_errors("the white reference")):
        console.camera.release(rig)
        _, prov = capture_white_reference(
            rig, console.calibration_path, exposure_s=body.exposure_s, gain=body.gain,
            n_frames=body.n_frames, reflectance=body.reflectance, lighting=lighting,
            library=console.darks)
    hint = None if console.manager.rig.config.camera.calibration_file is not None else (
        f"the rig file names no calibration file: add calibration_file = \"{console.calibration_path}\" "
        "under [camera] so sessions use it")
    return {"file": str(console.calibration_path), "provenance": prov, "hint": hint}


@router.post("/calibration/phase", responses={**CONFLICT, **CROSS_SITE})
def phase(mg: Manager, console: ConsoleDep, body: cm.PhaseIn) -> dict[str, Any]:
    """One frame; does the mosaic's origin match the layout? (a readout offset shows here)."""
    with (mg.busy.claim("phase", "a phase check"), mg.guard.manual_access("the phase check") as rig,
          device_errors("the phase check")):
        console.camera.release(rig)
        return check_mosaic_phase(rig, exposure_s=body.exposure_s, gain=body.gain)
