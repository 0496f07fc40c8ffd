"""App factory for the graceful-shutdown test: every reconstruction first sleeps GRADSEP_TEST_SLOW_SECONDS.

Run as ``uvicorn tests.service.slow_app:create --factory``; the delay gives the test a window to send SIGTERM
while an inference is certainly in flight, without a test hook in the service itself.
"""

from __future__ import annotations

import os
import time

from fastapi import FastAPI

import gradsep.service.pipeline
from gradsep.service.main import create_app
from gradsep.service.settings import Settings


def create() -> FastAPI:
    real = gradsep.service.pipeline.reconstruct
    delay = float(os.environ.get("GRADSEP_TEST_SLOW_SECONDS", "2"))

    def slow(frame, method, alpha, models=None):  # noqa: ANN001, ANN202
        time.sleep(delay)
        return real(frame, method, alpha, models)

    gradsep.service.pipeline.reconstruct = slow
    return create_app(Settings(warm_up=False))
