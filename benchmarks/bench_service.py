"""End-to-end latency of the HTTP service for a 1280×720 frame, per method: p50 / p95 over sequential requests,
then throughput with ``--clients`` (2) concurrent clients in frames per minute, and the service's peak RSS.

    python benchmarks/bench_service.py                       # starts `gradsep serve` on a free port, every method
    python benchmarks/bench_service.py --methods l2,network  # a subset, by name (fused, oidn, ... when served)
    python benchmarks/bench_service.py --repeats 50 --json   # one JSON document on stdout
    python benchmarks/bench_service.py --url http://host:8000 --token T   # an already running service (no RSS)
    python benchmarks/bench_service.py --io                  # EXR decode/encode cost per compression, no service
    python benchmarks/bench_service.py --io --io-compressions ZIP_COMPRESSION --io-threads 0,1,2  # OpenEXR pool
    python benchmarks/bench_service.py --uploads 8           # 8 concurrent chunked 300 MiB uploads: RSS growth
    python benchmarks/bench_service.py --methods oidn,oidn-l1 --without-variance   # the back-off's cost: A/B
    python benchmarks/bench_service.py --baseline-checkout ../base --repeats 5 --warmup 1 \
        --throughput-requests 2 --variance-too       # A/B against another checkout's service (641eeb8's worktree)

What is timed is what a render-farm task sees: upload of the EXR, queueing, decode, reconstruction of each layer,
encode and download (client-side wall clock, one request at a time, connection kept alive). The service's own
``Server-Timing`` breakdown is reported alongside as medians, so transport overhead can be read off the
difference. Every method the service reports in /readyz is measured (network too when models are loaded) unless
``--methods`` narrows it; methods are addressed by name only, so a method the service adds later (``fused``,
``oidn``) is measured without a change here (METHOD_ORDER only sorts the table).

Throughput: ``--clients`` threads post the same frame ``--throughput-requests`` times in all, against a service
started with ``--concurrency`` inference slots (default 2: one per core); frames per minute = requests / wall time.
Peak RSS is the service process's VmHWM (Linux /proc) after all methods ran, children included when it forked.

The frame is synthetic and seeded: direct and indirect layers (smooth shading with edges, Monte-Carlo-like
multiplicative noise and rare fireflies in the bases, lighter noise in the gradients, each layer's variance as the
renderer writes it) plus albedo/normal/depth features, written as float32 ZIP EXR. Each method runs ``--warmup``
untimed requests first. Timings on a shared machine are noisy: the load average is printed with them.

``--baseline-checkout DIR``: this checkout's service and DIR's (another commit's worktree, e.g. ``git worktree add
../base 641eeb8``; served by DIR's own ``.venv/bin/python`` when it has one, else by this interpreter with
DIR first on PYTHONPATH) are started side by side with the same settings and sent the same frame, without its
variance channels (a checkout from before the variance back-off has none to use), interleaved: each round posts it
once to each, the order reversed every other round, so the machine's load falls on both alike. Per method: the p50
wall time and the median server CPU seconds per request (user + system of the service process, /proc: less moved by
other processes than wall time), their ratios to DIR's and the median of the per-round wall ratios (``paired``),
frames per minute in the throughput phase, and each service's peak RSS. ``--variance-too`` adds a third service of
this checkout, sent the frame with its variance channels (the back-off's cost, beside; its own process, so the
like-for-like RSS is not moved by it); ``--stages`` prints each side's Server-Timing medians. Each round costs one
request per side: keep ``--repeats`` small on 2 cores.

``--uploads N``: a service with the default settings, N concurrent chunked (no Content-Length) uploads of
``--upload-mib`` MiB of zeros each, every one over the body limit; the answers (413, 503) and the growth of the
service's resident memory: its VmHWM, reset (Linux ``clear_refs``) once the service is ready, minus its RSS then
(docs/service.md, "Request bodies and memory").
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
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from gradsep.model.exr_read import read_frame
from gradsep.model.exr_write import LOSSLESS_COMPRESSIONS, configure_exr_threads, encode_exr
from gradsep.model.frame import rgb_channels
from gradsep.model.synthetic import synthetic_frame
from gradsep.service.client import upload_body

#: The checkout the served subprocess runs from (its code and, by default, its models/).
REPO = Path(__file__).resolve().parents[1]

#: Table order; any other method the service offers is measured after these.
METHOD_ORDER = ("l2", "l1", "network", "fused", "oidn")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def checkout_python(repo: Path) -> str:
    """The interpreter that serves ``repo``: its own ``.venv/bin/python`` when it has one (a worktree made by
    the project's worktree script sees its checkout as ``gradsep``), else this one (``repo`` first on
    PYTHONPATH)."""
    own = repo / ".venv" / "bin" / "python"
    return str(own) if repo != REPO and own.is_file() else sys.executable


@contextmanager
def local_service(concurrency: int, pids: list[int] | None = None, repo: Path = REPO) -> Iterator[str]:
    """`gradsep serve` of checkout ``repo`` in a subprocess on a free port (Poisson methods unless
    GRADSEP_MODELS has models)."""
    port = free_port()
    path = os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path, "GRADSEP_CONCURRENCY": str(concurrency),
           "GRADSEP_LOG_LEVEL": "warning"}
    proc = subprocess.Popen([checkout_python(repo), "-m", "gradsep", "serve", "--host", "127.0.0.1", "--port",
                             str(port)], cwd=repo, env=env)
    if pids is not None:
        pids.append(proc.pid)
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


def post(client: httpx.Client, data: bytes, method: str, fmt: str, request_id: str) -> httpx.Response:
    """One POST of the frame as ``gradsep client`` sends it (service.client.upload_body: memoryview slices)."""
    body = upload_body(data)
    return client.post("/v1/reconstruct", params={"method": method, "format": fmt}, content=body["content"],
                       headers={"Content-Type": "image/x-exr", "X-Request-ID": request_id, **body["headers"]})


def measure(client: httpx.Client, data: bytes, method: str, repeats: int, warmup: int, fmt: str) -> dict:
    latencies: list[float] = []
    steps: dict[str, list[float]] = defaultdict(list)
    size = 0
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        r = post(client, data, method, fmt, f"bench-{method}-{i}")
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


def peak_rss_mib(pid: int) -> float | None:
    """VmHWM of a process (Linux), MiB; None where /proc is not readable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def throughput(url: str, headers: dict, data: bytes, method: str, clients: int, requests: int, fmt: str) -> dict:
    """``requests`` posts spread over ``clients`` concurrent connections; frames per minute."""
    def worker(count: int) -> int:
        with httpx.Client(base_url=url, headers=headers, timeout=600) as client:
            for i in range(count):
                r = post(client, data, method, fmt, f"tp-{method}-{i}")
                if r.status_code != 200:
                    raise SystemExit(f"{method}: HTTP {r.status_code}: {r.text[:300]}")
        return count

    shares = [requests // clients + (1 if i < requests % clients else 0) for i in range(clients)]
    start = time.perf_counter()
    with ThreadPoolExecutor(clients) as pool:
        done = sum(pool.map(worker, shares))
    wall = time.perf_counter() - start
    return {"clients": clients, "requests": done, "seconds": wall, "frames_per_minute": 60.0 * done / wall}


def io_costs(height: int, width: int, repeats: int, compressions: list[str], thread_counts: list[int]) -> None:
    """Decode and encode cost of the benchmark frame per lossless compression and OpenEXR thread-pool size
    (``GRADSEP_EXR_THREADS``; the service's default -1 is one per core), no service."""
    import io

    print(f"{width}x{height} direct+indirect frame with features; medians of {repeats}; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'compression':20} {'threads':>7} {'request MB':>10} {'read_frame s':>12} {'encode RGB s':>12} "
          f"{'answer MB':>9}")
    for compression in compressions:
        data = synthetic_frame(height, width, compression=compression)
        for threads in thread_counts:
            configure_exr_threads(threads)
            reads, encodes = [], []
            for _ in range(repeats):
                t0 = time.perf_counter()
                frame = read_frame(io.BytesIO(data))
                t1 = time.perf_counter()
                image = frame.combined().base
                t2 = time.perf_counter()
                answer = encode_exr(dict(rgb_channels("", image)), compression=compression)
                encodes.append(time.perf_counter() - t2)
                reads.append(t1 - t0)
            print(f"{compression:20} {threads:7} {len(data) / 1e6:10.1f} {np.median(reads):12.3f} "
                  f"{np.median(encodes):12.3f} {len(answer) / 1e6:9.1f}", flush=True)


def chunked_upload(url: str, mib: int) -> str:
    """POST ``mib`` MiB of zeros as a chunked body (a generator: no Content-Length); the answer's status and code.
    httpx reads the answer of a server that answers mid-upload and closes."""
    def zeros() -> Iterator[bytes]:
        chunk = bytes(1 << 20)
        for _ in range(mib):
            yield chunk

    try:
        r = httpx.post(f"{url}/v1/reconstruct", content=zeros(), headers={"Content-Type": "image/x-exr"}, timeout=600)
    except httpx.HTTPError as exc:
        return f"no answer ({type(exc).__name__})"
    try:
        return f"{r.status_code} {r.json()['error']['code']}"
    except (ValueError, KeyError, TypeError):
        return str(r.status_code)


def upload_memory(uploads: int, mib: int, concurrency: int) -> None:
    """``--uploads``: the service's RSS growth under ``uploads`` concurrent chunked uploads of ``mib`` MiB."""
    pids: list[int] = []
    with local_service(concurrency, pids) as url, httpx.Client(base_url=url, timeout=60) as client:
        wait_ready(client)
        Path(f"/proc/{pids[0]}/clear_refs").write_text("5")  # VmHWM := VmRSS
        baseline = peak_rss_mib(pids[0])
        started = time.monotonic()
        with ThreadPoolExecutor(uploads) as pool:
            results = list(pool.map(lambda _: chunked_upload(url, mib), range(uploads)))
        seconds = time.monotonic() - started
        peak = peak_rss_mib(pids[0])
        alive = client.get("/healthz").status_code
    answers: dict[str, int] = defaultdict(int)
    for r in results:
        answers[r] += 1
    assert baseline is not None and peak is not None
    print(f"{uploads} concurrent chunked uploads of {mib} MiB, service concurrency {concurrency}: answers "
          f"{dict(answers)} in {seconds:.1f} s; /healthz {alive}; service RSS baseline {baseline:.0f} MiB, peak "
          f"{peak:.0f} MiB, growth {peak - baseline:.0f} MiB; {os.cpu_count()} CPUs, load average "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))


