"""Bounded load and lifecycle against `gradsep serve` in its own process (real uvicorn, real SIGTERM).

* 8 concurrent clients x 20 frames of 256x256 (l2, to stay fast) on a 1-slot, 4-deep queue: every request
  gets 200 or 503 + Retry-After, every 200 is the right image for *its* frame and request id, the server's own
  counters agree with the clients' tallies (nothing lost), and resident memory stays bounded.
* Graceful shutdown: SIGTERM while an inference runs still delivers its 200, then the process exits 0.
"""

from __future__ import annotations

import re
import signal
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from tests.service.conftest import rss_bytes, server_process
from tests.service.frames import decode, expected_sum, frame_bytes, rgb

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc for memory")

CLIENTS, PER_CLIENT, SIZE, DISTINCT = 8, 20, 256, 16
MiB = 1024 * 1024


def served_count(url: str, status: int) -> int:
    text = httpx.get(f"{url}/metrics").text
    pattern = rf'gradsep_http_requests_total\{{method="POST",route="/v1/reconstruct",status="{status}"\}} (\S+)'
    match = re.search(pattern, text)
    return int(float(match.group(1))) if match else 0


@pytest.mark.slow
def test_bounded_load_every_request_answered_correctly_with_bounded_memory(tmp_path):
    frames = [frame_bytes(height=SIZE, width=SIZE, seed=s) for s in range(DISTINCT)]
    expected = [expected_sum(height=SIZE, width=SIZE, seed=s) for s in range(DISTINCT)]
    env = {"GRADSEP_CONCURRENCY": "1", "GRADSEP_QUEUE_SIZE": "4", "GRADSEP_LOG_LEVEL": "warning"}
    argv = ["-m", "gradsep", "serve", "--host", "127.0.0.1", "--port", "{port}"]
    with server_process(argv, env, tmp_path / "server.log") as (url, proc):
        with httpx.Client(base_url=url, timeout=120) as http:  # warm the allocator and code paths first
            for k in range(4):
                assert http.post("/v1/reconstruct", params={"method": "l2"}, content=frames[k],
                                 headers={"Content-Type": "image/x-exr"}).status_code == 200
        baseline = rss_bytes(proc.pid)

        def run_client(c: int) -> Counter:
            tally: Counter = Counter()
            with httpx.Client(base_url=url, timeout=120) as http:
                for i in range(PER_CLIENT):
                    k, rid = (c * PER_CLIENT + i) % DISTINCT, f"load-{c}-{i}"
                    try:
                        r = http.post("/v1/reconstruct", params={"method": "l2"}, content=frames[k],
                                      headers={"Content-Type": "image/x-exr", "X-Request-ID": rid})
                    except httpx.TransportError as exc:
                        tally[f"lost: {type(exc).__name__}"] += 1
                        continue
                    assert r.headers["x-request-id"] == rid
                    if r.status_code == 200:
                        np.testing.assert_allclose(rgb(decode(r.content)[0]), expected[k], rtol=1e-4, atol=1e-4)
                    elif r.status_code == 503:
                        assert int(r.headers["retry-after"]) >= 1
                        assert r.json()["error"]["code"] == "queue_full"
                    tally[r.status_code] += 1
            return tally

        with ThreadPoolExecutor(CLIENTS) as pool:
            tallies = list(pool.map(run_client, range(CLIENTS)))
        total = sum(tallies, Counter())
        assert set(total) <= {200, 503}, total  # nothing else, nothing lost
        assert total[200] + total[503] == CLIENTS * PER_CLIENT
        assert total[200] >= CLIENTS  # the queue drains: load is shed, not everything refused
        assert served_count(url, 200) == total[200] + 4 and served_count(url, 503) == total[503]

        # Memory: at most concurrency + queue + connections bodies/frames (~5 MB each) live at once; a leak
        # of one frame per request would add ~800 MB over 160 requests.
        peak, after = rss_bytes(proc.pid, "VmHWM"), rss_bytes(proc.pid)
        print(f"RSS MiB: baseline {baseline / MiB:.0f}, peak {peak / MiB:.0f}, after {after / MiB:.0f}; {total}")
        assert peak - baseline < 300 * MiB, (baseline / MiB, peak / MiB)
        assert after - baseline < 150 * MiB, (baseline / MiB, after / MiB)


def test_sigterm_lets_the_in_flight_inference_finish(tmp_path):
    env = {"GRADSEP_TEST_SLOW_SECONDS": "2", "GRADSEP_LOG_LEVEL": "warning"}
    argv = ["-m", "uvicorn", "tests.service.slow_app:create", "--factory", "--host", "127.0.0.1", "--port",
            "{port}", "--timeout-graceful-shutdown", "30"]
    with server_process(argv, env, tmp_path / "server.log") as (url, proc):
        result: dict = {}

        def request() -> None:
            with httpx.Client(base_url=url, timeout=60) as http:
                # l2 named: the default follows model.policy (oidn for this frame), whose answer is not exact
                result["response"] = http.post("/v1/reconstruct", params={"method": "l2"},
                                               content=frame_bytes(seed=21), headers={"Content-Type": "image/x-exr"})

        thread = threading.Thread(target=request)
        thread.start()
        deadline = time.monotonic() + 30
        while "gradsep_inference_running 1.0" not in httpx.get(f"{url}/metrics").text:
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.02)
        proc.terminate()  # SIGTERM, mid-inference
        thread.join(timeout=60)
        assert proc.wait(timeout=60) in (0, -signal.SIGTERM)  # uvicorn re-raises it after shutting down
    response = result["response"]
    assert response.status_code == 200
    np.testing.assert_allclose(rgb(decode(response.content)[0]), expected_sum(seed=21), rtol=1e-4, atol=1e-4)
