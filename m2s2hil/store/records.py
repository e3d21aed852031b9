"""What the session store returns: typed, frozen records of the journal's rows, the
problems an integrity check finds, and a listed session.

``frame_record``/``dark_record``/``skip_record`` turn a journal row (m2s2hil.store.journal)
into its record; every reader of the journal's tables goes through them.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict


class _Rec(BaseModel):
    model_config = ConfigDict(frozen=True)


class FileRecord(_Rec):
    path: str  # relative to the session folder, POSIX separators
    sha256: str
    bytes: int


class FrameRecord(_Rec):
    event_id: str
    index: int
    time: float
    dark_id: str | None
    files: dict[str, FileRecord]  # role -> file: "raw", "cube", "preview", extras
    meta: dict[str, Any]


class DarkRecord(_Rec):
    dark_id: str
    exposure_s: float
    gain: float
    n_frames: int
    reduce: str
    time: float
    files: dict[str, FileRecord]  # "master"
    meta: dict[str, Any]


class SkipRecord(_Rec):
    event_id: str
    index: int
    time: float
    reason: str
    fault_class: str


@dataclass(frozen=True)
class Problem:
    """A stored file (or the journal) that failed a check."""

    path: str
    kind: str  # missing | size | checksum | orphan | temporary | journal
    detail: str

    def __str__(self) -> str:
        return f"{self.path}: {self.kind}: {self.detail}"


class SessionInfo(_Rec):
    """A session as ``list_sessions`` finds it on a data root (m2s2hil.store.catalogue)."""

    session_id: str
    path: str
    state: str  # the journal's state; "damaged" when the journal cannot be trusted
    satellite: str | None = None
    build: str | None = None
    created: float | None = None
    updated: float | None = None
    frames: int = 0
    error: str | None = None


def _files(text: str) -> dict[str, FileRecord]:
    return {k: FileRecord(**v) for k, v in json.loads(text).items()}


def frame_record(r: sqlite3.Row) -> FrameRecord:
    """The record of a row of the journal's ``frames`` table."""
    return FrameRecord(event_id=r["event_id"], index=r["idx"], time=r["time"], dark_id=r["dark_id"],
                       files=_files(r["files"]), meta=json.loads(r["meta"]))


def dark_record(r: sqlite3.Row) -> DarkRecord:
    """The record of a row of the journal's ``darks`` table."""
    return DarkRecord(dark_id=r["dark_id"], exposure_s=r["exposure_s"], gain=r["gain"],
                      n_frames=r["n_frames"], reduce=r["reduce"], time=r["time"],
                      files=_files(r["files"]), meta=json.loads(r["meta"]))


def skip_record(r: sqlite3.Row) -> SkipRecord:
    """The record of a row of the journal's ``skips`` table."""
    return SkipRecord(event_id=r["event_id"], index=r["idx"], time=r["time"], reason=r["reason"],
                      fault_class=r["fault_class"])
