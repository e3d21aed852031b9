"""The daemon's metrics: fed from engine events, exposed through prometheus_client."""

from prometheus_client.parser import text_string_to_metric_families

from m2s2hil.daemon.prometheus import Metrics
from m2s2hil.engine.state import FaultInfo, FaultRecorded, FrameStored, RunState, SessionFinished


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for fam in text_string_to_metric_families(text) for s in fam.samples}


def test_events_and_scrape_time_gauges_reach_the_exposition():
    m = Metrics()
    m.gauge("m2s2hil_queue_depth", "waiting", lambda: {(("queue", "sessions"),): 2.0})
    m.gauge("m2s2hil_broken", "a gauge that cannot be read", lambda: 1 / 0)
    for i in range(3):
        m.observe(FrameStored(seq=i, time_s=0.0, wall=0.0))
    m.observe(FaultRecorded(seq=3, time_s=0.0, wall=0.0, fault=FaultInfo(1.0, "timeout", "retry", "late")))
    m.observe(SessionFinished(seq=4, time_s=0.0, wall=0.0, state=RunState.ABORTED, duration_s=75.0))
    m.count_estop()
    m.sse_delta(+2)
    m.sse_delta(-1)
    s = _samples(m.render())
    assert s[("m2s2hil_frames_captured_total", ())] == 3
    assert s[("m2s2hil_faults_total", (("fault_class", "timeout"),))] == 1
    assert s[("m2s2hil_faults_total", (("fault_class", "alarm"),))] == 0  # every class, even at 0
    assert s[("m2s2hil_sessions_finished_total", (("state", "aborted"),))] == 1
    assert s[("m2s2hil_session_duration_seconds_bucket", (("le", "60.0"),))] == 0
    assert s[("m2s2hil_session_duration_seconds_bucket", (("le", "300.0"),))] == 1
    assert s[("m2s2hil_session_duration_seconds_sum", ())] == 75.0
    assert s[("m2s2hil_emergency_stops_total", ())] == 1
    assert s[("m2s2hil_sse_clients", ())] == 1
    assert s[("m2s2hil_queue_depth", (("queue", "sessions"),))] == 2
    assert not any(name.startswith("m2s2hil_broken") or name.endswith("_created") for name, _ in s)


def test_two_daemons_in_one_process_count_apart():
    a, b = Metrics(), Metrics()
    a.observe(FrameStored(seq=0, time_s=0.0, wall=0.0))
    assert _samples(b.render())[("m2s2hil_frames_captured_total", ())] == 0
