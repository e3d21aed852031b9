"""The OpenAPI schema: committed and up to date, and schemathesis finds no server error in it."""

from __future__ import annotations

from pathlib import Path

import schemathesis
from api_support import daemon, small_rig_config
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from m2s2hil.api import openapi_json

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
DOCS = Path(__file__).resolve().parent.parent / "docs" / "openapi.json"


def test_committed_schema_is_current() -> None:
    assert DOCS.is_file(), "docs/openapi.json is missing: python -m m2s2hil.api > docs/openapi.json"
    assert DOCS.read_text() == openapi_json(), (
        "docs/openapi.json is stale: regenerate it with python -m m2s2hil.api > docs/openapi.json"
    )


def test_no_request_the_schema_allows_gets_a_5xx(tmp_path) -> None:
    """Every operation, positive (valid by the schema) and negative (invalid) examples: no 5xx, the
    status codes, content types and bodies as documented. (Driven by hand: schemathesis's pytest
    plugin does not run under pytest 9.)"""
    # A small plan limit and queue keep generated sessions short; whatever is queued gets aborted.
    with daemon(tmp_path / "data", rig_config=small_rig_config(64), max_plan_frames=24, queue_limit=2) as d:
        schema = schemathesis.openapi.from_asgi("/openapi.json", d.client.app)
        failures: list[str] = []
        operations = [r.ok() for r in schema.get_all_operations()]
        assert len(operations) >= 15
        for op in operations:
            for mode, n in ((GenerationMode.POSITIVE, 30), (GenerationMode.NEGATIVE, 15)):

                @settings(max_examples=n, deadline=None, suppress_health_check=list(HealthCheck),
                          database=None, derandomize=True)
                @given(case=op.as_strategy(generation_mode=mode))
                def run(case: schemathesis.Case) -> None:
                    case.call_and_validate(checks=CHECKS)

                try:
                    run()
                except Unsatisfiable:
                    assert mode is GenerationMode.NEGATIVE  # nothing to get wrong: no parameters, no body
                except (Exception, BaseExceptionGroup) as exc:  # one report names every broken operation
                    failures.append(f"{op.label} [{mode.value}]: {exc}")
        assert not failures, "\n\n".join(failures)
