"""`gradsep client FRAME.exr -o OUT.exr`: what a render-farm task runs to get a frame reconstructed.

Behaviour a farm scheduler can rely on:

* 503 (queue full, not ready) and connection-level failures are retried with exponential backoff and full
  jitter; a 503's ``Retry-After`` is honoured (waited at least, plus up to 20 % jitter so a farm's tasks don't
  return in lockstep). 4xx answers are never retried: the same bytes would be rejected again.
* The answer is decoded in full (every channel of the EXR) before it is written: a truncated or corrupt answer is
  a service failure (exit 1, one line), and nothing is written.
* The output is written atomically (temporary file in the same folder, then rename): a killed task never leaves
  a half-written OUT, and an existing OUT is only replaced by a complete new one.
* Every request of one invocation carries the same ``X-Request-ID`` and every log line names it, so a farm log
  line can be matched with the service's access log.

Exit status: 0 written; 2 bad input or a 4xx answer (the frame or the request is wrong -- don't retry);
75 (``EX_TEMPFAIL``) the service stayed unavailable through every retry, or a request timed out, client-side or
as the service's 504 (retry the task later); 1 the service failed otherwise (a 5xx other than 503 or 504, or an
answer that is not a complete, decodable EXR).
"""

from __future__ import annotations

import email.utils
import logging
import os
import random
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from gradsep.model.errors import CommandError

DEFAULT_URL = "http://127.0.0.1:8000"
EXIT_OK, EXIT_SERVER_ERROR, EXIT_UNAVAILABLE = 0, 1, 75
EXR_MAGIC = b"\x76\x2f\x31\x01"
# Connection-level failures: the request may not have reached the service, so retrying is safe.
RETRYABLE_TRANSPORT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError, httpx.ReadError,
                       httpx.WriteError, httpx.PoolTimeout)

log = logging.getLogger("gradsep.client")


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at emit time (tests and embedders swap it)."""

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


_STDERR_HANDLER = _StderrHandler()


class Unavailable(Exception):
    """The service could not be reached or stayed overloaded through every retry (exit 75)."""


class ServerFailure(Exception):
    """The service answered, but with a failure retrying would not fix (exit 1)."""


@dataclass(frozen=True)
class RetryPolicy:
    retries: int = 5  # retries after the first attempt
    base_seconds: float = 0.5  # first backoff ceiling; doubles each attempt
    max_seconds: float = 30.0  # backoff ceiling
    max_retry_after: float = 300.0  # never sleep longer than this for one Retry-After


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds from a Retry-After header: delta-seconds or an HTTP date; None if absent or unparsable."""
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - (time.time() if now is None else now))


def backoff_delay(attempt: int, policy: RetryPolicy, retry_after: float | None,
                  rng: random.Random | None = None) -> float:
    """Seconds to wait before retry ``attempt`` (0-based): Retry-After plus jitter, else full-jitter backoff."""
    rng = rng or random.Random()
    if retry_after is not None:
        wait = min(retry_after, policy.max_retry_after)
        return wait * rng.uniform(1.0, 1.2)
    return rng.uniform(0.0, min(policy.max_seconds, policy.base_seconds * 2.0**attempt))


def error_summary(response: httpx.Response) -> str:
    """``413 body_too_large: request body is over ...`` from the service's JSON error, or the raw text."""
    try:
        err = response.json()["error"]
        return f"{response.status_code} {err['code']}: {err['message']}"
    except (ValueError, KeyError, TypeError):
        text = " ".join(response.text.split())[:200]
        return f"{response.status_code} {response.reason_phrase}{': ' + text if text else ''}"


#: The request body is handed to httpx in slices of this size: given one ``bytes`` object, httpcore sends it with
#: ``buffer = buffer[n:]`` after each partial ``send``, copying the unsent rest every time (quadratic in the
#: frame's size; docs/decisions.md has the measurement). Slices of a memoryview are copied once each. Same bytes
#: on the wire, with the same Content-Length framing.
UPLOAD_CHUNK = 1 << 20


def upload_body(data: bytes, chunk: int = UPLOAD_CHUNK) -> dict[str, Any]:
    """``client.post`` keywords sending ``data`` in memoryview slices with an explicit Content-Length (httpx
    would otherwise frame an iterator as chunked transfer encoding). A fresh iterator per call: pass it to one
    request only."""
    view = memoryview(data)

    def slices() -> Any:
        for start in range(0, len(view), chunk):
            yield view[start:start + chunk]

    return {"content": slices(), "headers": {"Content-Length": str(len(view))}}


@dataclass(frozen=True)
class FrameRequest:
    """One frame's request: the service, the query parameters, the request id and how hard to retry."""

    url: str
    params: dict[str, Any]
    request_id: str
    policy: RetryPolicy = RetryPolicy()
    content_type: str = "image/x-exr"  # a window's multipart body names its boundary here


