"""OIDN's pretrained U-Net on ONNX Runtime: the same weights as the installed ``pyoidn``, another runtime.

Intel Open Image Denoise runs its filters on its own CPU kernels in fp32. This module runs the same network on
ONNX Runtime (``$GRADSEP_OIDN_RUNTIME=onnx``; model/oidn.py), so OpenVINO's bf16 kernels can be measured against
it: on this project's Zen 5 CPU they take 0.39 s per 720p layer against the library's 0.65 s, but bf16 rounding
in PU space raises RelMSE 1.04-4x on held-out frames, so the library stays the default (docs/oidn.md, "Runtime").
In fp32 the graph reproduces the library's output (tested).

It reads the weights of one OIDN model out of the installed ``pyoidn`` library (nothing is downloaded or
shipped: the weights are the library's own, so they always match the installed version), builds the U-Net as an
ONNX graph, and runs it with ONNX Runtime on the provider :func:`model.onnx_session.choose_provider` picks (the one the
``network`` method uses: OpenVINO in bf16 where the CPU has it, else ORT's CPU provider in fp32).

What OIDN does around its network is done here the same way (``RT`` filter, HDR colour, raw albedo/normal):

    colour × inputScale ─► clamp [0, FLT_MAX] ─► PU transfer / PU(65504) ┐
    albedo ─► clamp [0, 1]                                              ├─► zero-pad to 16 ─► U-Net ─► crop
    normal ─► clamp [-1, 1] ─► × ½ + ½                                  ┘
    ─► clamp ≥ 0 ─► × PU(65504) ─► inverse PU ─► ÷ inputScale

Frames above OIDN's own tile size (2160² pixels) run in tiles with OIDN's overlap (96 pixels, half the U-Net's
receptive field rounded to 16), each tile's core cropped, as OIDN does. Only the U-Nets of OIDN's base and
``small`` models are built (the ``large`` model has another layout); :func:`weights_for` says which model a
setting needs and ``None`` where this runtime cannot run it, and the caller then uses the library.

Weights: OIDN stores each model as a Tensor Archive (``.tza``: a small header, a table of named tensors, the
tensors fp16 ``oihw``) inside ``libOpenImageDenoise_core``, under the symbol ``oidn::blobs::weights::<model>``.
The symbol is found with pyelftools in the library's dynamic symbol table.
"""

from __future__ import annotations

import glob
import importlib.util
import logging
import math
import os
import struct
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gradsep.model.onnx_session import ProviderChoice, SessionSettings

log = logging.getLogger("gradsep.oidn")

#: OIDN pads every image to a multiple of this (its U-Net pools four times).
ALIGNMENT = 16
#: OIDN's largest tile (pixels) and the overlap between tiles (half the base U-Net's 174-pixel receptive
#: field, rounded up to the alignment): core/unet_filter.h.
MAX_TILE_PIXELS = 2160 * 2160
TILE_OVERLAP = 96
_F32_MAX = float(np.finfo(np.float32).max)

# --------------------------------------------------------------------------------------------------------------
# The PU transfer function (OIDN core/color.h): a perceptually uniform encoding of HDR radiance, normalised so
# that 65504 (the largest half float) maps to 1.
# --------------------------------------------------------------------------------------------------------------

PU_A, PU_B, PU_C, PU_D = 1.41283765e03, 1.64593172e00, 4.31384981e-01, -2.94139609e-03
PU_E, PU_F, PU_G = 1.92653254e-01, 6.26026094e-03, 9.98620152e-01
PU_Y0, PU_Y1 = 1.57945760e-06, 3.22087631e-02
PU_X0, PU_X1 = 2.23151711e-03, 3.70974749e-01
Y_MAX = 65504.0


class PUTransfer:
    """OIDN's PU curve with forward (radiance → network space) and inverse, as numpy float32 operations."""

    def __init__(self) -> None:
        self.norm = np.float32(1.0 / float(self._forward(np.array([Y_MAX], np.float32))[0]))

    @staticmethod
    def _forward(y: np.ndarray) -> np.ndarray:
        low = PU_A * y
        mid = PU_B * np.power(np.maximum(y, PU_Y0), PU_C) + PU_D
        high = PU_E * np.log(np.maximum(y, PU_Y1) + PU_F) + PU_G
        return np.where(y <= PU_Y0, low, np.where(y <= PU_Y1, mid, high)).astype(np.float32)

    def forward(self, y: np.ndarray) -> np.ndarray:
        return self._forward(y) * self.norm

    def inverse(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64) / float(self.norm)
        low = x / PU_A
        mid = np.power(np.maximum((x - PU_D) / PU_B, 0.0), 1.0 / PU_C)
        high = np.exp(np.minimum((x - PU_G) / PU_E, 88.0)) - PU_F  # exp(88) ~ 1.7e38: float32's range
        y = np.where(x <= PU_X0, low, np.where(x <= PU_X1, mid, high))
        return np.minimum(y, _F32_MAX).astype(np.float32)


