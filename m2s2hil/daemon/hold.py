"""The queue's hold, kept on the data root so that it outlives the daemon.

An emergency stop, an operator's hold (a mockup swap) or a failed session holds the queue:
no session starts until an operator releases it. The hold is written here (atomically:
temporary file, fsync, rename, fsync of the folder) *before* the request that set it is
answered, and read back when a daemon starts, so a restart, a ``kill -9`` or a power loss
does not release it. Only a release removes the file.

A hold file that cannot be read or makes no sense counts as a hold (fail safe): the rig
stays held, with a reason that says the file is damaged, until an operator releases it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from m2s2hil.atomic import fsync_dir, write_text_atomic
from m2s2hil.errors import M2S2Error

from .errors import HoldNotSaved

log = logging.getLogger(__name__)

HOLD_NAME = ".m2s2hil-hold.json"
_FORMAT = 1


@dataclass(frozen=True)
class Hold:
    reason: str
    since: float  # Unix time the hold was set
    damaged: str | None = None  # why the file could not be read (it then holds anyway)

    @property
    def since_iso(self) -> str:
        return iso_utc(self.since)


def iso_utc(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _printable(text: str) -> str:
    """A reason from a file may have been edited by hand: never let it break a log line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class HoldFile:
    """``<root>/.m2s2hil-hold.json``: present while the queue is held."""

    def __init__(self, root: str | Path) -> None:
        self.path = Path(root) / HOLD_NAME

    def save(self, reason: str, since: float | None = None) -> Hold:
        """Write the hold durably; :class:`HoldNotSaved` when that fails."""
        hold = Hold(reason, time.time() if since is None else since)
        doc = {"format": _FORMAT, "reason": reason, "since": hold.since_iso, "since_unix": hold.since,
               "pid": os.getpid()}
        try:
            write_text_atomic(self.path, json.dumps(doc, indent=1) + "\n")
        except (OSError, M2S2Error) as exc:
            raise HoldNotSaved(f"the hold ({reason}) could not be saved to {self.path}: "
                               f"{type(exc).__name__}: {exc}; it holds in this daemon but would not "
                               "survive a restart") from exc
        return hold

    def clear(self) -> None:
        """Remove the file (released); :class:`HoldNotSaved` when it stays."""
        try:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
            fsync_dir(self.path.parent)
        except OSError as exc:
            raise HoldNotSaved(f"the hold file {self.path} could not be removed: {type(exc).__name__}: "
                               f"{exc}; the queue stays held") from exc

    def load(self) -> Hold | None:
        """The saved hold; None when there is none. A file that exists but cannot be read or
        parsed is a hold too (:attr:`Hold.damaged` says why)."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            return self._damaged(f"{type(exc).__name__}: {exc.strerror or exc}")
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            return self._damaged(f"not JSON: {exc}")
        if not isinstance(doc, dict):
            return self._damaged("not a JSON object")
        reason, since = doc.get("reason"), doc.get("since_unix")
        if not isinstance(reason, str) or not reason.strip():
            return self._damaged("no reason")
        if isinstance(since, bool) or not isinstance(since, (int, float)) or not 0 < since < 1e11:
            return self._damaged("no valid 'since_unix'")
        return Hold(_printable(reason), float(since))

    def _damaged(self, problem: str) -> Hold:
        try:
            since = self.path.stat().st_mtime
        except OSError:
            since = time.time()
        problem = _printable(problem)
        return Hold(f"the hold file {self.path} is damaged ({problem}): held until released", since,
                    damaged=problem)


class QueueHold:
    """The queue's hold, in memory and in its file. Memory changes under the queue's condition
    ``cond`` (the caller's), so a hold and the dispatcher's decision to start a session are one
    locked step; the file follows (:meth:`save`) before the request that set it is answered.
    Lock order: this object's file lock, then ``cond``."""

    def __init__(self, root: str | Path, cond: threading.Condition) -> None:
        self.file = HoldFile(root)
        self._cond = cond
        self._file_lock = threading.Lock()  # one writer of the file at a time
        self.reason: str | None = None  # why the queue is held; None: not held
        self.since: float | None = None
        self._gen = 0  # counts holds set, so a release cannot clear one it did not see

    def restore(self) -> None:
        """Take over the hold a previous daemon left on the data root, and say so in one line."""
        saved = self.file.load()
        if saved is None:
            return
        with self._cond:
            self.reason, self.since = saved.reason, saved.since
            self._gen += 1
        if saved.damaged:
            log.error("rig HELD (fail safe): the hold file %s is damaged (%s); no session starts until "
                      "an operator releases it (POST /queue/release)", self.file.path, saved.damaged)
        else:
            log.warning("rig HELD since %s: %s; no session starts until an operator releases it "
                        "(POST /queue/release)", saved.since_iso, saved.reason)

    def set_now(self, reason: str) -> None:
        """Hold in memory at once (nothing is dispatched from here on); caller holds ``cond``
        and calls :meth:`save` after letting it go."""
        self.reason, self.since = reason, time.time()
        self._gen += 1
        self._cond.notify_all()

    def save(self) -> None:
        """Make the file say what memory says (:class:`HoldNotSaved` when it cannot). Serialised,
        and memory is read once the file is ours: whatever order holds and releases come in,
        the last writer is right."""
        with self._file_lock:
            with self._cond:
                reason, since = self.reason, self.since
            if reason is None:
                self.file.clear()
            else:
                self.file.save(reason, since)

    def release(self) -> str | None:
        """Release; returns the reason it was held. The file goes first: when it cannot be
        removed (:class:`HoldNotSaved`) the queue stays held."""
        with self._file_lock:
            with self._cond:
                gen, was = self._gen, self.reason
            self.file.clear()
            with self._cond:
                if self._gen == gen:  # no new hold (an emergency stop) came in meanwhile
                    self.reason = self.since = None
                    self._cond.notify_all()
        return was