def post_frame(client: httpx.Client, request: FrameRequest, data: bytes,
               sleep: Callable[[float], None] = time.sleep, rng: random.Random | None = None) -> httpx.Response:
    """POST the frame, retrying 503 and connection failures; return the 200 response or raise."""
    url, params, request_id, policy = request.url, request.params, request.request_id, request.policy
    endpoint = f"{url.rstrip('/')}/v1/reconstruct"
    headers = {"Content-Type": request.content_type, "X-Request-ID": request_id}
    attempts = policy.retries + 1
    reason = "no attempt made"
    for attempt in range(attempts):
        retry_after = None
        try:
            body = upload_body(data)
            response = client.post(endpoint, params=params, content=body["content"],
                                   headers={**headers, **body["headers"]})
        except RETRYABLE_TRANSPORT as exc:
            reason = f"cannot reach {url}: {type(exc).__name__}: {exc or 'connection failed'}"
        except httpx.TimeoutException as exc:
            raise Unavailable(f"request timed out ({type(exc).__name__}) at {url}") from exc
        else:
            if response.status_code == 200:
                return response
            if response.status_code == 504:  # the service's own timeout: the exit table's 75, no retry (the
                # abandoned job still runs there, so an immediate retry would only add load)
                raise Unavailable(f"service timed out: {error_summary(response)}")
            if response.status_code != 503:
                summary = error_summary(response)
                if 400 <= response.status_code < 500:
                    raise CommandError(f"service rejected the request: {summary} (request_id={request_id})")
                raise ServerFailure(f"service failed: {summary}")
            reason = f"service unavailable: {error_summary(response)}"
            retry_after = parse_retry_after(response.headers.get("retry-after"))
        if attempt + 1 < attempts:
            delay = backoff_delay(attempt, policy, retry_after, rng)
            log.warning("attempt %d/%d failed (%s); retrying in %.1f s request_id=%s",
                        attempt + 1, attempts, reason, delay, request_id)
            sleep(delay)
    raise Unavailable(f"{reason} (gave up after {attempts} attempts)")


#: What an answer may declare: far above any service's own limits (the client trusts the size its service chose,
#: and checks only that every declared pixel decodes).
ANSWER_LIMITS_PIXELS = 1 << 31


def verify_answer(data: bytes) -> None:
    """Decode every channel of the answer; ServerFailure naming the problem unless the whole EXR decodes."""
    from gradsep.model.errors import FrameError
    from gradsep.model.exr_read import ReadLimits, verify_exr

    limits = ReadLimits(max_pixels=ANSWER_LIMITS_PIXELS, max_values=ANSWER_LIMITS_PIXELS * 64, max_side=1 << 24)
    try:
        verify_exr(data, limits)
    except FrameError as exc:
        raise ServerFailure(f"service answered 200 with an EXR that does not decode ({len(data)} bytes): "
                            f"{exc.message}") from None


def resolve_target(url: str | None, token: str | None) -> tuple[str, str | None]:
    """URL and token: the given value, else GRADSEP_URL / GRADSEP_TOKEN, else the default URL and no token."""
    url = url or os.environ.get("GRADSEP_URL") or DEFAULT_URL
    token = token or os.environ.get("GRADSEP_TOKEN") or None
    if not url.startswith(("http://", "https://")):
        raise CommandError(f"--url must start with http:// or https://, got {url!r}")
    return url, token


def _setup_logging() -> None:
    """Attach our one stderr handler (once) so farm logs get attempt/result lines with the request id."""
    if _STDERR_HANDLER not in log.handlers:
        _STDERR_HANDLER.setFormatter(logging.Formatter("gradsep client: %(message)s"))
        log.addHandler(_STDERR_HANDLER)
        log.setLevel(logging.INFO)
        log.propagate = False


@dataclass(frozen=True)
class ClientOptions:
    """What `gradsep client` was told: the service (None: from the environment), the request's query parameters
    (method, alpha, format, layers, channels; None values are dropped), retries and the per-request timeout."""

    url: str | None = None
    token: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    retries: int = 5
    timeout: float = 300.0


def _checked(options: ClientOptions, output: Path) -> tuple[str, str | None]:
    """The service and token, after checking the options and the output folder (CommandError: exit 2)."""
    url, token = resolve_target(options.url, options.token)
    if options.retries < 0:
        raise CommandError(f"--retries must be 0 or more, got {options.retries}")
    if not options.timeout > 0:
        raise CommandError(f"--timeout must be positive, got {options.timeout}")
    if not output.parent.is_dir():
        raise CommandError(f"output folder {output.parent} does not exist")
    return url, token


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CommandError(f"cannot read {path}: {exc.strerror or exc}") from None