def without_variance(data: bytes, compression: str) -> bytes:
    """The EXR ``data`` without its layers' variance channels (``L.var.Y``), everything else as it was."""
    import io

    import OpenEXR

    with OpenEXR.File(io.BytesIO(data)) as exr:
        channels = {name: c.pixels.copy() for name, c in exr.channels().items() if ".var." not in name}
    out = io.BytesIO()
    header = {"compression": getattr(OpenEXR, compression), "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(out)
    return out.getvalue()


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a process, all its threads (Linux /proc); None where it is not readable."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class Side:
    """One column of an A/B: a started service, the frame it is sent, and what each request cost it."""

    name: str
    url: str
    pid: int
    data: bytes
    wall: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    cpu: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    steps: dict[str, dict[str, list[float]]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(list)))
    fpm: dict[str, float] = field(default_factory=dict)

    def request(self, client: httpx.Client, method: str, fmt: str, request_id: str, record: bool) -> None:
        before = cpu_seconds(self.pid)
        t0 = time.perf_counter()
        r = post(client, self.data, method, fmt, request_id)
        elapsed = time.perf_counter() - t0
        after = cpu_seconds(self.pid)
        if r.status_code != 200:
            raise SystemExit(f"{self.name} {method}: HTTP {r.status_code}: {r.text[:300]}")
        if record:
            self.wall[method].append(elapsed)
            if before is not None and after is not None:
                self.cpu[method].append(after - before)
            for name, seconds in server_timing(r.headers.get("server-timing", "")).items():
                self.steps[method][name].append(seconds)


