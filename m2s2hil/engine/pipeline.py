"""Capture → process → store, as threads joined by bounded queues.

The engine's thread captures and calls :meth:`Pipeline.submit`; a processing thread
runs ``process(item)`` (dark subtraction, demosaicing, the QC hook) and a storage
thread runs ``store(item)`` (checksummed atomic writes). Each queue holds at most
``depth`` items, so at most ``process_depth + store_depth + store_workers + 2`` frames
are ever in flight (the queues, one in each worker, one being handed over) and memory
stays bounded however slow the disk is. Storage may run in several workers (encoding and
checksumming release the GIL); outcomes then arrive in completion order. A full queue
blocks ``submit`` (backpressure; the time spent blocked is counted in
:attr:`PipelineStats.blocked_s`) rather than growing; with queues sized for the burst the
camera never waits.

Results come back through :meth:`Pipeline.results` as :class:`Outcome` objects
(no pixel data) that the engine consumes in its own thread at safe boundaries, so
all engine state stays single-threaded. A failing item is reported, not retried:
the engine's fault policy decides.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from m2s2hil.protocols.errors import M2S2Error

log = logging.getLogger(__name__)

_STOP = object()


def _log_failure(name: str, stage: str, key: Any, exc: BaseException) -> None:
    """A device or store error is the fault policy's (debug); anything else is a bug, e.g. a race
    between threads, whose traceback the fault's one-line message would lose: logged whole."""
    if isinstance(exc, (M2S2Error, OSError)):
        log.debug("%s: %s failed for %r: %s", name, stage, key, exc)
    else:
        log.error("%s: %s failed for %r", name, stage, key, exc_info=exc)


class PipelineClosed(RuntimeError):
    """submit() on a pipeline that has been stopped."""


@dataclass(frozen=True)
class Outcome:
    """What became of one submitted item. ``key`` identifies it (the event)."""

    key: Any
    ok: bool
    result: Any = None  # what store() returned
    error: BaseException | None = None
    stage: str = "store"  # where it failed: "process" | "store"


@dataclass(frozen=True)
class PipelineStats:
    submitted: int
    processed: int
    stored: int
    failed: int
    in_flight: int
    max_in_flight: int
    max_process_depth: int
    max_store_depth: int
    process_depth: int  # bound
    store_depth: int  # bound
    store_workers: int
    blocked_s: float  # real seconds submit() waited for room
    blocked_count: int
    process_s: float  # real seconds spent in process()
    store_s: float  # real seconds spent in store()

    @property
    def bound(self) -> int:
        """The most items that can be in flight at once (queues, workers, one handed over)."""
        return self.process_depth + self.store_depth + self.store_workers + 2


