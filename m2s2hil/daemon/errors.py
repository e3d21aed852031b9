"""What the daemon refuses with, by the HTTP status the API maps it to."""

from __future__ import annotations

from m2s2hil.errors import M2S2Error, UsageError


class UnknownSession(UsageError):
    """No such session under the data root (HTTP 404)."""


class Conflict(UsageError):
    """The request is well formed but the session's or the rig's state does not allow it (HTTP 409)."""


class QueueFull(UsageError):
    """Too many sessions already wait for the rig (HTTP 429)."""


class PlanTooLarge(UsageError):
    """A sweep with more frames than the daemon accepts (HTTP 422)."""


class HoldNotSaved(M2S2Error):
    """The hold file could not be written or removed (HTTP 500): the hold is in force in this
    process, but its file on the data root does not say so (or still says held)."""
