"""A session's stored files checked against its journal: ``verify`` (report only),
``check_stored`` (before a resume: a damaged capture is moved aside to be captured again),
``complete`` (the end of a run: every file read back, the manifest, the final state).

Every check walks the same list of committed files (:func:`stored_files`) and judges each
file with the same :func:`file_problem`: missing, wrong size, wrong sha256.
"""

from __future__ import annotations

import json
import os
import secrets
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from m2s2hil.atomic import TMP_MARK, fsync_dir, sha256_file, write_text_atomic
from m2s2hil.store.errors import StoreError
from m2s2hil.store.layout import JOURNAL, safe_name
from m2s2hil.store.owner_lock import writer_active
from m2s2hil.store.records import FileRecord, Problem

if TYPE_CHECKING:
    from pathlib import Path

    from m2s2hil.store.session import SessionStore


def stored_files(store: SessionStore) -> list[tuple[str, dict[str, FileRecord]]]:
    """(event id, files) of every committed frame, then every dark."""
    frames = [(fr.event_id, fr.files) for fr in store.frames()]
    return frames + [(d.dark_id, d.files) for d in store.darks()]


def file_problem(folder: Path, rec: FileRecord, *, checksum: bool = True) -> Problem | None:
    """What is wrong with the stored file ``rec`` of the session in ``folder``, or None."""
    p = folder / rec.path
    if not p.is_file():
        return Problem(rec.path, "missing", "file listed in the journal is missing")
    size = p.stat().st_size
    if size != rec.bytes:
        return Problem(rec.path, "size", f"{size} bytes, journal says {rec.bytes}")
    if checksum:
        digest = sha256_file(p)
        if digest != rec.sha256:
            return Problem(rec.path, "checksum", f"sha256 {digest[:12]}…, journal says {rec.sha256[:12]}…")
    return None


def verify(store: SessionStore) -> list[Problem]:
    """Every file's sha256 recomputed against the journal; also files the journal does not
    know (orphans of an interrupted write) and journal damage. Temporary files of a live
    writer are its business and not reported."""
    problems: list[Problem] = []
    damage = store.journal.check()
    if damage is not None:
        problems.append(Problem(JOURNAL, "journal", damage))
    known: set[str] = set()
    for rec in (f for _, files in stored_files(store) for f in files.values()):
        known.add(rec.path)
        problem = file_problem(store.path, rec)
        if problem is not None:
            problems.append(problem)
    live = store.writable or writer_active(store.path)
    for folder in ("frames", "darks"):
        for p in sorted((store.path / folder).glob("*")):
            rel = p.relative_to(store.path).as_posix()
            if not p.is_file() or rel in known:
                continue
            if TMP_MARK in p.name:
                if not live:
                    problems.append(Problem(rel, "temporary", "left by an interrupted write; removed "
                                                              "when the session is next resumed"))
                continue
            problems.append(Problem(rel, "orphan", "file not in the journal (interrupted write)"))
    return problems


def check_stored(store: SessionStore, *, checksum: bool = True) -> list[Problem]:
    """Before a resume trusts the journal: every committed frame's and dark's files must be
    there with their size and sha256. A capture whose files fail is moved aside (its files
    into ``quarantine/``, its journal row into a ``quarantined`` event; nothing is deleted)
    so the run captures it again. Returns the problems. Needs the session open for writing."""
    store.require_writer("check_stored")
    out: list[Problem] = []
    for event_id, files in stored_files(store):
        probs = [pr for rec in files.values()
                 if (pr := file_problem(store.path, rec, checksum=checksum)) is not None]
        if not probs:
            continue
        stamp = datetime.fromtimestamp(store.clock.wall(), UTC).strftime("%Y%m%dT%H%M%S")
        aside = store.path / "quarantine" / f"{safe_name(event_id)}-{stamp}-{secrets.token_hex(2)}"
        moved = []
        for rec in files.values():
            src = store.path / rec.path
            if src.is_file():
                aside.mkdir(parents=True, exist_ok=True)
                os.replace(src, aside / src.name)
                moved.append((aside / src.name).relative_to(store.path).as_posix())
        if moved:
            fsync_dir(aside)
        kept = f"; kept in {aside.relative_to(store.path).as_posix()}" if moved else ""
        store.journal.remove_record(event_id, now=store.clock.wall(),
                                    reason="; ".join(str(p) for p in probs) + kept)
        out.extend(probs)
    return out


def write_manifest(store: SessionStore, state: str | None = None) -> dict[str, Any]:
    """Write manifest.json (every file with its sha256) and return it. ``state``: the state
    to record in it (default: the current one)."""
    store.require_writer("manifest")
    row = store.journal.session()
    files = []
    for fr in store.frames():
        for role, rec in fr.files.items():
            files.append({"event_id": fr.event_id, "role": role, **rec.model_dump()})
    for d in store.darks():
        for role, rec in d.files.items():
            files.append({"event_id": d.dark_id, "role": f"dark-{role}", **rec.model_dump()})
    man = {
        "session_id": store.session_id,
        "satellite": store.sweep.satellite,
        "build": store.sweep.build,
        "state": state or row["state"],
        "created": row["created"],
        "written": store.clock.wall(),
        "software_version": store.software_version,
        "rig_digest": store.rig_digest,
        "sweep": store.sweep.model_dump(mode="json"),
        "files": files,
        "skips": [s.model_dump() for s in store.skips()],
    }
    write_text_atomic(store.path / "manifest.json", json.dumps(man, indent=2, sort_keys=True) + "\n")
    return man


def complete(store: SessionStore, state: str = "completed") -> dict[str, Any]:
    """End of run: every committed file read back and checked against its sha256 (a file lost
    or damaged since it was written fails the run here, not in the dataset), the manifest,
    then the session's state (the very last step)."""
    store.require_writer("complete")
    lost = [pr for _, files in stored_files(store) for rec in files.values()
            if (pr := file_problem(store.path, rec)) is not None]
    if lost:
        raise StoreError(f"session {store.session_id}: {len(lost)} stored file(s) failed the final "
                         f"check ({lost[0]}); resume the session to capture them again")
    man = write_manifest(store, state)
    store.set_state(state)
    return man
