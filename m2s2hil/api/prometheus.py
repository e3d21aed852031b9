"""Daemon metrics in the Prometheus text exposition format (version 0.0.4).

Counters and histograms are fed from the engines' events (:meth:`Metrics.observe`);
gauges (queue depths, running sessions, pipeline depth) are read at scrape time from
callables the manager registers. Kept to the few series an operator alerts on:

- ``m2s2hil_frames_captured_total``: frames stored by this daemon.
- ``m2s2hil_faults_total{fault_class}``: faults met, by class (all classes always present).
- ``m2s2hil_sessions_finished_total{state}``: completed / aborted / failed.
- ``m2s2hil_session_duration_seconds``: histogram of the active time of finished runs
  (engine clock, pauses excluded).
- ``m2s2hil_queue_depth{queue}``: sessions waiting (``sessions``), frames in the running
  session's processing pipeline (``pipeline``).
- ``m2s2hil_sessions_running``, ``m2s2hil_queue_held``, ``m2s2hil_sse_clients``,
  ``m2s2hil_emergency_stops_total``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from m2s2hil.engine.fault_policy import FAULT_CLASSES
from m2s2hil.engine.state import EngineEvent, FaultRecorded, FrameStored, SessionFinished

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
DURATION_BUCKETS = (10.0, 60.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
FINAL_STATES = ("completed", "aborted", "failed")


def _escape(v: str) -> str:
    return v.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _num(x: float) -> str:
    if math.isinf(x):
        return "+Inf" if x > 0 else "-Inf"
    if math.isnan(x):
        return "NaN"
    return repr(float(x)) if not float(x).is_integer() else str(int(x))


def _labels(labels: dict[str, str]) -> str:
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels.items()) + "}"


class Metrics:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.frames = 0
        self.faults = dict.fromkeys(FAULT_CLASSES, 0)
        self.finished = dict.fromkeys(FINAL_STATES, 0)
        self.estops = 0
        self.sse_clients = 0
        self._buckets = [0] * len(DURATION_BUCKETS)
        self._dur_sum = 0.0
        self._dur_count = 0
        self._gauges: dict[str, tuple[str, Callable[[], dict[tuple[tuple[str, str], ...], float]]]] = {}

    # ------------------------------------------------------------------ feeding
    def observe(self, ev: EngineEvent) -> None:
        """Engine event subscriber (called in the engine's thread: cheap and lock-short)."""
        with self._lock:
            if isinstance(ev, FrameStored):
                self.frames += 1
            elif isinstance(ev, FaultRecorded):
                fc = ev.fault.fault_class
                self.faults[fc] = self.faults.get(fc, 0) + 1
            elif isinstance(ev, SessionFinished):
                st = ev.state.value
                self.finished[st] = self.finished.get(st, 0) + 1
                d = max(0.0, float(ev.duration_s))
                self._dur_sum += d
                self._dur_count += 1
                for i, le in enumerate(DURATION_BUCKETS):
                    if d <= le:
                        self._buckets[i] += 1

    def count_estop(self) -> None:
        with self._lock:
            self.estops += 1

    def sse_delta(self, n: int) -> None:
        with self._lock:
            self.sse_clients += n

    def gauge(self, name: str, help_text: str,
              read: Callable[[], dict[tuple[tuple[str, str], ...], float]]) -> None:
        """Register a gauge read at scrape time: ``read()`` -> {label pairs: value}."""
        self._gauges[name] = (help_text, read)

    # ------------------------------------------------------------------ exposition
    def render(self) -> str:
        out: list[str] = []

        def family(name: str, kind: str, help_text: str,
                   samples: list[tuple[str, dict[str, str], float]]) -> None:
            out.append(f"# HELP {name} {help_text}")
            out.append(f"# TYPE {name} {kind}")
            for suffix, labels, value in samples:
                out.append(f"{name}{suffix}{_labels(labels)} {_num(value)}")

        with self._lock:
            frames, faults, finished = self.frames, dict(self.faults), dict(self.finished)
            buckets, dsum, dcount = list(self._buckets), self._dur_sum, self._dur_count
            estops, sse = self.estops, self.sse_clients
        family("m2s2hil_frames_captured_total", "counter", "Frames stored by this daemon.",
               [("", {}, frames)])
        family("m2s2hil_faults_total", "counter", "Faults met by the capture engine, by fault class.",
               [("", {"fault_class": fc}, n) for fc, n in sorted(faults.items())])
        family("m2s2hil_sessions_finished_total", "counter", "Session runs that ended, by final state.",
               [("", {"state": st}, n) for st, n in sorted(finished.items())])
        hist = [("_bucket", {"le": _num(le)}, c) for le, c in zip(DURATION_BUCKETS, buckets, strict=True)]
        hist += [("_bucket", {"le": "+Inf"}, dcount), ("_sum", {}, dsum), ("_count", {}, dcount)]
        family("m2s2hil_session_duration_seconds", "histogram",
               "Active duration of finished session runs (engine clock, pauses excluded).", hist)
        family("m2s2hil_emergency_stops_total", "counter", "Emergency stops requested.", [("", {}, estops)])
        family("m2s2hil_sse_clients", "gauge", "Open event streams.", [("", {}, sse)])
        for name, (help_text, read) in sorted(self._gauges.items()):
            try:
                values = read()
            except Exception:  # a gauge that cannot be read is left out, not fatal to the scrape
                continue
            family(name, "gauge", help_text, [("", dict(k), v) for k, v in values.items()])
        return "\n".join(out) + "\n"
