"""The one ONNX Runtime session loader every model goes through: the network's per-layer models
(model/infer.py) and the fused blend models (model/fused.py).

It picks the execution provider and precision for this host (:func:`choose_provider`), builds the session, falls
back to ORT's CPU provider when the accelerated one cannot build it, and reports what really serves the session
(:class:`ProviderChoice`, which ``/v1/models`` shows per model): ORT may build a session without the provider it
was given, and then the CPU serves.

Import-light: numpy-free, and onnxruntime is imported only when a session is opened.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import onnxruntime

_OPT_LEVELS = ("disable", "basic", "extended", "all")
#: Execution providers ``SessionSettings.provider`` can ask for; "auto" picks (see ``choose_provider``).
PROVIDERS = ("auto", "cuda", "openvino", "cpu")
CUDA_EP, OPENVINO_EP, CPU_EP = "CUDAExecutionProvider", "OpenVINOExecutionProvider", "CPUExecutionProvider"
#: CPU flags that give OpenVINO's CPU plugin native bf16 arithmetic (AVX-512 BF16 or AMX).
BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})

log = logging.getLogger("gradsep.onnx")


def _env_provider() -> str:
    return os.environ.get("GRADSEP_ONNX_PROVIDER", "auto").strip().lower() or "auto"


@dataclass(frozen=True)
class SessionSettings:
    """ONNX Runtime session options.

    ``intra_op_threads`` 0 lets ORT use one thread per physical core, the fastest setting on the 2-core target;
    a service running several inferences side by side may want fewer. Full graph optimisation (operator
    fusion, NCHWc layouts) measured fastest in benchmarks/bench_network.py.

    ``provider`` (env ``GRADSEP_ONNX_PROVIDER``): "auto" runs ORT's CUDA provider where the installed build has
    it (``onnxruntime-gpu`` on a GPU host), else the OpenVINO execution provider in bf16 when the build has it
    (the ``onnxruntime-openvino`` distribution) and the CPU has native bf16 (``avx512_bf16``/``amx_bf16`` in
    /proc/cpuinfo), else ORT's own CPU provider in fp32; "cuda" asks for the CUDA provider (the CPU choice where
    the build lacks it); "openvino" forces OpenVINO (bf16 where the CPU has it, else fp32); "cpu" forces ORT's
    CPU provider (fp32).
    """

    intra_op_threads: int = 0
    optimization: str = "all"
    allow_spinning: bool = True  # spinning threads cut latency; turn off to free the CPU between requests
    memory_arena: bool = True    # ORT's CPU arena: faster allocation, but it keeps its high-water mark
    provider: str = field(default_factory=_env_provider)

    def options(self) -> onnxruntime.SessionOptions:
        import onnxruntime as ort

        if self.optimization not in _OPT_LEVELS:
            raise ValueError(f"optimization must be one of {_OPT_LEVELS}, got {self.optimization!r}")
        so = ort.SessionOptions()
        so.graph_optimization_level = {
            "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
            "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
            "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
            "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        }[self.optimization]
        so.intra_op_num_threads = max(0, int(self.intra_op_threads))
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.enable_cpu_mem_arena = self.memory_arena
        so.add_session_config_entry("session.intra_op.allow_spinning", "1" if self.allow_spinning else "0")
        so.log_severity_level = 3  # errors only: ORT's warnings about unused initialisers are noise here
        return so


def cpu_flags(cpuinfo: str | os.PathLike[str] = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU's feature flags (Linux /proc/cpuinfo); empty where that file is missing or unreadable."""
    try:
        with open(cpuinfo) as fh:
            for line in fh:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


@dataclass(frozen=True)
class ProviderChoice:
    """Which execution provider serves, in which precision, and why (reported by /v1/models and logged)."""

    provider: str   # "cuda", "openvino" or "cpu"
    precision: str  # "bf16" or "fp32"
    reason: str

    def providers(self) -> list[Any]:
        """The ``providers`` argument of ``InferenceSession``."""
        if self.provider == "cpu":
            return [CPU_EP]
        if self.provider == "cuda":  # fp32 on the GPU; ORT gives the CPU provider any node CUDA does not take
            return [(CUDA_EP, {"device_id": 0}), CPU_EP]
        hint = {"bf16": "bf16", "fp32": "f32"}[self.precision]
        config = json.dumps({"CPU": {"INFERENCE_PRECISION_HINT": hint}})
        # The CPU provider stays listed: ORT assigns it any node OpenVINO does not take.
        return [(OPENVINO_EP, {"device_type": "CPU", "load_config": config}), CPU_EP]

    def describe(self) -> dict[str, str]:
        """The keys /v1/models reports for every model."""
        return {"provider": self.provider, "precision": self.precision, "provider_reason": self.reason}


