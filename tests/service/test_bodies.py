"""Request bodies within a bound (service/bodies.py): the pool is never overdrawn, a body it cannot hold goes on
intact on disk, and under many concurrent chunked uploads the memory held stays within GRADSEP_BODY_MEMORY_BYTES
while each upload gets 413 (or 503) and none a 500 or no answer.

The last test is the issue's target against `gradsep serve` in its own process: eight concurrent chunked 300 MiB
uploads with the default settings grow the server's resident memory by at most 400 MiB.
"""

from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import anyio
import httpx
import numpy as np
import pytest

from gradsep.service.bodies import BytePool, SpooledBody, read_body
from gradsep.service.main import create_app
from tests.service.conftest import rss_bytes, server_process, settings, uvicorn_server, wait_ready
from tests.service.frames import decode, expected_sum, frame_bytes, rgb
from tests.service.uploads import chunked_upload

MiB = 1 << 20


async def _chunks(data: bytes, size: int):  # noqa: ANN202 (an async generator)
    for start in range(0, len(data), size):
        yield data[start:start + size]


def _read(data: bytes, pool: BytePool, declared: int | None = None, spool_dir: Path | None = None) -> SpooledBody:
    return anyio.run(read_body, _chunks(data, 1000), pool, spool_dir, declared)


def test_a_body_the_pool_holds_stays_in_memory_and_gives_its_bytes_back() -> None:
    pool = BytePool(10_000)
    body = _read(bytes(range(256)) * 30, pool)
    assert not body.on_disk and body.size == 7680 and pool.held == 7680
    assert body.file.read() == bytes(range(256)) * 30
    body.close()
    body.close()  # idempotent: the job and the request may both close it
    assert pool.held == 0


