"""Replacing a stored frame's derived label map (the twin's projected labels) after the fact.

Capture writes ``projected_labels`` from the coarse incremental registration; ``sessions
register`` refits and rewrites them here. Per frame the swap is atomic: the new map goes to a
new file (written through ``m2s2hil.atomic``, fsynced), then one journal transaction points the
frame at it and updates its metadata, and only then is the old file removed. An interruption
leaves each frame with either its old labels or its new ones, never a torn file; at worst a
new file nobody points at, which the next rewrite overwrites. The raw frame (and the metadata
in its TIFF) and the simulator's ``truth_labels`` are never touched.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from m2s2hil.atomic import DEFAULT_RESERVE_BYTES, check_free_space, write_files_atomic
from m2s2hil.store.errors import SessionCorrupt
from m2s2hil.store.frame_files import dumps, extra_file
from m2s2hil.store.layout import safe_name

ROLE = "projected_labels"


def check_label_file(store: Any, event_id: str, role: str = ROLE) -> None:
    """SessionCorrupt (one line) if the frame's stored label file is missing or not what the
    journal says it is; nothing if the frame has none."""
    fr = store.frame(event_id)
    rec = fr.files.get(role)
    if rec is None:
        return
    try:
        store.read_file(rec, check=True)
    except FileNotFoundError:
        raise SessionCorrupt(f"{store.path / rec.path}: {role} of frame {event_id} is missing") from None
    except SessionCorrupt as exc:
        raise SessionCorrupt(f"{exc} ({role} of frame {event_id}; `m2s2hil sessions repair` quarantines "
                             "it, or pass --no-relabel)") from None


def replace_frame_labels(store: Any, event_id: str, labels: np.ndarray, meta: dict[str, Any], *,
                         tag: str, role: str = ROLE) -> str:
    """Store ``labels`` as the frame's ``role`` file and ``meta`` as ``meta["qc"][role]``; the
    previous metadata moves to ``meta["qc"][role + "_superseded"]`` (the last one only), so
    readers of ``meta["qc"][role]`` see only the new provenance. ``tag`` names the new file
    (``frames/<event>.<role>.<tag>.png``). Returns the new file's path."""
    store.require_writer(f"rewriting the {role} of {event_id!r}")
    if not re.fullmatch(r"[a-z0-9]{1,16}", tag):
        raise ValueError(f"label file tag {tag!r}: 1–16 lower-case letters or digits")
    fr = store.frame(event_id)
    rel, data = extra_file(safe_name(event_id), role, labels, event_id)
    stem, dot, ext = rel.rpartition(".")
    rel = f"{stem}.{tag}{dot}{ext}"
    check_free_space(store.path, len(data), reserve_bytes=DEFAULT_RESERVE_BYTES)
    written = write_files_atomic({store.path / rel: data})[store.path / rel]
    files = {k: v.model_dump() for k, v in fr.files.items()}
    old = files.get(role)
    files[role] = {"path": rel, "sha256": written.sha256, "bytes": written.bytes}
    full = dict(fr.meta)
    qc = dict(full.get("qc") or {})
    if isinstance(qc.get(role), dict):
        qc[f"{role}_superseded"] = {k: v for k, v in qc[role].items() if k != "superseded"}
    qc[role] = meta
    full["qc"] = qc
    with store.journal.transaction() as db:
        db.execute("UPDATE frames SET files = ?, meta = ? WHERE event_id = ?",
                   (dumps(files), dumps(full), event_id))
    if old is not None and old["path"] != rel:
        (store.path / old["path"]).unlink(missing_ok=True)
    return rel
