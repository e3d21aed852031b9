"""The session queue: read it, hold it, release it."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from .. import models as m
from ..common import CROSS_SITE, MARKED, Manager
from ..guards.logsafe import HOLD_REASON_MAX, clean_text

router = APIRouter(tags=["queue"])


@router.get("/queue", response_model=m.QueueState)
def get_queue(mg: Manager) -> dict:
    """The running session and the ones waiting, first to run first."""
    return mg.queue()


@router.post("/queue/hold", response_model=m.QueueState,
             responses=CROSS_SITE, dependencies=MARKED)
def hold_queue(mg: Manager,
               reason: Annotated[str, Query(min_length=1, max_length=HOLD_REASON_MAX)] = "operator") -> dict:
    """Hold the queue: the running session goes on, no queued one starts (e.g. to swap the mockup).
    Control characters in ``reason`` are escaped before it is logged or shown."""
    mg.hold(clean_text(reason, HOLD_REASON_MAX))
    return mg.queue()


@router.post("/queue/release", response_model=m.QueueState,
             responses=CROSS_SITE, dependencies=MARKED)
def release_queue(mg: Manager) -> dict:
    """Let queued sessions start again after an emergency stop or a failure held the queue."""
    mg.release()
    return mg.queue()