@pytest.mark.parametrize("declared, sent", [(7680, 7680), (9000, 7680), (5000, 7680)])
def test_a_declared_body_comes_back_as_sent_whatever_its_declared_length(tmp_path: Path, declared: int,
                                                                         sent: int) -> None:
    """A granted Content-Length presizes the in-memory buffer: a body shorter than declared is cut to what came,
    and one longer (so past its reservation) spills to disk with exactly the bytes sent."""
    pool = BytePool(declared)
    data = bytes(range(256)) * (sent // 256)
    body = _read(data, pool, declared, tmp_path)
    assert body.size == sent and body.on_disk == (sent > declared)
    assert body.file.read() == data and body.file.read() == b""
    body.file.seek(0, 2)
    assert body.file.tell() == sent
    body.close()
    assert pool.held == 0


@pytest.mark.parametrize("declared", [None, 7680])
def test_a_body_the_pool_cannot_hold_goes_on_intact_on_disk(tmp_path: Path, declared: int | None) -> None:
    pool = BytePool(5000)
    other = _read(b"x" * 3000, pool)  # another upload holds most of the pool
    body = _read(bytes(range(256)) * 30, pool, declared, tmp_path)
    assert body.on_disk and body.size == 7680
    assert body.file.read() == bytes(range(256)) * 30
    assert pool.held == 3000 and pool.peak <= pool.capacity  # the spilled body gave its memory back
    body.close()
    other.close()
    assert pool.held == 0


def test_a_declared_length_the_pool_grants_is_reserved_and_the_unused_rest_returned() -> None:
    pool = BytePool(10_000)
    body = _read(b"y" * 3000, pool, declared=4000)  # a client that sends less than it declared
    assert not body.on_disk and pool.held == 3000
    body.close()
    assert pool.held == 0


def test_a_failed_read_closes_its_body() -> None:
    pool = BytePool(10_000)

    async def broken():  # noqa: ANN202
        yield b"z" * 2000
        raise ConnectionError("client went away")

    with pytest.raises(ConnectionError):
        anyio.run(read_body, broken(), pool, None, None)
    assert pool.held == 0


def test_frames_spooled_to_disk_reconstruct_exactly() -> None:
    """GRADSEP_BODY_MEMORY_BYTES=0: every raw body is on disk; the answers are the same as from memory."""
    app = create_app(settings(body_memory_bytes=0))
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        wait_ready(client)
        for seed, headers in ((3, {}), (4, {"Transfer-Encoding": "chunked"})):
            data = frame_bytes(seed=seed)
            content = iter([data[:1000], data[1000:]]) if headers else data
            r = client.post("/v1/reconstruct", params={"method": "l2"}, content=content,
                            headers={"Content-Type": "image/x-exr", **headers})
            assert r.status_code == 200, r.text
            np.testing.assert_allclose(rgb(decode(r.content)[0]), expected_sum(seed=seed), rtol=1e-4, atol=1e-4)
    assert app.state.engine.body_pool.peak == 0 and app.state.engine.body_pool.held == 0


def test_concurrent_chunked_uploads_never_hold_more_than_the_pool() -> None:
    """Eight chunked 32 MiB uploads against an 8 MiB body limit and a 12 MiB pool: each crosses the limit and gets
    its 413 there with Connection: close (not after the whole body: the client is still sending, its surplus in
    socket and uvicorn buffers), none a 500 or no answer, and the pool never held more than 12 MiB (the uploads
    that found it full went on on disk)."""
    app = create_app(settings(max_body_bytes=8 * MiB, body_memory_bytes=12 * MiB))
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        wait_ready(client)
        port = int(url.rsplit(":", 1)[1])
        with ThreadPoolExecutor(8) as pool:
            results = list(pool.map(lambda _: chunked_upload(port, 32 * MiB, chunk=256 << 10, timeout=60),
                                    range(8)))
        assert client.get("/healthz").status_code == 200
    for r in results:
        assert r.status == 413 and r.code == "body_too_large", r
        # answered when the limit was crossed, while the client was still sending; and the connection closed,
        # so the server did not go on reading (and discarding) the rest of the body
        assert r.sent < 32 * MiB and r.headers.get("connection") == "close", r
    body_pool = app.state.engine.body_pool
    assert 0 < body_pool.peak <= 12 * MiB and body_pool.held == 0


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc for memory")
def test_eight_chunked_300_mib_uploads_grow_the_servers_memory_by_at_most_400_mib(tmp_path: Path) -> None:
    """The default settings, `gradsep serve` in its own process; the peak resident memory is the kernel's
    high-water mark, reset once the server is ready (or, where that is refused, sampled)."""
    env = {"GRADSEP_LOG_LEVEL": "warning"}
    argv = ["-m", "gradsep", "serve", "--host", "127.0.0.1", "--port", "{port}"]
    with server_process(argv, env, tmp_path / "server.log") as (url, proc):
        baseline = reset_peak(proc.pid)
        port = int(url.rsplit(":", 1)[1])
        with ThreadPoolExecutor(8) as pool:
            results = list(pool.map(lambda _: chunked_upload(port, 300 * MiB, timeout=240), range(8)))
        peak = rss_bytes(proc.pid, "VmHWM")
        assert httpx.get(f"{url}/healthz", timeout=10).status_code == 200
    print(f"RSS MiB: baseline {baseline / MiB:.0f}, peak {peak / MiB:.0f}, growth {(peak - baseline) / MiB:.0f}; "
          f"answers {sorted((r.status, r.code) for r in results)}")
    for r in results:
        assert (r.status, r.code) in {(413, "body_too_large"), (503, "uploads_full"), (503, "queue_full")}, r
    assert peak - baseline <= 400 * MiB


def reset_peak(pid: int) -> int:
    """Reset the process's VmHWM to its current RSS (Linux ``clear_refs`` 5); return that RSS."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return rss_bytes(pid, "VmHWM")


def test_a_body_that_cannot_be_spooled_is_503_with_retry_after(monkeypatch: pytest.MonkeyPatch) -> None:
    """A full or vanished spool folder is the server's trouble: 503 spool_failed, never a 500."""
    def full(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("gradsep.service.bodies.tempfile.TemporaryFile", full)
    app = create_app(settings(body_memory_bytes=0, warm_up=False))
    with uvicorn_server(app) as url, httpx.Client(base_url=url, timeout=60) as client:
        wait_ready(client)
        r = client.post("/v1/reconstruct", params={"method": "l2"}, content=frame_bytes(seed=1),
                        headers={"Content-Type": "image/x-exr"})
        assert r.status_code == 503 and r.json()["error"]["code"] == "spool_failed", r.text
        assert r.headers["retry-after"] == "30" and "No space left" in r.json()["error"]["message"]
    assert app.state.engine.body_pool.held == 0


def test_a_spool_folder_that_is_not_a_folder_stops_the_settings(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="is not a folder"):
        settings(spool_dir=tmp_path / "missing")
    assert settings(spool_dir=tmp_path).spool_dir == tmp_path
