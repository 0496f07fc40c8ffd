"""schemathesis: the OpenAPI schema FastAPI generates is accurate, and no generated input yields a 5xx.

Runs against a real uvicorn (the lifespan has to run for readiness), operation by operation, with schema-valid
and schema-violating (negative) inputs and a bounded number of examples each. ``positive_data_acceptance`` is
excluded: the schema can only say the body is binary, and random schema-valid bytes are, correctly, not an
OpenEXR file (400). (schemathesis' own pytest loader is not used: its lazy fixture mode breaks on pytest 9.)
"""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from schemathesis.specs.openapi.checks import positive_data_acceptance

from service.main import create_app
from tests.service.conftest import settings as app_settings
from tests.service.conftest import uvicorn_server, wait_ready

EXAMPLES = 20


@pytest.fixture(scope="module")
def live_schema() -> Iterator[object]:
    app = create_app(app_settings(queue_size=64))
    with uvicorn_server(app) as url:
        with httpx.Client(base_url=url) as client:
            wait_ready(client)
        yield schemathesis.openapi.from_url(f"{url}/openapi.json")


def operations(schema) -> list:
    return [result.ok() for result in schema.get_all_operations()]


def test_schema_lists_the_whole_api(live_schema) -> None:
    labels = {op.label for op in operations(live_schema)}
    assert labels == {"GET /healthz", "GET /readyz", "GET /v1/models", "POST /v1/reconstruct", "GET /metrics"}


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_every_operation_conforms_to_the_schema(live_schema, mode) -> None:
    for operation in operations(live_schema):
        if mode == GenerationMode.NEGATIVE and not (len(operation.query) or len(operation.body)):
            continue  # nothing to violate: no parameters, no body

        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        def check(case) -> None:
            case.call_and_validate(excluded_checks=[positive_data_acceptance])

        try:
            check()
        except Exception as exc:  # name the operation: hypothesis' report alone does not
            raise AssertionError(f"{operation.label} ({mode}): {exc}") from exc