def ab_methods(args: argparse.Namespace, ready: list[dict]) -> list[str]:
    """``--methods``, else every method both services offer, in table order."""
    offered = args.methods.split(",") if args.methods else [m for m in ready[0]["methods"]
                                                            if all(m in r["methods"] for r in ready[1:])]
    return sorted(offered, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER))


def ab_run(args: argparse.Namespace, sides: list[Side], methods: list[str]) -> None:
    """Per method: warm-up, then ``--repeats`` rounds that post the frame once to every side, the order reversed
    every other round (ABBA...), so drift and the machine's load fall on every side alike; then the throughput
    phase, side after side in the same alternating order."""
    clients = {s.name: httpx.Client(base_url=s.url, timeout=600) for s in sides}
    try:
        for k, method in enumerate(methods):
            for side in sides:
                for i in range(args.warmup):
                    side.request(clients[side.name], method, args.format, f"ab-warm-{method}-{i}", False)
            for i in range(args.repeats):
                for side in (sides if (i + k) % 2 == 0 else sides[::-1]):
                    side.request(clients[side.name], method, args.format, f"ab-{method}-{i}", True)
            if args.throughput_requests:
                for side in (sides if k % 2 == 0 else sides[::-1]):
                    side.fpm[method] = throughput(side.url, {}, side.data, method, args.clients,
                                                  args.throughput_requests, args.format)["frames_per_minute"]
            print(f"  {method} done; load average {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
    finally:
        for client in clients.values():
            client.close()


def ab_report(sides: list[Side], methods: list[str], peaks: list[float | None], stages: bool) -> None:
    """The A/B table: p50 wall and median server CPU per request of each side, each against the first side's
    (ratios of medians, and the median of the per-round wall ratios), frames per minute, peak RSS."""
    base = sides[0]
    head = "".join(f" {s.name + ' p50':>14} {'cpu':>6}" for s in sides)
    ratios = "".join(f" {s.name + '/' + base.name:>18} {'paired':>6} {'cpu':>5}" for s in sides[1:])
    print(f"{'method':8}{head}{ratios}   frames/min ({', '.join(s.name for s in sides)})")
    for m in methods:
        cells = "".join(f" {np.median(s.wall[m]):14.3f} {_median(s.cpu[m]):6.2f}" for s in sides)
        rel = "".join(f" {np.median(s.wall[m]) / np.median(base.wall[m]):18.3f} "
                      f"{np.median(np.divide(s.wall[m], base.wall[m])):6.3f} "
                      f"{_median(s.cpu[m]) / _median(base.cpu[m]):5.2f}" for s in sides[1:])
        fpm = " ".join(f"{s.fpm[m]:.1f}" for s in sides if m in s.fpm)
        print(f"{m:8}{cells}{rel}   {fpm}")
    print("peak RSS (MiB): " + ", ".join(f"{s.name} {p:.0f}" if p is not None else f"{s.name} n/a"
                                         for s, p in zip(sides, peaks, strict=True))
          + "".join(f"; {s.name}/{base.name} {p / peaks[0]:.3f}" for s, p in zip(sides[1:], peaks[1:], strict=True)
                    if p is not None and peaks[0]))
    if stages:
        print("server medians (s) per step:")
        for m in methods:
            for s in sides:
                print(f"  {m:8} {s.name:10} " + " ".join(f"{k}={np.median(v):.3f}" for k, v in s.steps[m].items()))


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def ab_compare(args: argparse.Namespace, data: bytes, baseline: Path) -> None:
    """``--baseline-checkout``: this checkout's service against ``baseline``'s, both started at once and sent the
    same frame, interleaved; ``--variance-too`` adds a third service, this checkout's, sent the frame with its
    variance channels (its own process, so the like-for-like peak RSS is not moved by it)."""
    plain = without_variance(data, args.compression)
    columns = [("base", baseline, plain), ("this", REPO, plain)]
    if args.variance_too:
        columns.append(("this+var", REPO, data))
    with ExitStack() as stack:
        sides = []
        for name, repo, frame in columns:
            pids: list[int] = []
            url = stack.enter_context(local_service(args.concurrency, pids, repo))
            sides.append(Side(name, url, pids[0], frame))
        ready = []
        for side in sides:
            with httpx.Client(base_url=side.url, timeout=60) as client:
                ready.append(wait_ready(client, 300))
        methods = ab_methods(args, ready)
        print(f"A/B: {baseline} (base) against {REPO} (this), {len(plain) / 1e6:.1f} MB frame without variance "
              f"channels, {args.repeats} rounds per method (order alternating), service concurrency "
              f"{args.concurrency}; {os.cpu_count()} CPUs, load average "
              + " ".join(f"{x:.2f}" for x in os.getloadavg()), flush=True)
        ab_run(args, sides, methods)
        peaks = [peak_rss_mib(side.pid) for side in sides]
    ab_report(sides, methods, peaks, args.stages)
    print("load average at the end " + " ".join(f"{x:.2f}" for x in os.getloadavg()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default=None, help="measure a running service instead of starting one")
    parser.add_argument("--token", default=os.environ.get("GRADSEP_TOKEN"))
    parser.add_argument("--methods", default=None, help="comma-separated (default: all the service offers)")
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--format", choices=("float", "half"), default="float")
    parser.add_argument("--concurrency", type=int, default=2, help="GRADSEP_CONCURRENCY of a started service")
    parser.add_argument("--clients", type=int, default=2, help="concurrent clients for the throughput phase")
    parser.add_argument("--throughput-requests", type=int, default=8, help="requests per method in that phase")
    parser.add_argument("--compression", default="ZIP_COMPRESSION", choices=LOSSLESS_COMPRESSIONS,
                        help="the request EXR's compression (the answer follows it)")
    parser.add_argument("--io", action="store_true", help="only measure EXR decode/encode per compression")
    parser.add_argument("--io-compressions", default=",".join(LOSSLESS_COMPRESSIONS),
                        help="--io: comma-separated compressions")
    parser.add_argument("--io-threads", default="0,-1", help="--io: OpenEXR thread-pool sizes (-1: one per core)")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--without-variance", action="store_true",
                        help="post the frame without its L.var.Y channels (no variance back-off): its cost, by A/B")
    parser.add_argument("--baseline-checkout", type=Path, default=None,
                        help="A/B: this checkout's service against this other checkout's, interleaved")
    parser.add_argument("--variance-too", action="store_true",
                        help="--baseline-checkout: also this checkout on the frame with its variance channels")
    parser.add_argument("--stages", action="store_true", help="--baseline-checkout: Server-Timing medians too")
    parser.add_argument("--uploads", type=int, default=0, help="only measure RSS under N chunked uploads")
    parser.add_argument("--upload-mib", type=int, default=300, help="--uploads: MiB per upload")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    if args.uploads:
        upload_memory(args.uploads, args.upload_mib, args.concurrency)
        return
    if args.io:
        io_costs(height, width, max(1, min(args.repeats, 5)), args.io_compressions.split(","),
                 [int(t) for t in args.io_threads.split(",")])
        return
    data = synthetic_frame(height, width, compression=args.compression)
    if args.baseline_checkout is not None:
        ab_compare(args, data, args.baseline_checkout.resolve())
        return
    if args.without_variance:
        data = without_variance(data, args.compression)

    pids: list[int] = []
    with (contextmanager(lambda: (yield args.url))() if args.url else local_service(args.concurrency, pids)) as url:
        headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
        with httpx.Client(base_url=url, headers=headers, timeout=600) as client:
            ready = wait_ready(client)
            models = client.get("/v1/models").json().get("models", [])
            offered = args.methods.split(",") if args.methods else ready["methods"]
            methods = sorted(offered, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER))
            results = [measure(client, data, m, args.repeats, args.warmup, args.format) for m in methods]
        for r in results:
            r["throughput"] = throughput(url, headers, data, r["method"], args.clients, args.throughput_requests,
                                         args.format)
        peak = peak_rss_mib(pids[0]) if pids else None

    report = {"frame": f"{width}x{height}", "request_bytes": len(data), "format": args.format,
              "compression": args.compression, "platform": platform.platform(), "cpus": os.cpu_count(),
              "loadavg": os.getloadavg(), "peak_rss_mib": peak,
              "providers": sorted({f"{m.get('provider', '?')}/{m.get('precision', '?')}" for m in models}),
              "results": results}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"{width}x{height} direct+indirect frame ({len(data) / 1e6:.1f} MB EXR, {args.compression}), "
          f"{args.repeats} requests per method, output {args.format}; {os.cpu_count()} CPUs, load average "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print(f"network provider: {', '.join(report['providers']) or 'no models'}")
    print(f"{'method':8} {'p50 s':>8} {'p95 s':>8} {'min s':>8} {'frames/min':>10}   server medians (s)")
    for r in results:
        steps = " ".join(f"{k}={v:.3f}" for k, v in r["server_median_s"].items() if k != "total")
        tp = r["throughput"]
        print(f"{r['method']:8} {r['p50_s']:8.3f} {r['p95_s']:8.3f} {r['min_s']:8.3f} "
              f"{tp['frames_per_minute']:10.1f}   {steps}")
    print(f"throughput: {args.clients} concurrent clients, {args.throughput_requests} requests per method, service "
          f"concurrency {args.concurrency}; peak RSS of the service: "
          + (f"{peak:.0f} MiB" if peak is not None else "n/a (external service)"))


if __name__ == "__main__":
    main()
