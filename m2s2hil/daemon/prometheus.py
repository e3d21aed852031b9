"""Daemon metrics for Prometheus, kept in a ``prometheus_client`` registry of their own.

Counters and the histogram are fed from the engines' events (:meth:`Metrics.observe`);
gauges (queue depths, running sessions, the queue hold) are read at scrape time from
callables the manager registers. Kept to the few series an operator alerts on:

- ``m2s2hil_frames_captured_total``: frames stored by this daemon.
- ``m2s2hil_faults_total{fault_class}``: faults met, by class (all classes always present).
- ``m2s2hil_sessions_finished_total{state}``: completed / completed_with_gaps / aborted / failed.
- ``m2s2hil_session_duration_seconds``: histogram of the active time of finished runs
  (engine clock, pauses excluded).
- ``m2s2hil_queue_depth{queue}``: sessions waiting (``sessions``), frames in the running
  session's processing pipeline (``pipeline``).
- ``m2s2hil_sessions_running``, ``m2s2hil_queue_held``, ``m2s2hil_sse_clients``,
  ``m2s2hil_emergency_stops_total``.

Each :class:`Metrics` has its own ``CollectorRegistry`` (not the process-wide default), so
several daemons in one process (the tests) never share counts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import prometheus_client
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4

from m2s2hil.engine.fault_policy import FAULT_CLASSES
from m2s2hil.engine.state import EngineEvent, FaultRecorded, FrameStored, SessionFinished

CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4
DURATION_BUCKETS = (10.0, 60.0, 300.0, 900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
FINAL_STATES = ("completed", "completed_with_gaps", "aborted", "failed")

# No ``*_created`` series: a counter's creation time only doubles the series count here.
prometheus_client.disable_created_metrics()

GaugeReader = Callable[[], dict[tuple[tuple[str, str], ...], float]]


class _ScrapeTimeGauges:
    """Gauges whose values are read when Prometheus scrapes (a custom collector)."""

    def __init__(self) -> None:
        self.gauges: dict[str, tuple[str, GaugeReader]] = {}

    def collect(self) -> Iterator[Metric]:
        for name, (help_text, read) in sorted(self.gauges.items()):
            try:
                values = read()
            except Exception:  # a gauge that cannot be read is left out, not fatal to the scrape
                continue
            labels = sorted({k for pairs in values for k, _ in pairs})
            family = GaugeMetricFamily(name, help_text, labels=labels)
            for pairs, value in values.items():
                given = dict(pairs)
                family.add_metric([given.get(k, "") for k in labels], float(value))
            yield family


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        reg = self.registry
        self._frames = Counter("m2s2hil_frames_captured", "Frames stored by this daemon.", registry=reg)
        self._faults = Counter("m2s2hil_faults", "Faults met by the capture engine, by fault class.",
                               ["fault_class"], registry=reg)
        for fc in FAULT_CLASSES:
            self._faults.labels(fc)
        self._finished = Counter("m2s2hil_sessions_finished", "Session runs that ended, by final state.",
                                 ["state"], registry=reg)
        for st in FINAL_STATES:
            self._finished.labels(st)
        self._duration = Histogram(
            "m2s2hil_session_duration_seconds",
            "Active duration of finished session runs (engine clock, pauses excluded).",
            buckets=DURATION_BUCKETS, registry=reg,
        )
        self._estops = Counter("m2s2hil_emergency_stops", "Emergency stops requested.", registry=reg)
        self._sse = Gauge("m2s2hil_sse_clients", "Open event streams.", registry=reg)
        self._scrape_time = _ScrapeTimeGauges()
        reg.register(self._scrape_time)

    # ------------------------------------------------------------------ feeding
    def observe(self, ev: EngineEvent) -> None:
        """Engine event subscriber (called in the engine's thread: cheap, no I/O)."""
        if isinstance(ev, FrameStored):
            self._frames.inc()
        elif isinstance(ev, FaultRecorded):
            self._faults.labels(ev.fault.fault_class).inc()
        elif isinstance(ev, SessionFinished):
            self._finished.labels(ev.state.value).inc()
            self._duration.observe(max(0.0, float(ev.duration_s)))

    def count_estop(self) -> None:
        self._estops.inc()

    def sse_delta(self, n: int) -> None:
        self._sse.inc(n)

    def gauge(self, name: str, help_text: str, read: GaugeReader) -> None:
        """Register a gauge read at scrape time: ``read()`` -> {label pairs: value}."""
        self._scrape_time.gauges[name] = (help_text, read)

    # ------------------------------------------------------------------ exposition
    def render(self) -> str:
        """The registry in the Prometheus text format 0.0.4."""
        return generate_latest(self.registry).decode("utf-8")
