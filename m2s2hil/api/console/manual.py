"""Manual control of an idle rig: each axis's position and limits, jog, go-to, stop, homing or the
origin (as the axis's policy says), lamps by preset or one by one.

The rig has one owner: while a session runs (or is paused, or starting) every command here is
refused with 409 and the reason; ``GET /rig/axes`` says who owns the rig. A move is commanded
and answered at once (202) with the axis's read-back; the console polls ``GET /rig/axes`` to
follow it. A jog starts from the target of the manual move still in force (not from the
read-back while a move runs), so jogs sent together add up (:mod:`m2s2hil.daemon.move_targets`).
The emergency stop (``POST /rig/stop``) works whatever runs.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any, Literal

from fastapi import APIRouter, HTTPException, Path, Request

from m2s2hil.daemon.errors import Conflict
from m2s2hil.daemon.move_targets import MoveTargets
from m2s2hil.errors import UsageError
from m2s2hil.rig.manual import ManualCommandError, ManualControl
from m2s2hil.rig.opened import Rig

from ..common import CONFLICT, CROSS_SITE, MARKED, Manager
from ..guards.logsafe import clean_text
from . import models as cm
from .state import ConsoleDep, device_errors

router = APIRouter(tags=["manual control"])
log = logging.getLogger(__name__)

AxisName = Literal["turntable", "tilt"]
AxisPath = Path(description="turntable or tilt")


def _axis_out(mc: ManualControl, role: AxisName, owner: str | None) -> dict:
    cfg = mc.rig.config.axes[role]
    homing = cfg.homing
    can_home = any(role in link.roles and link.homing is not None for link in mc.rig.links)
    out: dict[str, Any] = {"role": role, "min_deg": cfg.min_deg, "max_deg": cfg.max_deg,
                           "max_speed_dps": cfg.max_speed_dps, "homing": homing,
                           "can_home": can_home and homing == "switches", "position_deg": None,
                           "moving": None, "error": None}
    if owner is None:
        try:
            v = mc.axis_view(role)
            out.update(position_deg=v.position_deg, moving=v.moving)
        except Exception as exc:
            out["error"] = f"{type(exc).__name__}: {exc}"
    return out


@router.get("/rig/axes", response_model=cm.AxesOut)
def get_axes(mg: Manager) -> dict:
    """Each axis's read-back, limits and homing policy; the lamps and presets. While a session owns
    the rig, positions come from its status instead of the devices."""
    owner = mg.running_id()
    cfg = mg.rig.config
    mc = ManualControl(mg.rig)
    axes: list[dict] = []
    lamps_on: list[str] | None = None
    targets = mg.guard.targets
    if owner is None:
        try:
            with mg.guard.manual_access("reading the axes"):  # the device lock (it yields mg.rig, mc's rig)
                axes = [_axis_out(mc, r, None) for r in ("turntable", "tilt")]
                try:
                    lamps_on = mc.lamps_on()
                except Exception:
                    lamps_on = None
        except Conflict:  # a session is starting: it owns the rig already
            owner = mg.running_id() or "a session starting"
    if owner is not None:
        axes = [_axis_out(mc, r, owner) for r in ("turntable", "tilt")]
        try:
            st = mg.reads.status(owner)
            axes[0]["position_deg"], axes[1]["position_deg"] = st.get("azimuth_deg"), st.get("tilt_deg")
            # the lamps the session switched on (its engine's channels), by name
            on = set(st.get("lamps_on") or ())
            lamps_on = sorted(n for n, lc in cfg.lamps.items() if lc.channel in on)
        except UsageError:
            pass
    for a in axes:
        a["target_deg"] = targets.pending(a["role"]) if owner is None else None
    return {"owner": owner, "axes": axes, "lamps_on": lamps_on,
            "lamps": {n: lc.kind for n, lc in cfg.lamps.items()},
            "presets": {k: list(v) for k, v in cfg.lighting.items()}, "busy": mg.busy.items()}


@contextlib.contextmanager
def _forget_on_error(targets: MoveTargets, role: AxisName) -> Iterator[None]:
    """A move the device refused (or a request that failed half-way) may leave the axis anywhere:
    the next jog starts from the read-back. A move refused before sending (422) changes nothing."""
    try:
        yield
    except ManualCommandError:
        raise
    except Exception:
        targets.forget(role)
        raise


def _moved(rig: Rig, role: AxisName, target: float) -> dict:
    """The answer to a move just commanded: its target and the axis's read-back (same lock)."""
    moving, degrees = rig.axis(role).motion()  # one poll: two could pair mid-move with standing
    return {"axis": role, "target_deg": target, "position_deg": float(degrees), "moving": bool(moving)}


@router.post("/rig/axes/{axis}/jog", status_code=202, response_model=cm.MoveOut,
             responses={**CONFLICT, **CROSS_SITE})