def send_frame(frame: Path, output: Path, options: ClientOptions = ClientOptions(),
               sleep: Callable[[float], None] = time.sleep) -> int:
    """Post ``frame`` to the service and write the answer to ``output`` atomically; returns the exit status.

    Bad input and 4xx answers raise CommandError (exit 2); an unavailable or failing service returns
    EXIT_UNAVAILABLE / EXIT_SERVER_ERROR after printing one line.
    """
    _setup_logging()
    frame, output = Path(frame), Path(output)
    url, token = _checked(options, output)
    data = _read(frame)
    return _exchange(data, "image/x-exr", output, (url, token, uuid.uuid4().hex), options, sleep)


def _exchange(data: bytes, content_type: str, output: Path, target: tuple[str, str | None, str],
              options: ClientOptions, sleep: Callable[[float], None]) -> int:
    """One request with its retries, the answer verified and written atomically; the exit status."""
    from gradsep.model.exr_write import write_bytes_atomic

    url, token, request_id = target
    params = {k: v for k, v in options.params.items() if v is not None}
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    http_timeout = httpx.Timeout(options.timeout, connect=min(options.timeout, 10.0))
    started = time.perf_counter()
    request = FrameRequest(url, params, request_id, RetryPolicy(retries=options.retries), content_type)
    try:
        with httpx.Client(timeout=http_timeout, headers=auth) as client:
            response = post_frame(client, request, data, sleep)
        if not response.content.startswith(EXR_MAGIC):
            raise ServerFailure(f"service answered 200 with a non-EXR body "
                                f"({response.headers.get('content-type', 'no content type')})")
        verify_answer(response.content)
    except Unavailable as exc:
        print(f"gradsep client: error: {exc} (request_id={request_id})", file=sys.stderr)
        return EXIT_UNAVAILABLE
    except ServerFailure as exc:
        print(f"gradsep client: error: {exc} (request_id={request_id})", file=sys.stderr)
        return EXIT_SERVER_ERROR
    try:
        write_bytes_atomic(output, response.content)
    except OSError as exc:
        raise CommandError(f"cannot write {output}: {exc.strerror or exc}") from None
    used = response.headers.get("x-gradsep-neighbours")
    log.info("wrote %s (%d bytes, method %s%s, %.2f s; %s) request_id=%s", output, len(response.content),
             response.headers.get("x-reconstruction-method", "?"), f", neighbours {used}" if used else "",
             time.perf_counter() - started, response.headers.get("server-timing", ""), request_id)
    for warning in filter(None, (response.headers.get("x-gradsep-warnings"),)):
        log.warning("%s: %s request_id=%s", output.name, warning, request_id)
    return EXIT_OK


@dataclass(frozen=True)
class Shot:
    """`gradsep client PATTERN --frames A-B -o PATTERN [--window N]`: the input and output patterns
    (model/shot.py's FramePattern), the frames and the window (odd, >= 1)."""

    source: Any
    output: Any
    frames: range
    window: int


def window_body(shot: Shot, n: int) -> tuple[bytes, str]:
    """Frame ``n``'s request: multipart ``frame`` plus its neighbours as ``previous`` / ``next`` parts, nearest
    first, within the window; a neighbour whose file is absent is an empty part (the service reports it missing),
    one before frame 0 is not sent. Returns the body and its Content-Type."""
    files: list[tuple[str, tuple[str, bytes, str]]] = [("frame", (shot.source.path(n).name,
                                                                   _read(shot.source.path(n)), "image/x-exr"))]
    for side, sign in (("previous", -1), ("next", 1)):
        for k in range(n + sign, n + sign * (shot.window // 2 + 1), sign):
            if k < 0:
                break
            path = shot.source.path(k)
            files.append((side, (path.name, _read(path) if path.is_file() else b"", "image/x-exr")))
    request = httpx.Request("POST", DEFAULT_URL, files=files)
    return request.read(), request.headers["content-type"]


def send_shot(shot: Shot, options: ClientOptions = ClientOptions(),
              sleep: Callable[[float], None] = time.sleep) -> int:
    """Post each frame of the shot with its window and write each answer atomically, frame after frame, with
    :func:`send_frame`'s retries; stops at the first frame that fails, returning its exit status (frames written
    before it stay)."""
    _setup_logging()
    if shot.window < 1 or shot.window % 2 == 0:
        raise CommandError(f"--window must be an odd number of frames >= 1, got {shot.window}")
    missing = [str(shot.source.path(n)) for n in shot.frames if not shot.source.path(n).is_file()]
    if missing:
        raise CommandError(f"frame {missing[0]} of the shot is missing"
                           + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    url, token = _checked(options, shot.output.path(shot.frames.start))
    request_id = uuid.uuid4().hex
    for n in shot.frames:
        body, content_type = window_body(shot, n)
        status = _exchange(body, content_type, shot.output.path(n), (url, token, request_id), options, sleep)
        if status != EXIT_OK:
            print(f"gradsep client: error: frame {n} failed; frames {shot.frames.start}-{n - 1} were written"
                  if n > shot.frames.start else f"gradsep client: error: frame {n} failed", file=sys.stderr)
            return status
    return EXIT_OK