PU = PUTransfer()

# The same transfer fused with the clamps, the layout change and the padding, compiled: the numpy formulation
# above costs ~0.13 s per 720p layer (a third of the bf16 graph), these kernels a few ms. model.kernels.AVAILABLE
# (GRADSEP_NUMBA=0, or no numba) selects the numpy path, which the tests compare them with.
from gradsep.model import kernels  # noqa: E402

if kernels.AVAILABLE:
    _jit = kernels._compiled

    @_jit
    def _clip_radiance(v):  # pragma: no cover - compiled
        """v clamped to [0, float32 max], NaN to 0."""
        if not v > 0.0:
            return 0.0
        return min(v, _F32_MAX)

    @_jit
    def _pu_forward(y):  # pragma: no cover - compiled
        if y <= PU_Y0:
            return PU_A * y
        if y <= PU_Y1:
            return PU_B * y**PU_C + PU_D
        return PU_E * math.log(y + PU_F) + PU_G

    @_jit
    def _pu_inverse(x):  # pragma: no cover - compiled
        if x <= PU_X0:
            return x / PU_A
        if x <= PU_X1:
            return ((x - PU_D) / PU_B) ** (1.0 / PU_C)
        return math.exp(min((x - PU_G) / PU_E, 88.0)) - PU_F

    @_jit
    def _encode(color, albedo, normal, scale, norm, out):  # pragma: no cover - compiled
        """out[0, :, :h, :w] = the network input of (h, w, 3) colour [+ albedo, normal]; the padding untouched."""
        height, width = color.shape[0], color.shape[1]
        aux = albedo.shape[0] == height
        for y in range(height):
            for x in range(width):
                for c in range(3):
                    out[0, c, y, x] = _pu_forward(_clip_radiance(float(color[y, x, c]) * scale)) * norm
                    if aux:
                        a = float(albedo[y, x, c])
                        out[0, 3 + c, y, x] = 0.0 if not a > 0.0 else min(a, 1.0)
                        n = float(normal[y, x, c])
                        n = 0.0 if n != n else max(-1.0, min(n, 1.0))
                        out[0, 6 + c, y, x] = n * 0.5 + 0.5
        return out

    @_jit
    def _decode(planes, y0, x0, rcp_norm, out_scale, out, oy, ox, height, width):  # pragma: no cover
        """out[oy:oy+height, ox:ox+width] = radiance of planes[:, y0:y0+height, x0:x0+width] (C, H, W)."""
        for y in range(height):
            for x in range(width):
                for c in range(3):
                    v = _clip_radiance(float(planes[c, y0 + y, x0 + x]))
                    out[oy + y, ox + x, c] = _clip_radiance(_pu_inverse(v * rcp_norm) * out_scale)
        return out

# --------------------------------------------------------------------------------------------------------------
# Weights: the installed library's Tensor Archives
# --------------------------------------------------------------------------------------------------------------

TZA_MAGIC = 0x41D7
_TZA_DTYPES = {"f": np.float32, "h": np.float16, "b": np.int8, "B": np.uint8}
#: The U-Net's convolutions in order (OIDN's base and small models share these names).
CONVS: tuple[str, ...] = ("enc_conv0", "enc_conv1", "enc_conv2", "enc_conv3", "enc_conv4", "enc_conv5a",
                          "enc_conv5b", "dec_conv4a", "dec_conv4b", "dec_conv3a", "dec_conv3b", "dec_conv2a",
                          "dec_conv2b", "dec_conv1a", "dec_conv1b", "dec_conv0")


class WeightsError(RuntimeError):
    """The installed OIDN library has no usable weights for a model (the caller falls back to the library)."""


