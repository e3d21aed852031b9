"""``m2s2hil sessions compact ID``: convert a session's files to the compressed format, atomically.

Per frame: the uncompressed raw is rewritten deflate-compressed under a new name
(``<event>-v2.raw.tiff``; the frame's other files are copied under the same new stem, so
the names still group by frame for ``sessions repair``); a stored cube that ``read_cube``
recomputes bit for bit from raw + dark is dropped, any other stored cube is kept,
deflate-compressed; the metadata gains the storage format and the cube recipe (encoded
once, the same text in the TIFF and the journal). Per dark: a float32 master of whole DN
becomes uint16, deflate.

Order, so that a crash at any point leaves a readable session and re-running finishes it:

1. the whole session verified (sha256 of every file against the journal); any problem but
   orphans stops the compaction before anything is written;
2. every new raw decoded and compared with the old pixels, then every new file written
   atomically (temporary name, fsync, rename) and read back byte for byte;
3. ONE journal transaction points every frame and dark at its new files (and records a
   ``compact`` event); the manifest is rewritten right after (it is a copy of the journal);
4. the old files removed; files the journal does not name in ``frames/`` and ``darks/``
   (leftovers of an interrupted compaction or write) too;
5. verified again.

A crash before 3 leaves new files the journal does not know (re-running overwrites them);
after 3, old files the journal no longer names (re-running removes them).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m2s2hil.atomic import fsync_dir, write_files_atomic
from m2s2hil.errors import M2S2Error
from m2s2hil.store.cubes import CubeComputer
from m2s2hil.store.frame_files import (
    EncodedJSON,
    decode_tiff,
    dumps,
    encode_cube,
    encode_dark,
    encode_raw,
)
from m2s2hil.store.frame_meta import cube_recipe
from m2s2hil.store.records import DarkRecord, FileRecord, FrameRecord
from m2s2hil.store.session import SessionStore


class CompactError(M2S2Error):
    """A session that cannot be compacted (damaged before, or a new file that reads back wrong)."""


@dataclass
class CompactReport:
    session_id: str
    frames: int = 0
    darks: int = 0
    cubes_dropped: int = 0
    cubes_kept: int = 0
    bytes_before: int = 0
    bytes_after: int = 0
    removed: list[str] = field(default_factory=list)

    def line(self) -> str:
        if not self.frames and not self.darks:
            return f"{self.session_id}: already compact ({self.bytes_after / 1e6:.1f} MB)"
        return (f"{self.session_id}: compacted {self.frames} frame(s) and {self.darks} dark(s), "
                f"{self.cubes_dropped} cube(s) now computed when read, {self.cubes_kept} kept; "
                f"{self.bytes_before / 1e6:.1f} MB -> {self.bytes_after / 1e6:.1f} MB, "
                "verified before and after")


def _is_compressed(data: bytes) -> bool:
    import io

    import tifffile

    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        return tf.pages[0].compression != tifffile.COMPRESSION.NONE


_FILE_RE = re.compile(r"^(?P<name>.+)\.(?P<role>[a-z][a-z0-9_]{0,31})\.(?P<ext>tiff|png|jpg)$")


def _v2(path: str) -> str:
    """The new name of a frame file: ``<event>.<role>.<ext>`` → ``<event>-v2.<role>.<ext>`` (the
    role stays last, where ``sessions repair`` looks for it); a dark ``<id>.tiff`` → ``<id>-v2.tiff``."""
    folder, _, name = path.rpartition("/")
    m = _FILE_RE.match(name)
    new = f"{m['name']}-v2.{m['role']}.{m['ext']}" if m else name.replace(".tiff", "-v2.tiff")
    return f"{folder}/{new}" if folder else new


def _size(store: SessionStore) -> int:
    return sum(r.bytes for fr in store.frames() for r in fr.files.values()) + sum(
        r.bytes for d in store.darks() for r in d.files.values())


class _Plan:
    """New files and journal rows, built before anything is switched."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}  # new relative path -> bytes
        self.frames: dict[str, tuple[dict[str, FileRecord | str], str]] = {}  # id -> (files, meta text)
        self.darks: dict[str, tuple[dict[str, FileRecord | str], str]] = {}


