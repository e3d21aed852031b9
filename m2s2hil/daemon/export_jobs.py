"""Exports as jobs: started by a request, run in a thread of their own, followed by polling.

An export takes from seconds to minutes (46 s for a Zarr store of a 36-frame session on the
shared machine), longer than a browser should hold a request open. :meth:`ExportJobs.start`
answers at once with the job; the job runs :func:`~.export_lock.export_once` (so it excludes
the CLI's and the synchronous endpoint's exports of the same folder) and records its phase,
elapsed time, progress (frames ``done`` of ``total``, told by the export at most every 0.5 s)
and result; its start, end or failure also goes to the activity log (kind ``action``, with
``export_progress`` = 0 at the start and the fraction reached at the end or failure). One job runs
at a time: while one runs, another is refused (409, :mod:`.busy` for the same session and
layout). Jobs are kept in memory, the last :data:`KEEP` of them; the export itself is on disk
(``<data root>/exports/<session>/<layout>/``) and downloadable as a zip (:func:`zip_chunks`).
"""

from __future__ import annotations

import secrets
import threading
import time
import zipfile
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .errors import Conflict

if TYPE_CHECKING:
    from .manager import SessionManager

KEEP = 32


@dataclass
class ExportJob:
    job_id: str
    session_id: str
    layout: str
    overwrite: bool
    state: str = "running"  # running → done | failed
    phase: str = "starting"  # starting → exporting → done | failed
    started: float = field(default_factory=time.time)
    finished: float | None = None
    frames: int | None = None
    done: int = 0  # frames written so far (the export's progress callback)
    result: dict[str, Any] | None = None
    error: str | None = None
    _t0: float = field(default_factory=time.monotonic)
    _t1: float | None = None

    @property
    def fraction(self) -> float:
        return 1.0 if self.state == "done" else round(self.done / self.frames, 3) if self.frames else 0.0

    def progress(self, done: int, total: int) -> None:
        self.done, self.frames = done, total  # one writer (the job's thread); ints: no lock needed

    def to_dict(self) -> dict[str, Any]:
        end = self._t1 if self._t1 is not None else time.monotonic()
        return {"job_id": self.job_id, "session_id": self.session_id, "layout": self.layout,
                "state": self.state, "phase": self.phase, "started": self.started, "finished": self.finished,
                "elapsed_s": round(end - self._t0, 1), "frames": self.frames, "done": self.done,
                "total": self.frames, "fraction": self.fraction, "result": self.result,
                "error": self.error, "url": f"/exports/jobs/{self.job_id}",
                "download_url": (f"/sessions/{self.session_id}/export/{self.layout}.zip"
                                 if self.state == "done" else None)}


class ExportJobs:
    def __init__(self, manager: SessionManager) -> None:
        self._mg = manager
        self._lock = threading.Lock()
        self._jobs: OrderedDict[str, ExportJob] = OrderedDict()

    def out_dir(self, session_id: str, layout: str) -> Path:
        return self._mg.root / "exports" / session_id / layout

    def start(self, session_id: str, layout: str, *, overwrite: bool = False) -> ExportJob:
        """Check the session can be exported, claim the (session, layout) and start the job."""
        with self._mg.reads.reading(session_id) as store:  # UnknownSession (404) first
            frames = len(store.frames())
        if not frames:
            raise Conflict(f"session {session_id} has no frames to export yet")
        with self._lock:  # one at a time: an export is disk- and CPU-heavy, beside a capture too
            running = next((j for j in self._jobs.values() if j.state == "running"), None)
        if running is not None:
            raise Conflict(f"the {running.layout} export of {running.session_id} is running (job "
                           f"{running.job_id}): one export job at a time, wait for it to finish")
        busy = self._mg.busy.start(f"export:{session_id}:{layout}", f"the {layout} export of {session_id}")
        job = ExportJob(secrets.token_hex(6), session_id, layout, overwrite, frames=frames)
        # the keys are there from the start: GET /busy may serialise the dict while progress updates it
        busy.detail.update(job_id=job.job_id, done=0, total=frames, fraction=0.0)
        with self._lock:
            self._jobs[job.job_id] = job
            while len(self._jobs) > KEEP:
                self._jobs.popitem(last=False)
        self._mg.activity.record("action", f"export {layout} of {session_id} started ({frames} frames)",
                                 session_id=session_id, job_id=job.job_id, export_progress=0.0)
        threading.Thread(target=self._run, args=(job, busy), name=f"export-{job.job_id}", daemon=True).start()
        return job

    def _run(self, job: ExportJob, busy: Any) -> None:
        from m2s2hil.store.export import ExportError

        from .export_lock import ExportBusy, export_once

        out = self.out_dir(job.session_id, job.layout)
        try:
            job.phase = "exporting"
            with self._mg.reads.reading(job.session_id) as store:
                res = export_once(store, out, job.layout, overwrite=job.overwrite, fresh=job.overwrite,
                                  progress=lambda k, n: self._progress(job, busy, k, n))
            job.result = {"folder": str(out), "images": res.images, "files": len(res.files)}
            job.state = job.phase = "done"
            self._mg.activity.record("action", f"export {job.layout} of {job.session_id} done: {res.images} "
                                     f"images, {len(res.files)} files", session_id=job.session_id,
                                     job_id=job.job_id, export_progress=1.0)
        except Exception as exc:
            hint = (" (it is exported already: ask with overwrite)"
                    if isinstance(exc, ExportError) and out.exists() and not job.overwrite else "")
            busy_now = " (another export of it runs)" if isinstance(exc, ExportBusy) else ""
            job.error = f"{type(exc).__name__}: {exc}{hint}{busy_now}"
            job.state = job.phase = "failed"
            self._mg.activity.record("action", f"export {job.layout} of {job.session_id} failed: {job.error}",
                                     level="error", session_id=job.session_id, job_id=job.job_id,
                                     export_progress=job.fraction)
        finally:
            job.finished, job._t1 = time.time(), time.monotonic()
            self._mg.busy.end(busy)

    @staticmethod
    def _progress(job: ExportJob, busy: Any, done: int, total: int) -> None:
        job.progress(done, total)
        busy.detail.update(done=done, total=total, fraction=job.fraction)  # /busy shows it too

    def get(self, job_id: str) -> ExportJob | None:
        with self._lock:
            return self._jobs.get(job_id)

    def items(self) -> list[dict[str, Any]]:
        with self._lock:
            return [j.to_dict() for j in reversed(self._jobs.values())]


class _Sink:
    """A write-only stream that hands its bytes out in pieces (zipfile writes to it)."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def write(self, b: bytes) -> int:
        self.buf += b
        return len(b)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out, self.buf = bytes(self.buf), bytearray()
        return out


def zip_chunks(folder: Path, arc_root: str, chunk: int = 1 << 20) -> Iterator[bytes]:
    """``folder`` as a zip (stored: the frames are compressed already), produced as it is read, so
    a large export is never held in memory or written twice."""
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:  # type: ignore[call-overload]
        for path in sorted(p for p in folder.rglob("*") if p.is_file() and not p.is_symlink()):
            arc = f"{arc_root}/{path.relative_to(folder).as_posix()}"
            with path.open("rb") as src, zf.open(arc, "w", force_zip64=True) as dst:
                while block := src.read(chunk):
                    dst.write(block)
                    if len(sink.buf) >= chunk:
                        yield sink.take()
            yield sink.take()
    yield sink.take()