def parse_tza(blob: bytes | memoryview) -> dict[str, np.ndarray]:
    """A Tensor Archive's tensors by name (float32 copies), checking every offset against the blob."""
    buf = memoryview(blob)
    if len(buf) < 12:
        raise WeightsError("tensor archive too short")
    magic, major, _minor, table = struct.unpack_from("<HBBQ", buf, 0)
    if magic != TZA_MAGIC or major != 2:
        raise WeightsError(f"not a version-2 tensor archive (magic {magic:#x}, version {major})")
    if not 12 <= table <= len(buf) - 4:
        raise WeightsError("tensor archive table outside the blob")
    (count,) = struct.unpack_from("<I", buf, table)
    pos, tensors = table + 4, {}
    for _ in range(count):
        (n,) = struct.unpack_from("<H", buf, pos)
        name = bytes(buf[pos + 2:pos + 2 + n]).decode()
        pos += 2 + n
        ndim = buf[pos]
        shape = struct.unpack_from(f"<{ndim}I", buf, pos + 1)
        pos += 1 + 4 * ndim + ndim  # shape, then the layout letters
        dtype = _TZA_DTYPES.get(chr(buf[pos]))
        (offset,) = struct.unpack_from("<Q", buf, pos + 1)
        pos += 9
        if dtype is None:
            raise WeightsError(f"tensor {name!r} has an unknown data type")
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        if offset + size > table:
            raise WeightsError(f"tensor {name!r} runs past the archive")
        tensors[name] = np.frombuffer(buf, dtype, int(np.prod(shape)), offset).reshape(shape).astype(np.float32)
    return tensors


def library_path() -> Path:
    """The installed pyoidn's ``libOpenImageDenoise_core`` (WeightsError when pyoidn or the library is missing)."""
    spec = importlib.util.find_spec("pyoidn")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError("pyoidn is not installed")
    for folder in spec.submodule_search_locations:
        found = sorted(glob.glob(os.path.join(folder, "oidn", "lib*", "libOpenImageDenoise_core.so*")))
        if found:
            return Path(found[-1])
    raise WeightsError("pyoidn has no libOpenImageDenoise_core library (not a Linux wheel?)")


def read_weights(model: str, library: str | os.PathLike[str] | None = None) -> dict[str, np.ndarray]:
    """The tensors of OIDN model ``model`` (e.g. ``rt_hdr_alb_nrm_small``) from the library's symbol table."""
    from elftools.elf.elffile import ELFFile

    path = Path(library) if library is not None else library_path()
    symbol = f"_ZN4oidn5blobs7weights{len(model)}{model}E"  # oidn::blobs::weights::<model>, Itanium-mangled
    with open(path, "rb") as fh:
        elf = ELFFile(fh)
        table = elf.get_section_by_name(".dynsym") or elf.get_section_by_name(".symtab")
        hits = table.get_symbol_by_name(symbol) if table is not None else None
        if not hits:
            raise WeightsError(f"{path.name} has no weights for OIDN model {model}")
        sym = hits[0]
        address, size = sym["st_value"], sym["st_size"]
        for seg in elf.iter_segments():
            if seg["p_type"] == "PT_LOAD" and seg["p_vaddr"] <= address < seg["p_vaddr"] + seg["p_filesz"]:
                fh.seek(seg["p_offset"] + address - seg["p_vaddr"])
                return parse_tza(fh.read(size))
    raise WeightsError(f"{path.name}: the weights of {model} lie outside its loaded segments")


def weights_for(aux: str, quality: str) -> str | None:
    """The OIDN model the ``RT`` filter runs on HDR colour for this setting, or None where this runtime does not
    build it: prefiltered (``cleanAux``) features select OIDN's large model at quality high."""
    if aux == "prefiltered":
        return None
    inputs = {"raw": "_alb_nrm", "none": ""}[aux]
    return f"rt_hdr{inputs}{'_small' if quality == 'fast' else ''}"


# --------------------------------------------------------------------------------------------------------------
# The U-Net as an ONNX graph
# --------------------------------------------------------------------------------------------------------------


#: Where :func:`unet_graph` splits the U-Net for mixed precision: the body (everything below full resolution)
#: ends with this activation (half resolution), the head (the full-resolution decoder level) starts from it.
SPLIT = "dec_conv2b.relu"


def _skip_conv(skip: str) -> str:
    """The weight of the convolution whose (pooled) output is the skip tensor ``skip`` of a decoder level."""
    return {"pool1": "enc_conv1.weight", "pool2": "enc_conv2.weight", "pool3": "enc_conv3.weight"}[skip]