def choose_provider(requested: str, available: list[str] | tuple[str, ...], flags: frozenset[str]) -> ProviderChoice:
    """Pick the provider and precision for ``requested`` ("auto", "cuda", "openvino" or "cpu") on this host."""
    if requested not in PROVIDERS:
        raise ValueError(f"ONNX provider must be one of {', '.join(PROVIDERS)}, got {requested!r}")
    has_ov = OPENVINO_EP in available
    bf16 = sorted(BF16_FLAGS & flags)
    if requested == "cpu":
        return ProviderChoice("cpu", "fp32", "ORT CPU provider requested")
    if CUDA_EP in available and requested in ("auto", "cuda"):
        return ProviderChoice("cuda", "fp32", "ORT CUDA provider (onnxruntime-gpu)")
    if requested == "cuda":
        log.warning("CUDA provider requested but this onnxruntime build has none (install onnxruntime-gpu); "
                    "choosing among the CPU providers")
        requested = "auto"
    if not has_ov:
        why = "this onnxruntime build has no OpenVINO provider (install onnxruntime-openvino)"
        if requested == "openvino":
            log.warning("OpenVINO provider requested but %s; using the CPU provider", why)
        return ProviderChoice("cpu", "fp32", why)
    if bf16:
        return ProviderChoice("openvino", "bf16", f"OpenVINO provider; the CPU has {', '.join(bf16)}")
    if requested == "openvino":
        return ProviderChoice("openvino", "fp32", "OpenVINO provider requested; the CPU lacks native bf16")
    return ProviderChoice("cpu", "fp32", "the CPU lacks native bf16 (no avx512_bf16/amx_bf16)")


def served_by(choice: ProviderChoice, session_providers: list[str]) -> ProviderChoice:
    """``choice`` as the session really runs it: ORT can build a session without the accelerated provider it was
    given (a CUDA build on a host without a usable GPU), and /v1/models must then say the CPU serves."""
    wanted = {"cuda": CUDA_EP, "openvino": OPENVINO_EP}.get(choice.provider)
    if wanted is None or wanted in session_providers:
        return choice
    log.warning("ONNX Runtime did not enable the %s provider (session providers: %s); the CPU provider serves",
                choice.provider, ", ".join(session_providers))
    return ProviderChoice("cpu", "fp32", f"the {choice.provider} provider was not enabled by ONNX Runtime here")


def graph_session(model: str | os.PathLike[str] | bytes,
                  settings: SessionSettings) -> Callable[[ProviderChoice], onnxruntime.InferenceSession]:
    """A builder for :func:`open_session`: one ``InferenceSession`` of a model file (path) or serialized graph
    (bytes) on the choice's providers."""
    import onnxruntime as ort

    source = model if isinstance(model, bytes) else str(model)
    return lambda choice: ort.InferenceSession(source, settings.options(), providers=choice.providers())


def open_session(build: Callable[[ProviderChoice], Any], what: str, settings: SessionSettings,
                 error: type[Exception] = RuntimeError, source: str | None = None) -> tuple[Any, ProviderChoice]:
    """Build a session (``build(choice)``, anything with ORT's ``get_providers()``) on this host's provider for
    ``settings``, falling back to the CPU provider (logged) should the accelerated one fail, so a deployment never
    loses a model over an optional accelerator. Returns the session and what really serves it (logged as
    ``what``); raises ``error`` naming ``source`` (default ``what``) when ONNX Runtime cannot load it at all."""
    import onnxruntime as ort

    choice = choose_provider(settings.provider, ort.get_available_providers(), cpu_flags())
    try:
        session = build(choice)
    except Exception as exc:  # ORT raises its own exception types for corrupt or unsupported graphs
        if choice.provider == "cpu":
            raise error(f"{source or what}: ONNX Runtime cannot load it on the cpu provider ({exc})") from exc
        log.warning("%s: the %s provider failed (%s); falling back to the ORT CPU provider", source or what,
                    choice.provider, exc)
        choice = ProviderChoice("cpu", "fp32", f"the {choice.provider} provider failed on this model ({exc})")
        try:
            session = build(choice)
        except Exception as exc2:
            raise error(f"{source or what}: ONNX Runtime cannot load it on the cpu provider ({exc2})") from exc2
    choice = served_by(choice, session.get_providers())
    log.info("%s: %s provider, %s (%s)", what, choice.provider, choice.precision, choice.reason)
    return session, choice
