"""The OpenAPI schema: committed and up to date, and it says what the daemon does.

schemathesis runs every phase (examples, coverage, fuzzing, stateful) with every check against
a daemon with a token, and the examples and a stateful walk against one without (the inputs
coverage and fuzzing generate meet the same handlers with or without a token: run once, they
are half of the suite's slowest test), driven through its Python API (its pytest plugin does
not run under pytest 9). Bounded: few examples per operation, a small plan limit so generated
sessions are short, one event read from each stream."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import schemathesis
from api_support import TOKEN, daemon, small_rig_config
from schemathesis.config import SchemathesisConfig
from schemathesis.engine import Status, events, from_schema

from m2s2hil.api import app as api_app
from m2s2hil.api import openapi_json

DOCS = Path(__file__).resolve().parent.parent / "docs" / "openapi.json"
#: Every router of the daemon, the console's included.
CORE = [*api_app.GUARDED_ROUTERS, *api_app.OPEN_ROUTERS]
#: The live view is an endless stream unless asked for a number of frames (no event count
#: bounds it as for SSE): tests/test_console_api.py reads it, bounded.
ENDLESS = {"/camera/live.mjpeg"}
#: Schema-valid bodies a daemon may still refuse with 422, because the answer depends on the rig
#: (its lamp names) or on the picture (a white reference that saturates or is too dim).
RIG_DEPENDENT = ["set_lamps", "take_white",
                 # the soft limits, the homing policy, the number of bands are the rig file's
                 "go_to", "jog", "set_origin", "home_axis", "update_live",
                 # a point or region outside the sensor (its size is the rig's)
                 "frame_spectrum", "live_spectrum"]
#: A sweep that is valid JSON-Schema-wise may still be refused with 422: the frame limit
#: (a product of list lengths and the azimuth step), the builds a satellite has and what the
#: rig can reach depend on the configuration, which a schema cannot state.
SWEEP_STATUSES = ["2xx", "401", "403", "404", "409", "422", "429", "5xx"]


def test_committed_schema_is_current() -> None:
    assert DOCS.is_file(), "docs/openapi.json is missing: python -m m2s2hil.api > docs/openapi.json"
    assert DOCS.read_text() == openapi_json(), (
        "docs/openapi.json is stale: regenerate it with python -m m2s2hil.api > docs/openapi.json"
    )


def _route_names(routes: list) -> list[str]:
    """Operation ids of ``routes``, into the routers a router includes (FastAPI keeps those as one route)."""
    names: list[str] = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        names += _route_names(inner.routes) if inner is not None else [route.name]
    return names


ALL_PHASES = ("examples", "coverage", "fuzzing", "stateful")


def _failures(app, token: str | None, phases: tuple[str, ...]) -> tuple[list[str], dict[str, int]]:
    cfg: dict = {
        "base-url": "http://127.0.0.1:8750",  # a Host the daemon serves
        "max-stream-events": 1,  # an event stream of a waiting session never ends by itself
        "generation": {"max-examples": 8, "deterministic": True, "mode": "all", "database": "none"},
        "phases": {"stateful": {"max-steps": 12},
                   **{p: {"enabled": False} for p in ALL_PHASES if p not in phases}},
        # By operation id: schemathesis ORs include-path with include-method, so a path and a
        # method would give these statuses to every POST and hide what they refuse.
        "operations": [{"include-operation-id": op,
                        "checks": {"positive_data_acceptance": {"expected-statuses": SWEEP_STATUSES}}}
                       # every operation that takes a sweep (darks: "at the exposures a plan uses"; a
                       # synthetic render: the rig's elevations and the frame limit)
                       for op in ("create_session", "estimate_plan", "take_darks", "create_synthetic",
                                  *RIG_DEPENDENT)],
    }
    if token:
        cfg["auth"] = {"openapi": {"HTTPBearer": {"bearer": token}}}
    # The schema this daemon serves, its own operations only.
    ids = {name for router in CORE for name in _route_names(router.routes)}
    doc = copy.deepcopy(app.openapi())
    doc["paths"] = {path: ops for path, item in doc["paths"].items() if path not in ENDLESS
                    if (ops := {m: op for m, op in item.items() if op.get("operationId") in ids})}
    schema = schemathesis.openapi.from_dict(doc, config=SchemathesisConfig.from_dict(cfg))
    schema.app, schema.location = app, "/openapi.json"
    failures: list[str] = []
    scenarios: dict[str, int] = {}
    for ev in from_schema(schema).execute():
        if isinstance(ev, events.ScenarioFinished):
            scenarios[str(ev.phase)] = scenarios.get(str(ev.phase), 0) + 1
            for nodes in ev.recorder.checks.values():
                failures += [f"{ev.phase} {ev.label} {n.name}: {n.failure_info.failure}" for n in nodes
                             if n.status == Status.FAILURE and n.failure_info is not None]
        elif isinstance(ev, (events.NonFatalError, events.FatalError)):
            failures.append(f"error: {ev.info.format()}")
    return sorted(set(failures)), scenarios


@pytest.mark.slow  # 40 s of CPU with a token, 6 s without
@pytest.mark.timeout(600)  # generous: a loaded machine stretches it, it does not fail it
@pytest.mark.parametrize(("token", "phases"), [(None, ("examples", "stateful")), (TOKEN, ALL_PHASES)],
                         ids=["no-token", "token"])
def test_schemathesis_all_checks_and_stateful_find_nothing(tmp_path, token, phases) -> None:
    with daemon(tmp_path / "data", token=token, rig_config=small_rig_config(64), max_plan_frames=24,
                queue_limit=2) as d:
        failures, scenarios = _failures(d.client.app, token, phases)
    assert not failures, "\n\n".join(failures)
    assert set(phases) <= set(scenarios), scenarios
    assert scenarios["stateful"] >= 1