def _plan_frame(store: SessionStore, fr: FrameRecord, plan: _Plan, computer: CubeComputer,
                report: CompactReport) -> None:
    raw_data = store.read_file(fr.files["raw"])
    has_cube = "cube" in fr.files
    cached = has_cube and bool((fr.meta.get("cube") or {}).get("stored"))  # a compressed format's cache
    if _is_compressed(raw_data) and (not has_cube or cached):
        return  # already in the compressed format
    raw, _ = decode_tiff(raw_data)
    keep_cube = False
    cube = None
    if has_cube:
        cube, _ = decode_tiff(store.read_file(fr.files["cube"]))
        try:
            recomputed = computer.compute(store, fr)
            keep_cube = recomputed.tobytes() != np.asarray(cube, dtype=np.float32).tobytes()
        except M2S2Error:
            keep_cube = True
    recipe = cube_recipe(fr.meta.get("processing_method", store.sweep.processing), fr.dark_id,
                         calibrated=fr.meta.get("calibration") is not None, stored=keep_cube)
    meta = {**fr.meta, "storage_format": "compressed", "cube": recipe}
    meta.pop("shape", None)
    text = EncodedJSON(dumps(meta))
    files: dict[str, FileRecord | str] = dict(fr.files)
    new_raw = _v2(fr.files["raw"].path)
    plan.files[new_raw] = encode_raw(raw, text, raw.shape, compress=True)
    if not np.array_equal(decode_tiff(plan.files[new_raw])[0], raw):  # lossless, or nothing switches
        raise CompactError(f"{store.path / new_raw}: the compressed raw does not decode to the same pixels")
    files["raw"] = new_raw
    for role, f in fr.files.items():  # previews, truth labels: the same bytes under the new name
        if role not in ("raw", "cube"):
            plan.files[_v2(f.path)] = store.read_file(f)
            files[role] = _v2(f.path)
    if has_cube:
        del files["cube"]
        if keep_cube:
            m = store.rig.camera.model
            new_cube = _v2(fr.files["cube"].path)
            plan.files[new_cube] = encode_cube(cube, {"event_id": fr.event_id, "cube": meta["cube"],
                                                      "bands_nm": list(m.bands_nm), "dims": "band,y,x"},
                                               int(cube.shape[0]), compress=True)
            files["cube"] = new_cube
            report.cubes_kept += 1
        else:
            report.cubes_dropped += 1
    plan.frames[fr.event_id] = (files, text)
    report.frames += 1


def _plan_dark(store: SessionStore, d: DarkRecord, plan: _Plan, report: CompactReport) -> None:
    data = store.read_file(d.files["master"])
    arr, _ = decode_tiff(data)
    if _is_compressed(data):
        return
    new = _v2(d.files["master"].path)
    meta = {**d.meta, "storage_format": "compressed"}
    plan.files[new] = encode_dark(arr, meta, arr.shape, compress=True)
    plan.darks[d.dark_id] = ({"master": new}, EncodedJSON(dumps(meta)))
    report.darks += 1


def compact_session(root: str | Path, session_id: str) -> CompactReport:
    """Compact one session (see the module docstring); raises CompactError before anything
    is switched if the session or a new file is not right."""
    with SessionStore.open(root, session_id, mode="write") as store:
        report = CompactReport(store.session_id, bytes_before=_size(store))
        problems = [p for p in store.verify() if p.kind != "orphan"]
        if problems:
            raise CompactError(f"{store.session_id}: not compacted, the session has problems; first: "
                               f"{problems[0]} (m2s2hil sessions show {session_id} --verify)")
        plan = _Plan()
        computer = CubeComputer()
        for fr in store.frames():
            _plan_frame(store, fr, plan, computer, report)
        for d in store.darks():
            _plan_dark(store, d, plan, report)
        written = write_files_atomic({store.path / rel: data for rel, data in plan.files.items()}) \
            if plan.files else {}
        for rel, data in plan.files.items():  # read back: the new file holds the old pixels
            if (store.path / rel).read_bytes() != data:
                raise CompactError(f"{store.path / rel}: reads back differently from what was written")

        def rec(v: FileRecord | str) -> dict:
            if isinstance(v, FileRecord):
                return v.model_dump()
            w = written[store.path / v]
            return FileRecord(path=v, sha256=w.sha256, bytes=w.bytes).model_dump()

        if plan.frames or plan.darks:
            now = store.clock.wall()
            with store.journal.transaction() as db:
                for eid, (files, text) in plan.frames.items():
                    db.execute("UPDATE frames SET files = ?, meta = ? WHERE event_id = ?",
                               (dumps({k: rec(v) for k, v in files.items()}), text, eid))
                for did, (files, text) in plan.darks.items():
                    db.execute("UPDATE darks SET files = ?, meta = ? WHERE dark_id = ?",
                               (dumps({k: rec(v) for k, v in files.items()}), text, did))
                db.execute("INSERT INTO events (time, kind, payload) VALUES (?, 'compact', ?)",
                           (now, dumps({"frames": report.frames, "darks": report.darks,
                                        "cubes_dropped": report.cubes_dropped})))
            if (store.path / "manifest.json").is_file():
                store.manifest()
        known = {r.path for fr in store.frames() for r in fr.files.values()}
        known |= {r.path for d in store.darks() for r in d.files.values()}
        for folder in ("frames", "darks"):
            for p in sorted((store.path / folder).glob("*")):
                rel = p.relative_to(store.path).as_posix()
                if p.is_file() and rel not in known:
                    p.unlink()
                    report.removed.append(rel)
            fsync_dir(store.path / folder)
        after = store.verify()
        if after:
            raise CompactError(f"{store.session_id}: verification after compaction failed: {after[0]}")
        report.bytes_after = _size(store)
        return report
