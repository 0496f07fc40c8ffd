"""End-to-end latency of the HTTP service for a 1280×720 frame, per method: p50 / p95 over sequential requests.

    python benchmarks/bench_service.py                       # starts `gradsep serve` on a free port, l1 + l2
    python benchmarks/bench_service.py --repeats 50 --json   # one JSON document on stdout
    python benchmarks/bench_service.py --url http://host:8000 --token T   # an already running service

What is timed is what a render-farm task sees: upload of the EXR, queueing, decode, reconstruction of each layer,
encode and download (client-side wall clock, one request at a time, connection kept alive). The service's own
``Server-Timing`` breakdown is reported alongside as medians, so transport overhead can be read off the
difference. Every method the service reports in /readyz is measured (network too when models are loaded) unless
``--methods`` narrows it.

The frame is synthetic and seeded: direct and indirect layers (smooth shading with edges, Monte-Carlo-like
multiplicative noise and rare fireflies in the bases, lighter noise in the gradients) plus albedo/normal/depth
features, written as float32 ZIP EXR. Each method runs ``--warmup`` untimed requests first. Timings on a shared
machine are noisy: the load average is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from model.frame import encode_exr, forward_differences, rgb_channels  # noqa: E402


def synthetic_frame(height: int, width: int, seed: int = 0) -> bytes:
    """A noisy separated frame with features, as EXR bytes (float32, ZIP)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    yy, xx = yy / height, xx / width
    channels: dict[str, np.ndarray] = {}
    for layer, noise in (("direct", 0.3), ("indirect", 0.8)):
        shading = np.stack([0.4 + 0.3 * np.sin(7 * xx + c) * np.cos(5 * yy - c) for c in range(3)], -1)
        edges = (xx > 0.35) * 0.5 + ((xx - 0.7) ** 2 + (yy - 0.4) ** 2 < 0.03) * 2.0
        truth = (shading + edges[..., None]) * (1.0 if layer == "direct" else 0.4)
        dx, dy = forward_differences(truth)
        fireflies = (rng.random(truth.shape[:2]) < 0.002)[..., None] * rng.exponential(20.0, truth.shape)
        base = truth * (1 + noise * rng.standard_normal(truth.shape)) + fireflies
        dx = dx + 0.3 * noise * rng.standard_normal(dx.shape)
        dy = dy + 0.3 * noise * rng.standard_normal(dy.shape)
        dx[:, -1], dy[-1] = 0, 0
        channels.update(rgb_channels(layer, np.maximum(base, 0)))
        channels.update(rgb_channels(f"{layer}.dx", dx))
        channels.update(rgb_channels(f"{layer}.dy", dy))
    normal = np.dstack([np.zeros((height, width, 2), np.float32), np.ones((height, width), np.float32)])
    channels.update(dict(zip(("albedo.R", "albedo.G", "albedo.B"), np.full((3, height, width), 0.6), strict=True)))
    channels.update(dict(zip(("normal.X", "normal.Y", "normal.Z"), np.moveaxis(normal, -1, 0), strict=True)))
    channels["depth.Z"] = 2.0 + yy
    return encode_exr({k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()})


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def local_service(concurrency: int) -> Iterator[str]:
    """`gradsep serve` in a subprocess on a free port (Poisson methods unless GRADSEP_MODELS has models)."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "GRADSEP_CONCURRENCY": str(concurrency),
           "GRADSEP_LOG_LEVEL": "warning"}
    proc = subprocess.Popen([sys.executable, "-m", "gradsep", "serve", "--host", "127.0.0.1", "--port", str(port)],
                            cwd=REPO, env=env)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)


def wait_ready(client: httpx.Client, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            r = client.get("/readyz")
            if r.status_code == 200:
                return r.json()
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"service at {client.base_url} not ready after {timeout:.0f} s")


def server_timing(header: str) -> dict[str, float]:
    """``decode;dur=12.3, direct;dur=...`` -> {"decode": 0.0123, ...} in seconds."""
    out = {}
    for part in header.split(","):
        name, _, params = part.strip().partition(";")
        if params.startswith("dur="):
            out[name] = float(params[4:]) / 1000
    return out


def measure(client: httpx.Client, data: bytes, method: str, repeats: int, warmup: int, fmt: str) -> dict:
    latencies: list[float] = []
    steps: dict[str, list[float]] = defaultdict(list)
    size = 0
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        r = client.post("/v1/reconstruct", params={"method": method, "format": fmt}, content=data,
                        headers={"Content-Type": "image/x-exr", "X-Request-ID": f"bench-{method}-{i}"})
        elapsed = time.perf_counter() - t0
        if r.status_code != 200:
            raise SystemExit(f"{method}: HTTP {r.status_code}: {r.text[:300]}")
        if i >= warmup:
            latencies.append(elapsed)
            size = len(r.content)
            for name, seconds in server_timing(r.headers.get("server-timing", "")).items():
                steps[name].append(seconds)
    lat = np.array(latencies)
    return {"method": method, "requests": repeats, "p50_s": float(np.percentile(lat, 50)),
            "p95_s": float(np.percentile(lat, 95)), "min_s": float(lat.min()), "max_s": float(lat.max()),
            "server_median_s": {k: float(np.median(v)) for k, v in steps.items()}, "response_bytes": size}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default=None, help="measure a running service instead of starting one")
    parser.add_argument("--token", default=os.environ.get("GRADSEP_TOKEN"))
    parser.add_argument("--methods", default=None, help="comma-separated (default: all the service offers)")
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--format", choices=("float", "half"), default="float")
    parser.add_argument("--concurrency", type=int, default=1, help="GRADSEP_CONCURRENCY of a started service")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    data = synthetic_frame(height, width)

    with (contextmanager(lambda: (yield args.url))() if args.url else local_service(args.concurrency)) as url:
        headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
        with httpx.Client(base_url=url, headers=headers, timeout=600) as client:
            ready = wait_ready(client)
            methods = args.methods.split(",") if args.methods else ready["methods"]
            results = [measure(client, data, m, args.repeats, args.warmup, args.format) for m in methods]

    report = {"frame": f"{width}x{height}", "request_bytes": len(data), "format": args.format,
              "platform": platform.platform(), "cpus": os.cpu_count(), "loadavg": os.getloadavg(),
              "results": results}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"{width}x{height} direct+indirect frame ({len(data) / 1e6:.1f} MB EXR), {args.repeats} requests per "
          f"method, output {args.format}; {os.cpu_count()} CPUs, load average "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print(f"{'method':8} {'p50 s':>8} {'p95 s':>8} {'min s':>8}   server medians (s)")
    for r in results:
        steps = " ".join(f"{k}={v:.3f}" for k, v in r["server_median_s"].items() if k != "total")
        print(f"{r['method']:8} {r['p50_s']:8.3f} {r['p95_s']:8.3f} {r['min_s']:8.3f}   {steps}")


if __name__ == "__main__":
    main()
