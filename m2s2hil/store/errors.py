"""The session store's errors: a session that is not there, already there, damaged, open
only for reading, or on a folder that cannot be written.

The store raises these as well as the typed errors of the modules underneath it:
``DiskFull`` (m2s2hil.atomic), ``DuplicateEvent`` (m2s2hil.store.journal), ``SessionLocked``
(m2s2hil.store.owner_lock) and ``InvalidImage`` (m2s2hil.store.frame_files).
"""

from __future__ import annotations

from pathlib import Path

from m2s2hil.errors import M2S2Error, UsageError


class StoreError(M2S2Error):
    """A session store problem that is not the user's input."""


class SessionNotFound(UsageError):
    def __init__(self, root: Path, session_id: str) -> None:
        super().__init__(f"no session {session_id!r} under {root}")


class SessionExists(UsageError):
    def __init__(self, path: Path) -> None:
        super().__init__(f"session folder {path} already exists")


class SessionCorrupt(StoreError):
    """A session folder whose journal is missing, unreadable or inconsistent."""


class SessionDamaged(SessionCorrupt):
    """The journal's database is damaged; ``sessions repair`` rebuilds it from the files."""

    def __init__(self, path: Path, detail: str) -> None:
        self.path = path
        self.detail = detail
        super().__init__(f"session {path.name}: journal damaged ({detail}); nothing was changed; "
                         f"rebuild it from the frame files with: m2s2hil sessions repair {path.name}"
                         f" --root {path.parent}")


class ReadOnlySession(UsageError):
    """A write through a session opened for reading."""

    def __init__(self, session_id: str, what: str) -> None:
        super().__init__(f"session {session_id} is open for reading; {what} needs "
                         "SessionStore.open(..., mode='write')")


class OutputNotWritable(UsageError):
    """The data root (or a session folder) cannot be written: read-only or no permission."""

    def __init__(self, path: Path, detail: str) -> None:
        self.path = path
        super().__init__(f"output folder {path} is not writable ({detail}); choose another with --out")
