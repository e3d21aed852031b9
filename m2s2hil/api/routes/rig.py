"""The rig: each device's state, and the emergency stop."""

from __future__ import annotations

from fastapi import APIRouter

from .. import models as m
from ..common import CROSS_SITE, MARKED, Manager

router = APIRouter(tags=["rig"])


@router.get("/rig", response_model=m.RigState)
def get_rig(mg: Manager) -> dict:
    """Each device's state and health."""
    return mg.guard.rig_state()


@router.post("/rig/stop", response_model=m.StopReport,
             responses=CROSS_SITE, dependencies=MARKED)
def emergency_stop(mg: Manager) -> dict:
    """Emergency stop: lamps off and motion stopped now, even during a session (which is aborted);
    the queue is held until POST /queue/release."""
    return mg.guard.emergency_stop()
