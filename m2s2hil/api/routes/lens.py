"""The operator's lens cap for a session's darks on a real rig.

A camera that is not simulated in this daemon cannot cap its own lens, and nothing here can
check the cap. Before the session's darks the engine parks at a safe boundary (lamps off,
motion stopped) with ``pause_reason`` ``"lens_cap: put the lens cap on"`` (in
``GET /sessions/{id}``), and before the next lit frame with ``"lens_cap: take the lens cap
off"`` (:mod:`m2s2hil.engine.darks`). ``POST /sessions/{id}/lens`` with ``{"capped": true}``
(or ``false``) is the operator's word for it and continues the run; ``/resume`` does not.
"""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from .. import models as m
from ..common import CONFLICT, CROSS_SITE, NOT_FOUND, Manager, SessionId, status_out

router = APIRouter(tags=["sessions"])


class LensIn(BaseModel):
    """What the operator has done to the lens cap (trusted: a real rig cannot check it)."""

    # strict: "true" as a string is refused, as the schema says
    model_config = ConfigDict(extra="forbid", strict=True)

    capped: bool = Field(description="true: the lens cap is on (the darks may be taken); false: it is off "
                                     "(lit frames may be taken).")


@router.post("/sessions/{session_id}/lens", response_model=m.SessionStatus,
             responses={**NOT_FOUND, **CONFLICT, **CROSS_SITE})
def confirm_lens(mg: Manager, session_id: SessionId, body: LensIn) -> dict:
    """Confirm the lens cap on (``capped: true``) or off for a session waiting for it (its
    ``pause_reason`` starts with ``lens_cap:``); the run continues. 409 when the session does
    not wait for exactly that."""
    return status_out(mg.confirm_lens(session_id, body.capped))