def unet_graph(weights: dict[str, np.ndarray], name: str, part: str = "all") -> bytes:
    """The serialized ONNX model of OIDN's U-Net, or of one ``part`` of it.

    ``all``: ``input`` (1, C, H, W) → ``output`` (1, 3, H, W), H and W multiples of :data:`ALIGNMENT`. 3×3
    convolutions with ReLU, 2×2 max pools, nearest 2× upsampling and skip concatenations, channel counts read off
    the weights (OIDN's base and small models). ``body``: ``input`` → ``output`` = the :data:`SPLIT` activation
    (half resolution); ``head``: (``input``, ``skip`` = that activation) → the image.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if part not in ("all", "body", "head"):
        raise ValueError(f"part must be all, body or head, got {part!r}")
    missing = [c for c in CONVS if f"{c}.weight" not in weights or f"{c}.bias" not in weights]
    if missing:
        raise WeightsError(f"{name} is not an OIDN base/small U-Net (missing {', '.join(missing[:3])})")
    nodes: list[Any] = []
    channels = int(weights["enc_conv0.weight"].shape[1])

    def conv(x: str, c: str, relu: bool = True) -> str:
        nodes.append(helper.make_node("Conv", [x, f"{c}.weight", f"{c}.bias"], [c], kernel_shape=[3, 3],
                                      pads=[1, 1, 1, 1]))
        if not relu:
            return c
        nodes.append(helper.make_node("Relu", [c], [f"{c}.relu"]))
        return f"{c}.relu"

    def pool(x: str, tag: str) -> str:
        nodes.append(helper.make_node("MaxPool", [x], [tag], kernel_shape=[2, 2], strides=[2, 2]))
        return tag

    derived: dict[str, np.ndarray] = {}

    def up_conv(x: str, skip: str, c: str) -> str:
        """ReLU(conv c of concat(nearest 2x upsample of x, skip)), computed without the upsampled tensor: a 3x3
        kernel over a nearest-upsampled image is, per output phase (a, b), a 2x2 kernel over the image itself
        (rows {i-1, i} for even output rows, {i, i+1} for odd ones; same for columns), so the upsampled
        channels cost 4 instead of 9 multiply-adds per output pixel. The four phases interleave by DepthToSpace.
        Exact up to float rounding (the tests compare it with the library)."""
        weight = weights[f"{c}.weight"].astype(np.float32)
        n_up = weight.shape[1] - (channels if skip == "input" else int(weights[_skip_conv(skip)].shape[0]))
        rows = (np.array([[1, 0, 0], [0, 1, 1]], np.float32), np.array([[1, 1, 0], [0, 0, 1]], np.float32))
        phases = []
        for a in (0, 1):
            for b in (0, 1):
                kernel = np.einsum("py,oiyx,qx->oipq", rows[a], weight[:, :n_up], rows[b])
                derived[f"{c}.phase{a}{b}"] = np.ascontiguousarray(kernel)
                nodes.append(helper.make_node("Conv", [x, f"{c}.phase{a}{b}"], [f"{c}.phase{a}{b}.out"],
                                              kernel_shape=[2, 2], pads=[1 - a, 1 - b, a, b]))
                phases.append(f"{c}.phase{a}{b}.out")
        nodes.append(helper.make_node("Concat", phases, [f"{c}.phases"], axis=1))
        nodes.append(helper.make_node("DepthToSpace", [f"{c}.phases"], [f"{c}.up"], blocksize=2, mode="DCR"))
        derived[f"{c}.skip_weight"] = np.ascontiguousarray(weight[:, n_up:])
        nodes.append(helper.make_node("Conv", [skip, f"{c}.skip_weight", f"{c}.bias"], [f"{c}.skip"],
                                      kernel_shape=[3, 3], pads=[1, 1, 1, 1]))
        nodes.append(helper.make_node("Add", [f"{c}.up", f"{c}.skip"], [c]))
        nodes.append(helper.make_node("Relu", [c], [f"{c}.relu"]))
        return f"{c}.relu"

    if part != "head":
        # Encoder
        x = conv("input", "enc_conv0")
        pool1 = pool(conv(x, "enc_conv1"), "pool1")
        pool2 = pool(conv(pool1, "enc_conv2"), "pool2")
        pool3 = pool(conv(pool2, "enc_conv3"), "pool3")
        x = pool(conv(pool3, "enc_conv4"), "pool4")
        x = conv(conv(x, "enc_conv5a"), "enc_conv5b")
        # Decoder: upsample, concatenate the encoder's skip, two convolutions per level
        x = conv(up_conv(x, pool3, "dec_conv4a"), "dec_conv4b")
        x = conv(up_conv(x, pool2, "dec_conv3a"), "dec_conv3b")
        x = conv(up_conv(x, pool1, "dec_conv2a"), "dec_conv2b")
        assert x == SPLIT
    if part != "body":
        x = conv(up_conv("skip" if part == "head" else SPLIT, "input", "dec_conv1a"), "dec_conv1b")
        x = conv(x, "dec_conv0", relu=False)
    nodes.append(helper.make_node("Identity", [x], ["output"]))

    used = {i for n in nodes for i in n.input}
    inits = [numpy_helper.from_array(weights[k].astype(np.float32), k) for c in CONVS
             for k in (f"{c}.weight", f"{c}.bias") if k in used]
    inits += [numpy_helper.from_array(v, k) for k, v in derived.items() if k in used]
    inputs = [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, channels, "height", "width"])]
    if part == "head":
        skip = int(weights["dec_conv2b.weight"].shape[0])
        inputs.append(helper.make_tensor_value_info("skip", TensorProto.FLOAT, [1, skip, "half_h", "half_w"]))
    out_c = int(weights["dec_conv2b.weight"].shape[0]) if part == "body" else 3
    out_h, out_w = ("half_h", "half_w") if part == "body" else ("height", "width")
    graph = helper.make_graph(nodes, f"{name}-{part}", inputs,
                              [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, out_c, out_h, out_w])],
                              initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="gradsep")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model.SerializeToString()


# --------------------------------------------------------------------------------------------------------------
# The filter
# --------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Tile:
    src: tuple[int, int, int, int]   # (y0, y1, x0, x1) of the input window in the image
    core: tuple[int, int, int, int]  # the part of the image the window's output owns


def plan_tiles(height: int, width: int, max_pixels: int = MAX_TILE_PIXELS,
               overlap: int = TILE_OVERLAP) -> list[_Tile]:
    """One window for an image of up to ``max_pixels``, else a grid of square-ish windows whose cores cover
    the image once, each with ``overlap`` pixels of context on its interior sides."""
    if height * width <= max_pixels:
        return [_Tile((0, height, 0, width), (0, height, 0, width))]
    side = max(ALIGNMENT, int(math.sqrt(max_pixels)) - 2 * overlap) // ALIGNMENT * ALIGNMENT
    tiles = []
    for y0 in range(0, height, side):
        for x0 in range(0, width, side):
            y1, x1 = min(height, y0 + side), min(width, x0 + side)
            tiles.append(_Tile((max(0, y0 - overlap), min(height, y1 + overlap),
                                max(0, x0 - overlap), min(width, x1 + overlap)), (y0, y1, x0, x1)))
    return tiles


class _Split:
    """The U-Net as two sessions: the body (everything below full resolution) in bf16, the full-resolution
    decoder level in fp32. bf16 rounding there is what costs accuracy (its output is PU-encoded: an error dx is
    a relative radiance error of ~16 dx), while the body's errors are mostly smoothed away: on held-out frames
    all-bf16 scored 1.51x the library's RelMSE (worst frame 4x), this split 1.01x (docs/oidn.md, "Runtime")."""

    def __init__(self, body: Any, head: Any) -> None:
        self.body, self.head = body, head

    def get_providers(self) -> list[str]:
        """The providers both sessions run on: a part ORT built without the accelerated provider runs on the CPU."""
        head = set(self.head.get_providers())
        return [p for p in self.body.get_providers() if p in head]

    def run(self, names: list[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        skip = self.body.run(["output"], feeds)[0]
        return self.head.run(names, {"input": feeds["input"], "skip": skip})


class OnnxUNet:
    """One OIDN model (``rt_hdr_alb_nrm_small``, ...) on ONNX Runtime. Thread-safe (ORT sessions are).

    The provider is :func:`model.onnx_session.choose_provider`'s (``$GRADSEP_ONNX_PROVIDER``). Where that is OpenVINO
    in bf16 the graph runs split (:class:`_Split`: body bf16, full-resolution head fp32, reported as precision
    ``bf16+fp32``); elsewhere whole, in fp32.
    """

    def __init__(self, model: str, settings: SessionSettings | None = None,
                 library: str | os.PathLike[str] | None = None) -> None:
        import onnxruntime as ort

        from gradsep.model.onnx_session import ProviderChoice, SessionSettings, open_session

        self.model = model
        self.weights = read_weights(model, library)
        settings = settings or SessionSettings()

        def session(part: str, choice: ProviderChoice) -> Any:
            return ort.InferenceSession(unet_graph(self.weights, model, part), settings.options(),
                                        providers=choice.providers())

        def build(choice: ProviderChoice) -> Any:
            if (choice.provider, choice.precision) == ("openvino", "bf16"):
                return _Split(session("body", choice), session("head", replace(choice, precision="fp32")))
            return session("all", choice)

        self.session, choice = open_session(build, f"OIDN model {model} on ONNX Runtime", settings)
        if isinstance(self.session, _Split) and choice.provider == "openvino":  # what serves it, not what was asked
            choice = ProviderChoice("openvino", "bf16+fp32", f"{choice.reason}; full-resolution level in fp32")
        self.choice: ProviderChoice = choice
        self.channels = int(self.weights["enc_conv0.weight"].shape[1])  # the graph checked the layers exist

    def denoise(self, color: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None,
                input_scale: float) -> np.ndarray:
        """OIDN's ``RT`` filter on HDR ``color`` (H, W, 3) with raw ``albedo``/``normal`` (or None for a model
        without them) at ``input_scale``: (H, W, 3) float32, finite, ≥ 0."""
        height, width = color.shape[:2]
        want = 9 if albedo is not None else 3
        if want != self.channels:
            raise ValueError(f"OIDN model {self.model} takes {self.channels} input channels, got {want}")
        out = np.empty((height, width, 3), np.float32)
        compiled = kernels.AVAILABLE
        for tile in plan_tiles(height, width):
            sy0, sy1, sx0, sx1 = tile.src
            cy0, cy1, cx0, cx1 = tile.core
            planes = self._inputs(color[sy0:sy1, sx0:sx1], None if albedo is None else albedo[sy0:sy1, sx0:sx1],
                                  None if normal is None else normal[sy0:sy1, sx0:sx1], input_scale, compiled)
            result = self.session.run(["output"], {"input": planes})[0][0]
            if compiled:
                _decode(result, cy0 - sy0, cx0 - sx0, 1.0 / float(PU.norm), 1.0 / input_scale if input_scale
                        else 0.0, out, cy0, cx0, cy1 - cy0, cx1 - cx0)
            else:
                core = result[:, cy0 - sy0:cy1 - sy0, cx0 - sx0:cx1 - sx0]
                out[cy0:cy1, cx0:cx1] = self._output(np.moveaxis(core, 0, -1), input_scale)
        return out

    def _inputs(self, color: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None,
                scale: float, compiled: bool = False) -> np.ndarray:
        """The network's (1, C, H16, W16) input: the transfer-encoded colour and the features, zero-padded at
        the bottom and right to the alignment (where OIDN puts its padding too)."""
        h, w = color.shape[:2]
        hp, wp = -(-h // ALIGNMENT) * ALIGNMENT, -(-w // ALIGNMENT) * ALIGNMENT
        planes = np.zeros((1, self.channels, hp, wp), np.float32)
        if compiled:
            empty = np.zeros((0, 0, 3), np.float32)
            return _encode(color, empty if albedo is None else albedo, empty if normal is None else normal,
                           float(scale), float(PU.norm), planes)
        c = np.nan_to_num(color * np.float32(scale), nan=0.0, posinf=_F32_MAX, neginf=0.0)
        np.clip(c, 0.0, _F32_MAX, out=c)
        planes[0, 0:3, :h, :w] = np.moveaxis(PU.forward(c), -1, 0)
        if albedo is not None and normal is not None:
            planes[0, 3:6, :h, :w] = np.moveaxis(np.clip(np.nan_to_num(albedo, nan=0.0), 0.0, 1.0), -1, 0)
            n = np.clip(np.nan_to_num(normal, nan=0.0), -1.0, 1.0)
            planes[0, 6:9, :h, :w] = np.moveaxis(n * np.float32(0.5) + np.float32(0.5), -1, 0)
        return planes

    @staticmethod
    def _output(out: np.ndarray, scale: float) -> np.ndarray:
        out = np.array(out, np.float32)
        np.nan_to_num(out, copy=False, nan=0.0, posinf=_F32_MAX, neginf=0.0)
        np.clip(out, 0.0, _F32_MAX, out=out)
        radiance = PU.inverse(out) * np.float32(1.0 / scale if scale else 0.0)
        np.nan_to_num(radiance, copy=False, nan=0.0, posinf=_F32_MAX, neginf=0.0)
        return np.clip(radiance, 0.0, _F32_MAX, out=radiance)

    def describe(self) -> dict[str, Any]:
        return {"model": self.model, **self.choice.describe()}