def jog(request: Request, mg: Manager, body: cm.Jog, axis: AxisName = AxisPath) -> dict:
    """Move by ``delta_deg`` from the target of the manual move still in force, else from the
    read-back (refused beyond the soft limits): jogs sent together end at their sum."""
    targets = mg.guard.targets
    with (mg.guard.manual_access() as rig, _forget_on_error(targets, axis),
          device_errors(f"jogging the {axis}")):
        base = targets.base(axis, rig.axis(axis).position)
        target = ManualControl(rig).go_to(axis, base + body.delta_deg)
        targets.commanded(axis, target)
        moved = _moved(rig, axis, target)
    log.info("manual: %s jog %+.3f° → %.3f°", axis, body.delta_deg, target)
    request.state.activity = f"{axis} jog {body.delta_deg:+g}° → {target:.3f}°"  # the activity log's words
    return moved


@router.post("/rig/axes/{axis}/goto", status_code=202, response_model=cm.MoveOut,
             responses={**CONFLICT, **CROSS_SITE})
def go_to(request: Request, mg: Manager, body: cm.GoTo, axis: AxisName = AxisPath) -> dict:
    """Move to ``position_deg`` (refused beyond the soft limits)."""
    targets = mg.guard.targets
    with (mg.guard.manual_access() as rig, _forget_on_error(targets, axis),
          device_errors(f"moving the {axis}")):
        target = ManualControl(rig).go_to(axis, body.position_deg)
        targets.commanded(axis, target)
        moved = _moved(rig, axis, target)
    log.info("manual: %s go to %.3f°", axis, target)
    request.state.activity = f"{axis} go to {target:.3f}°"
    return moved


@router.post("/rig/axes/{axis}/stop", response_model=cm.MoveOut, responses={**CONFLICT, **CROSS_SITE},
             dependencies=MARKED)
def stop_axis(mg: Manager, axis: AxisName = AxisPath) -> dict:
    """Stop this axis (use ``POST /rig/stop`` to stop everything and switch the lamps off)."""
    with mg.guard.manual_access() as rig, device_errors(f"stopping the {axis}"):
        mg.guard.targets.forget(axis)  # it stops short of its target
        ManualControl(rig).stop(axis)
        pos = float(rig.axis(axis).position())
    return {"axis": axis, "target_deg": pos, "position_deg": pos, "moving": False}


@router.post("/rig/axes/{axis}/home", response_model=cm.MoveOut, responses={**CONFLICT, **CROSS_SITE},
             dependencies=MARKED)
def home_axis(mg: Manager, console: ConsoleDep, axis: AxisName = AxisPath) -> dict:
    """Home the axis on its switches (axes whose policy is ``switches``; others set an origin)."""
    if mg.rig.config.axes[axis].homing != "switches":
        raise Conflict(f"{axis} has no homing switches in the rig file (homing = "
                       f"{mg.rig.config.axes[axis].homing!r}): set its origin instead")
    with mg.guard.manual_access("homing") as rig, device_errors(f"homing the {axis}"):
        mg.guard.targets.forget()  # homing moves the controller's axes and redefines 0
        ManualControl(rig).home(axis)
        pos = float(rig.axis(axis).position())
    log.info("manual: %s homed", axis)
    return {"axis": axis, "target_deg": 0.0, "position_deg": pos, "moving": False}


@router.post("/rig/axes/{axis}/origin", response_model=cm.MoveOut, responses={**CONFLICT, **CROSS_SITE},
             dependencies=MARKED)
def set_origin(mg: Manager, axis: AxisName = AxisPath) -> dict:
    """Make where the axis stands its origin (0°), for axes without homing switches."""
    from m2s2hil.rig.open_errors import RigOpenError
    from m2s2hil.rig.origin import set_origin_open

    with mg.guard.manual_access("setting the origin") as rig, device_errors(f"setting the {axis} origin"):
        mg.guard.targets.forget(axis)  # 0 is redefined
        try:
            set_origin_open(rig, axis)
        except RigOpenError as exc:
            raise HTTPException(503, str(exc)) from None
        pos = float(rig.axis(axis).position())
    log.info("manual: %s origin set here", axis)
    return {"axis": axis, "target_deg": 0.0, "position_deg": pos, "moving": False}


@router.put("/rig/lamps", response_model=cm.LampsOut, responses={**CONFLICT, **CROSS_SITE})
def set_lamps(request: Request, mg: Manager, body: cm.Lamps) -> dict:
    """A lighting preset (``{"preset": "weak"}``; ``{"preset": null}`` switches every lamp off) or
    exactly these lamps on (``{"lamps": ["bar1", "spot"]}``)."""
    with mg.guard.manual_access("switching lamps") as rig, device_errors("switching the lamps"):
        mc = ManualControl(rig)
        on = mc.set_lamps(body.lamps) if body.lamps is not None else mc.set_preset(body.preset)
    log.info("manual: lamps on: %s", clean_text(", ".join(on) or "none"))
    request.state.activity = f"lamps on: {clean_text(', '.join(on) or 'none')}"
    return {"lamps_on": on}