class Pipeline:
    """Bounded two-stage pipeline; items are ``(key, payload)`` pairs."""

    def __init__(
        self,
        process: Callable[[Any, Any], Any],
        store: Callable[[Any, Any], Any],
        *,
        process_depth: int = 4,
        store_depth: int = 4,
        store_workers: int = 1,
        name: str = "pipeline",
    ) -> None:
        if process_depth < 1 or store_depth < 1:
            raise ValueError("queue depths must be at least 1")
        if store_workers < 1:
            raise ValueError("store_workers must be at least 1")
        self.store_workers = store_workers
        self._process = process
        self._store = store
        self.process_depth = process_depth
        self.store_depth = store_depth
        self.name = name
        self._pq: queue.Queue = queue.Queue(maxsize=process_depth)
        self._sq: queue.Queue = queue.Queue(maxsize=store_depth)
        self._results: queue.SimpleQueue[Outcome] = queue.SimpleQueue()
        self._cond = threading.Condition()
        self._in_flight = 0
        self._counts = dict(
            submitted=0, processed=0, stored=0, failed=0, max_in_flight=0, max_pq=0, max_sq=0,
            blocked_count=0,
        )
        self._times = dict(blocked_s=0.0, process_s=0.0, store_s=0.0)
        self._threads: list[threading.Thread] = []
        self._stopped = False

    # -- life cycle ------------------------------------------------------------------
    def start(self) -> Pipeline:
        if self._threads:
            return self
        self._threads = [
            threading.Thread(target=self._process_loop, name=f"{self.name}-process", daemon=True),
            *(threading.Thread(target=self._store_loop, name=f"{self.name}-store{i}", daemon=True)
              for i in range(self.store_workers)),
        ]
        for t in self._threads:
            t.start()
        return self

    def submit(self, key: Any, payload: Any) -> None:
        """Hand an item to the processing stage; blocks while the queue is full."""
        if self._stopped:
            raise PipelineClosed(f"{self.name} is stopped")
        if not self._threads:
            self.start()
        with self._cond:
            self._in_flight += 1
            self._counts["submitted"] += 1
            self._counts["max_in_flight"] = max(self._counts["max_in_flight"], self._in_flight)
        try:
            self._pq.put_nowait((key, payload))
        except queue.Full:
            t0 = time.perf_counter()
            self._pq.put((key, payload))
            with self._cond:
                self._times["blocked_s"] += time.perf_counter() - t0
                self._counts["blocked_count"] += 1
        with self._cond:
            self._counts["max_pq"] = max(self._counts["max_pq"], self._pq.qsize())

    def drain(self, timeout: float | None = None) -> bool:
        """Wait (real time) until every submitted item is stored or failed."""
        with self._cond:
            return self._cond.wait_for(lambda: self._in_flight == 0, timeout=timeout)

    def stop(self, timeout: float | None = 30.0) -> None:
        """Finish what is queued, then end the worker threads."""
        if self._stopped:
            return
        self._stopped = True
        if self._threads:
            self._pq.put(_STOP)
            for t in self._threads:
                t.join(timeout)

    @property
    def in_flight(self) -> int:
        with self._cond:
            return self._in_flight

    def results(self) -> list[Outcome]:
        """Outcomes ready now (non-blocking)."""
        out: list[Outcome] = []
        while True:
            try:
                out.append(self._results.get_nowait())
            except queue.Empty:
                return out

    def stats(self) -> PipelineStats:
        with self._cond:
            c, t = dict(self._counts), dict(self._times)
            inf = self._in_flight
        return PipelineStats(
            submitted=c["submitted"], processed=c["processed"], stored=c["stored"], failed=c["failed"],
            in_flight=inf, max_in_flight=c["max_in_flight"], max_process_depth=c["max_pq"],
            max_store_depth=c["max_sq"], process_depth=self.process_depth, store_depth=self.store_depth,
            store_workers=self.store_workers,
            blocked_s=t["blocked_s"], blocked_count=c["blocked_count"], process_s=t["process_s"],
            store_s=t["store_s"],
        )

    # -- workers ---------------------------------------------------------------------
    def _finish(self, outcome: Outcome) -> None:
        self._results.put(outcome)
        with self._cond:
            self._in_flight -= 1
            if outcome.ok:
                self._counts["stored"] += 1
            else:
                self._counts["failed"] += 1
            self._cond.notify_all()

    def _process_loop(self) -> None:
        while True:
            item = self._pq.get()
            if item is _STOP:
                for _ in range(self.store_workers):
                    self._sq.put(_STOP)
                return
            key, payload = item
            del item
            t0 = time.perf_counter()
            try:
                processed = self._process(key, payload)
            except BaseException as exc:  # reported to the engine, never dropped
                _log_failure(self.name, "process", key, exc)
                self._finish(Outcome(key, ok=False, error=exc, stage="process"))
                continue
            finally:
                del payload
                with self._cond:
                    self._times["process_s"] += time.perf_counter() - t0
            with self._cond:
                self._counts["processed"] += 1
            self._sq.put((key, processed))
            del processed
            with self._cond:
                self._counts["max_sq"] = max(self._counts["max_sq"], self._sq.qsize())

    def _store_loop(self) -> None:
        while True:
            item = self._sq.get()
            if item is _STOP:
                return
            key, processed = item
            del item
            t0 = time.perf_counter()
            try:
                result = self._store(key, processed)
            except BaseException as exc:
                _log_failure(self.name, "store", key, exc)
                outcome = Outcome(key, ok=False, error=exc, stage="store")
            else:
                outcome = Outcome(key, ok=True, result=result)
            finally:
                del processed
                with self._cond:
                    self._times["store_s"] += time.perf_counter() - t0
            self._finish(outcome)
