"""A small TensorFlow Lite reader and an op-by-op torch replay of its graph (differentiable).

`read_tflite(path)` parses a `.tflite` flatbuffer (through the PyPI package `tflite`) into
plain Python: tensors (name, shape, dtype, constant data or None) and operators (name,
input and output tensor indices, options). `TfliteModule(graph)` turns every constant into a
frozen `nn.Parameter` (float16 weights are dequantized once to float32) and replays the
operators with `torch.nn.functional`, so gradients flow from the outputs back to the input
image (and, after `requires_grad_(True)`, to the weights).

Supported operators (the set of MediaPipe's face detectors, face mesh and iris networks):
DEQUANTIZE, DENSIFY, CONV_2D, DEPTHWISE_CONV_2D, ADD, PRELU, RELU, MAX_POOL_2D, PAD, RESHAPE,
CONCATENATION, RESIZE_BILINEAR, DEPTH_TO_SPACE, with fused NONE / RELU / RELU6 / RELU_N1_TO_1
activations and TF "SAME" (asymmetric, extra pixel after) or "VALID" padding. Anything else
raises `ValueError` naming the operator.

Sparse constants (TFLite's `SparsityParameters`: per traversed dimension DENSE or SPARSE_CSR,
as in `face_detection_full_range_sparse.tflite`) are expanded to dense arrays when the file is
read (`densify`), so DENSIFY replays as the identity on a constant.

Speed: `forward` runs a plan resolved once per input size (`_build_plan`: every padding known,
symmetric ones inside the convolution, 1 x 1 convolutions and whole-input ones as matrix
products on the NHWC memory, weights stored channels-last, registers freed after their last use,
sums written into a dying operand when no gradient is recorded); `forward_reference` is the plain
op-by-op replay it is tested against (tests/nodes/landmarks/test_netspeed.py: values to 2e-5 of
the output's scale in float32, gradients to 1e-10 in float64). One thread, per call: face mesh
7.6 -> 5.3 ms, iris (2 eyes) 12.3 -> 9.3 ms (`bench/landmark_networks.py`, load 3).

Layout: TFLite activations are NHWC; the replay keeps 4-D activations NCHW internally
(torch's fast path) and converts back to NHWC wherever the layout is observable (RESHAPE,
CONCATENATION on a non-channel axis, and the graph outputs), so outputs have exactly the
shapes and values TFLite gives.

This module imports torch at the top: import it from node `run()` methods, not from the
package `__init__`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["TfliteTensor", "TfliteOperator", "TfliteGraph", "read_tflite", "TfliteModule",
           "SUPPORTED_OPERATORS", "densify", "depth_to_space", "resize_bilinear_tf"]

SUPPORTED_OPERATORS = ("DEQUANTIZE", "DENSIFY", "CONV_2D", "DEPTHWISE_CONV_2D", "ADD", "PRELU", "RELU",
                       "MAX_POOL_2D", "PAD", "RESHAPE", "CONCATENATION", "RESIZE_BILINEAR", "DEPTH_TO_SPACE")
"""Operators `TfliteModule` replays."""

_NUMPY_TYPES = {0: np.float32, 1: np.float16, 2: np.int32, 3: np.uint8, 4: np.int64, 9: np.int8}


@dataclass
class TfliteTensor:
    """One tensor of a TFLite graph.

    Attributes:
        name: the tensor's name in the file.
        shape: its shape (NHWC for images).
        dtype: numpy dtype of its elements.
        data: the constant value (weights, biases, shape vectors), or None for activations.
    """

    name: str
    shape: tuple[int, ...]
    dtype: Any
    data: np.ndarray | None = None


@dataclass
class TfliteOperator:
    """One operator: builtin name, tensor indices in and out, parsed options."""

    name: str
    inputs: list[int]
    outputs: list[int]
    options: dict[str, Any] = field(default_factory=dict)


@dataclass
class TfliteGraph:
    """A parsed TFLite subgraph: tensors, operators in execution order, graph inputs/outputs."""

    tensors: list[TfliteTensor]
    operators: list[TfliteOperator]
    inputs: list[int]
    outputs: list[int]
    source: str = ""

    def tensor_index(self, name: str) -> int:
        """Index of the tensor called `name` (ValueError listing the outputs when absent)."""
        for index, tensor in enumerate(self.tensors):
            if tensor.name == name:
                return index
        raise ValueError(f"{self.source}: no tensor named {name!r}; outputs are "
                         f"{[self.tensors[i].name for i in self.outputs]}")


def _options(op: Any, name: str) -> dict[str, Any]:
    import tflite

    table = op.BuiltinOptions()
    classes = {"CONV_2D": tflite.Conv2DOptions, "DEPTHWISE_CONV_2D": tflite.DepthwiseConv2DOptions,
               "MAX_POOL_2D": tflite.Pool2DOptions, "ADD": tflite.AddOptions,
               "CONCATENATION": tflite.ConcatenationOptions, "RESHAPE": tflite.ReshapeOptions,
               "RESIZE_BILINEAR": tflite.ResizeBilinearOptions, "DEPTH_TO_SPACE": tflite.DepthToSpaceOptions}
    if table is None or name not in classes:
        return {}
    opt = classes[name]()
    opt.Init(table.Bytes, table.Pos)
    out: dict[str, Any] = {}
    if name in ("CONV_2D", "DEPTHWISE_CONV_2D", "MAX_POOL_2D"):
        out.update(padding="SAME" if opt.Padding() == tflite.Padding.SAME else "VALID",
                   stride=(opt.StrideH(), opt.StrideW()), activation=opt.FusedActivationFunction())
    if name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
        out["dilation"] = (opt.DilationHFactor(), opt.DilationWFactor())
    if name == "DEPTHWISE_CONV_2D":
        out["depth_multiplier"] = opt.DepthMultiplier()
    if name == "MAX_POOL_2D":
        out["filter"] = (opt.FilterHeight(), opt.FilterWidth())
    if name in ("ADD", "CONCATENATION"):
        out["activation"] = opt.FusedActivationFunction()
    if name == "CONCATENATION":
        out["axis"] = opt.Axis()
    if name == "RESHAPE" and not opt.NewShapeIsNone():
        out["new_shape"] = [int(v) for v in opt.NewShapeAsNumpy()]
    if name == "RESIZE_BILINEAR":
        out.update(align_corners=bool(opt.AlignCorners()), half_pixel_centers=bool(opt.HalfPixelCenters()))
    if name == "DEPTH_TO_SPACE":
        out["block_size"] = int(opt.BlockSize())
    return out


def densify(values: np.ndarray, shape: tuple[int, ...], traversal_order: list[int],
            dims: list[tuple[str, int, np.ndarray | None, np.ndarray | None]]) -> np.ndarray:
    """Expand a TFLite sparse tensor (no block map) to its dense array.

    The dimensions are traversed in `traversal_order`; a DENSE dimension of size n gives each
    position p of the level above the children p * n + i (i < n), a SPARSE_CSR one the children
    segments[p] .. segments[p + 1] - 1 with coordinates indices[child]. After the last level a
    position is the index of the stored value (TFLite's FormatConverter, without blocks).

    Args:
        values: (N,) the stored (non-zero) values, in traversal order.
        shape: the dense shape.
        traversal_order: dimension traversed at each level (a permutation of range(len(shape))).
        dims: per level ("DENSE", size, None, None) or ("SPARSE_CSR", 0, segments, indices).
    Returns:
        the dense array of `shape`, zeros where nothing is stored.

    Example:
        >>> densify(np.array([5., 7.]), (2, 3), [0, 1],
        ...         [("DENSE", 2, None, None), ("SPARSE_CSR", 0, np.array([0, 1, 2]), np.array([2, 0]))]).tolist()
        [[0.0, 0.0, 5.0], [7.0, 0.0, 0.0]]
    """
    if sorted(traversal_order) != list(range(len(shape))) or len(dims) != len(shape):
        raise ValueError(f"sparsity: traversal order {traversal_order} with {len(dims)} dimension(s) does "
                         f"not describe a tensor of shape {shape} (block maps are not supported)")
    positions = np.zeros(1, np.int64)
    coords = np.zeros((1, 0), np.int64)
    for kind, size, segments, indices in dims:
        if kind == "DENSE":
            child = np.arange(size, dtype=np.int64)
            positions = (positions[:, None] * size + child).reshape(-1)
            coords = np.concatenate([np.repeat(coords, size, 0), np.tile(child, len(coords))[:, None]], 1)
        else:
            segments = np.asarray(segments, np.int64)
            start, stop = segments[positions], segments[positions + 1]
            counts = stop - start
            parent = np.repeat(np.arange(len(positions)), counts)
            offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)  # within a segment
            positions = np.repeat(start, counts) + offset
            coords = np.concatenate([coords[parent], np.asarray(indices, np.int64)[positions][:, None]], 1)
    if len(positions) != len(values):
        raise ValueError(f"sparsity: the index arrays address {len(positions)} values, {len(values)} are stored")
    dense = np.zeros(shape, values.dtype)
    axes = np.empty_like(coords)
    axes[:, traversal_order] = coords
    dense[tuple(axes.T)] = values[positions]
    return dense


def _sparse_dims(sparsity: Any) -> tuple[list[int], list[tuple[str, int, np.ndarray | None, np.ndarray | None]]]:
    """Traversal order and per-level (format, dense size, segments, indices) of a SparsityParameters table."""
    import tflite

    vectors = {tflite.SparseIndexVector.Int32Vector: tflite.Int32Vector,
               tflite.SparseIndexVector.Uint16Vector: tflite.Uint16Vector,
               tflite.SparseIndexVector.Uint8Vector: tflite.Uint8Vector}

    def vector(kind: int, table: Any) -> np.ndarray:
        if kind not in vectors:
            raise ValueError(f"sparsity: index vector type {kind}, expected one of {sorted(vectors)}")
        v = vectors[kind]()
        v.Init(table.Bytes, table.Pos)
        return np.asarray(v.ValuesAsNumpy(), np.int64)

    if sparsity.BlockMapLength():
        raise ValueError(f"sparsity: block map {list(sparsity.BlockMapAsNumpy())} is not supported")
    dims = []
    for d in range(sparsity.DimMetadataLength()):
        meta = sparsity.DimMetadata(d)
        if meta.Format() == tflite.DimensionType.DENSE:
            dims.append(("DENSE", int(meta.DenseSize()), None, None))
        else:
            dims.append(("SPARSE_CSR", 0, vector(meta.ArraySegmentsType(), meta.ArraySegments()),
                         vector(meta.ArrayIndicesType(), meta.ArrayIndices())))
    return [int(v) for v in sparsity.TraversalOrderAsNumpy()], dims


def read_tflite(path: str | Path) -> TfliteGraph:
    """Parse the first subgraph of a `.tflite` file.

    Args:
        path: the flatbuffer file.
    Returns:
        TfliteGraph with constant tensors' data as numpy arrays of their stored dtype.
    Raises:
        FileNotFoundError: no such file.
        ValueError: not a TFLite flatbuffer, or a tensor of an unsupported element type.
    """
    import tflite

    path = Path(path)
    buf = path.read_bytes()
    if len(buf) < 8 or buf[4:8] != b"TFL3":
        raise ValueError(f"path: '{path}' is not a TFLite flatbuffer (no 'TFL3' identifier)")
    model = tflite.Model.GetRootAsModel(buf, 0)
    graph = model.Subgraphs(0)
    names = {v: k for k, v in vars(tflite.BuiltinOperator).items() if not k.startswith("_")}
    codes = []
    for i in range(model.OperatorCodesLength()):
        code = model.OperatorCodes(i)
        codes.append(names.get(max(code.BuiltinCode(), code.DeprecatedBuiltinCode()), "CUSTOM"))
    tensors = []
    for i in range(graph.TensorsLength()):
        t = graph.Tensors(i)
        if t.Type() not in _NUMPY_TYPES:
            raise ValueError(f"path: '{path}': tensor {t.Name().decode()!r} has TFLite type "
                             f"{t.Type()}, expected one of {sorted(_NUMPY_TYPES)}")
        dtype = _NUMPY_TYPES[t.Type()]
        shape = tuple(int(s) for s in t.ShapeAsNumpy()) if t.ShapeLength() else ()
        raw = model.Buffers(t.Buffer()).DataAsNumpy() if t.Buffer() < model.BuffersLength() else 0
        data = None
        if isinstance(raw, np.ndarray) and raw.size:
            data = np.frombuffer(raw.tobytes(), dtype=dtype)
            if t.Sparsity() is not None:  # stored compressed: expand once (DENSIFY of a constant)
                try:
                    data = densify(data, shape, *_sparse_dims(t.Sparsity()))
                except ValueError as error:
                    raise ValueError(f"path: '{path}': tensor {t.Name().decode()!r}: {error}") from None
            data = data.reshape(shape)
        tensors.append(TfliteTensor(t.Name().decode(), shape, dtype, data))
    operators = []
    for i in range(graph.OperatorsLength()):
        op = graph.Operators(i)
        name = codes[op.OpcodeIndex()]
        operators.append(TfliteOperator(name, [int(v) for v in op.InputsAsNumpy()],
                                        [int(v) for v in op.OutputsAsNumpy()], _options(op, name)))
    return TfliteGraph(tensors, operators, [int(v) for v in graph.InputsAsNumpy()],
                       [int(v) for v in graph.OutputsAsNumpy()], source=str(path))


def _same_pad(size: int, kernel: int, stride: int, dilation: int) -> tuple[int, int]:
    """TF 'SAME' padding (before, after) of one axis: the extra pixel goes after."""
    out = -(-size // stride)
    total = max((out - 1) * stride + (kernel - 1) * dilation + 1 - size, 0)
    return total // 2, total - total // 2


def _activate(x: Tensor, code: int) -> Tensor:
    if code == 0:
        return x
    if code == 1:
        return F.relu(x)
    if code == 2:
        return x.clamp(-1.0, 1.0)
    if code == 3:
        return x.clamp(0.0, 6.0)
    raise ValueError(f"fused activation: expected NONE, RELU, RELU_N1_TO_1 or RELU6, found code {code}")


def depth_to_space(x: Tensor, block: int) -> Tensor:
    """TFLite DEPTH_TO_SPACE on an NCHW tensor: (B, C * b * b, H, W) -> (B, C, H * b, W * b).

    TFLite's channel order (NHWC "DCR"): output[n, h * b + i, w * b + j, c] =
    input[n, h, w, (i * b + j) * C + c] (torch's `pixel_shuffle` orders the channels (c, i, j)).
    """
    bsz, channels, height, width = x.shape
    if channels % (block * block):
        raise ValueError(f"DEPTH_TO_SPACE: expected channels divisible by {block * block}, found {channels}")
    out = channels // (block * block)
    return (x.reshape(bsz, block, block, out, height, width).permute(0, 3, 4, 1, 5, 2)
            .reshape(bsz, out, height * block, width * block))


def _source_index(out_size: int, in_size: int, align_corners: bool, half_pixel: bool,
                  device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """TFLite's bilinear source coordinate of each output pixel of one axis: (lower, upper, weight of upper)."""
    i = torch.arange(out_size, device=device, dtype=torch.float64)
    if align_corners and out_size > 1:
        src = i * ((in_size - 1) / (out_size - 1))
    elif half_pixel:
        src = (i + 0.5) * (in_size / out_size) - 0.5
    else:
        src = i * (in_size / out_size)
    low = torch.floor(src)
    weight = (src - low).to(dtype)
    lower = low.clamp(0, in_size - 1).long()
    upper = torch.ceil(src).clamp(0, in_size - 1).long()
    return lower, upper, weight


def resize_bilinear_tf(x: Tensor, size: tuple[int, int], align_corners: bool = False,
                       half_pixel_centers: bool = False) -> Tensor:
    """TFLite RESIZE_BILINEAR on an NCHW tensor (B, C, H, W) -> (B, C, size[0], size[1]).

    Per axis the output pixel i reads the input at s = i (in - 1) / (out - 1) (`align_corners`),
    (i + 1/2) in / out - 1/2 (`half_pixel_centers`) or i in / out (neither, TF's legacy mode);
    the value is x[floor(s)] + (s - floor(s)) (x[ceil(s)] - x[floor(s)]), indices clamped to the
    input (TFLite's reference kernel).
    """
    (ly, uy, wy), (lx, ux, wx) = (_source_index(o, n, align_corners, half_pixel_centers, x.device, x.dtype)
                                  for o, n in zip(size, x.shape[2:]))
    rows = x[:, :, ly] + (x[:, :, uy] - x[:, :, ly]) * wy[:, None]
    return rows[..., lx] + (rows[..., ux] - rows[..., lx]) * wx


class TfliteModule(nn.Module):
    """Replay a TFLite graph with torch ops (see the module docstring).

    Args:
        graph: the parsed graph (`read_tflite`).
        outputs: names of the tensors `forward` returns, in order; default the graph outputs.

    Forward:
        image: (B, H, W, C) float tensor, NHWC like the TFLite input (any batch size B; H, W
            as the file's input).
        Returns a tuple of tensors, one per output, each (B, ...) as TFLite shapes it (the
        file's leading 1 replaced by B).

    Note:
        Weights are frozen `nn.Parameter`s (`requires_grad=False`); the module is float32 and
        can be moved with `.to(device)` / `.double()` (float64 for gradient checks).
    """

    def __init__(self, graph: TfliteGraph, outputs: list[str] | None = None):
        super().__init__()
        self.graph = graph
        unsupported = sorted({op.name for op in graph.operators} - set(SUPPORTED_OPERATORS))
        if unsupported:
            raise ValueError(f"{graph.source}: unsupported TFLite operator(s) {unsupported}; "
                             f"supported: {list(SUPPORTED_OPERATORS)}")
        self.output_indices = ([graph.tensor_index(n) for n in outputs] if outputs
                               else list(graph.outputs))
        self.weights = nn.ParameterDict()
        self._plans: dict[tuple[int, ...], tuple[list, int, int, list]] = {}  # input (H, W, C) -> `_build_plan`
        self._const: dict[int, str] = {}
        self._conv: dict[int, tuple[str, str | None]] = {}
        raw: dict[int, Tensor] = {}
        for index, tensor in enumerate(graph.tensors):
            if tensor.data is not None and tensor.dtype in (np.float16, np.float32):
                raw[index] = torch.from_numpy(tensor.data.astype(np.float32))
        for op in graph.operators:  # a DEQUANTIZE (DENSIFY) output is its input's constant, converted once
            if op.name in ("DEQUANTIZE", "DENSIFY") and op.inputs[0] in raw:
                raw[op.outputs[0]] = raw[op.inputs[0]]
        prepared: set[int] = set()
        for k, op in enumerate(graph.operators):
            if op.name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
                w = raw[op.inputs[1]]
                # CONV_2D weights OHWI -> OIHW; DEPTHWISE 1HW(C*M) -> (C*M)1HW
                # (stored channels-last: the memory of an NHWC activation, which convolutions of
                # channels-last inputs would otherwise copy the weight to on every call)
                w = w.permute(0, 3, 1, 2) if op.name == "CONV_2D" else w.permute(3, 0, 1, 2)
                self.weights[f"op{k}_w"] = nn.Parameter(w.contiguous(memory_format=torch.channels_last),
                                                        requires_grad=False)
                bias = None
                if len(op.inputs) > 2 and op.inputs[2] >= 0:
                    bias = f"op{k}_b"
                    self.weights[bias] = nn.Parameter(raw[op.inputs[2]].clone(), requires_grad=False)
                self._conv[k] = (f"op{k}_w", bias)
                prepared.update(op.inputs[1:3])
            elif op.name == "PRELU":  # alpha (..., C) -> (C, 1, 1) for NCHW
                alpha = raw[op.inputs[1]].reshape(-1, 1, 1).contiguous()
                self.weights[f"op{k}_alpha"] = nn.Parameter(alpha, requires_grad=False)
                self._conv[k] = (f"op{k}_alpha", None)
                prepared.add(op.inputs[1])
        for op in graph.operators:  # constants used as plain operands (ADD, CONCATENATION)
            if op.name in ("ADD", "CONCATENATION"):
                for i in op.inputs:
                    if i in raw and i not in self._const:
                        self._const[i] = f"t{i}"
                        self.weights[f"t{i}"] = nn.Parameter(raw[i].clone(), requires_grad=False)

    def _value(self, values: dict[int, Tensor], index: int) -> Tensor:
        if index in values:
            return values[index]
        if index in self._const:
            return self.weights[self._const[index]]
        raise ValueError(f"{self.graph.source}: tensor {self.graph.tensors[index].name!r} is used "
                         "before it is computed")

    def forward_reference(self, image: Tensor) -> tuple[Tensor, ...]:
        """The op-by-op replay, one operator at a time as the file lists them (what `forward`'s
        plan was checked against; kept for tests)."""
        g = self.graph
        values: dict[int, Tensor] = {}
        nchw: set[int] = set()  # tensors stored NCHW (4-D activations)
        # NHWC in memory (channels-last NCHW for torch): 1.2-1.4x faster convolutions than the NCHW
        # memory a crop from grid_sample has; the same values to float rounding (5e-5 px)
        x = image.contiguous().permute(0, 3, 1, 2)
        values[g.inputs[0]] = x
        nchw.add(g.inputs[0])

        def as_nhwc(i: int) -> Tensor:
            v = values[i]
            return v.permute(0, 2, 3, 1) if i in nchw else v

        for k, op in enumerate(g.operators):
            name, ins, out = op.name, op.inputs, op.outputs[0]
            if name in ("DEQUANTIZE", "DENSIFY"):
                if g.tensors[ins[0]].data is not None or ins[0] not in values:  # weights: done in __init__
                    continue
                if name == "DENSIFY":
                    raise ValueError(f"{g.source}: DENSIFY of a computed tensor is not supported")
                values[out] = values[ins[0]].float()
                if ins[0] in nchw:
                    nchw.add(out)
                continue
            if name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
                x = values[ins[0]]
                w_key, b_key = self._conv[k]
                w = self.weights[w_key]
                b = self.weights[b_key] if b_key else None
                o = op.options
                (sh, sw), (dh, dw) = o["stride"], o["dilation"]
                kh, kw = w.shape[2], w.shape[3]
                if o["padding"] == "SAME":
                    ph = _same_pad(x.shape[2], kh, sh, dh)
                    pw = _same_pad(x.shape[3], kw, sw, dw)
                    if any(ph + pw):
                        x = F.pad(x, (pw[0], pw[1], ph[0], ph[1]))
                groups = x.shape[1] if name == "DEPTHWISE_CONV_2D" else 1
                y = F.conv2d(x, w, b, stride=(sh, sw), dilation=(dh, dw), groups=groups)
                values[out] = _activate(y, o["activation"])
                nchw.add(out)
            elif name == "PRELU":
                x = values[ins[0]]
                alpha = self.weights[self._conv[k][0]]
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: PRELU on a non-image tensor is not supported")
                if alpha.numel() == x.shape[1]:  # one slope per channel: torch's fused kernel (6x faster)
                    values[out] = F.prelu(x, alpha.reshape(-1))
                else:
                    values[out] = torch.where(x >= 0, x, x * alpha)
                nchw.add(out)
            elif name == "RELU":
                values[out] = F.relu(values[ins[0]])
                if ins[0] in nchw:
                    nchw.add(out)
            elif name == "ADD":
                a, b = self._value(values, ins[0]), self._value(values, ins[1])
                if (ins[0] in nchw) != (ins[1] in nchw):
                    raise ValueError(f"{g.source}: ADD of an image and a non-image tensor is not supported")
                values[out] = _activate(a + b, op.options.get("activation", 0))
                if ins[0] in nchw:
                    nchw.add(out)
            elif name == "MAX_POOL_2D":
                x = values[ins[0]]
                o = op.options
                (sh, sw), (kh, kw) = o["stride"], o["filter"]
                if o["padding"] == "SAME":
                    ph = _same_pad(x.shape[2], kh, sh, 1)
                    pw = _same_pad(x.shape[3], kw, sw, 1)
                    if any(ph + pw):
                        x = F.pad(x, (pw[0], pw[1], ph[0], ph[1]), value=float("-inf"))
                values[out] = _activate(F.max_pool2d(x, (kh, kw), (sh, sw)), o["activation"])
                nchw.add(out)
            elif name == "PAD":
                pads = g.tensors[ins[1]].data
                if pads is None:
                    raise ValueError(f"{g.source}: PAD with computed paddings is not supported")
                pads = np.asarray(pads).reshape(-1, 2).tolist()
                if ins[0] in nchw:  # NHWC paddings -> F.pad order (W, H, C)
                    (_, _), (h0, h1), (w0, w1), (c0, c1) = pads
                    values[out] = F.pad(values[ins[0]], (w0, w1, h0, h1, c0, c1))
                    nchw.add(out)
                else:
                    flat = [p for pair in reversed(pads) for p in pair]
                    values[out] = F.pad(values[ins[0]], flat)
            elif name == "RESHAPE":
                x = as_nhwc(ins[0])
                shape = op.options.get("new_shape")
                if shape is None and len(ins) > 1:
                    shape = [int(v) for v in np.asarray(g.tensors[ins[1]].data).reshape(-1)]
                shape = [x.shape[0]] + list(shape[1:])  # batch follows the input
                values[out] = x.reshape(shape)
            elif name == "RESIZE_BILINEAR":
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: RESIZE_BILINEAR of a non-image tensor is not supported")
                size = g.tensors[ins[1]].data
                if size is None:
                    raise ValueError(f"{g.source}: RESIZE_BILINEAR with a computed size is not supported")
                values[out] = resize_bilinear_tf(values[ins[0]], tuple(int(v) for v in np.asarray(size).reshape(-1)),
                                                 op.options["align_corners"], op.options["half_pixel_centers"])
                nchw.add(out)
            elif name == "DEPTH_TO_SPACE":
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: DEPTH_TO_SPACE of a non-image tensor is not supported")
                values[out] = depth_to_space(values[ins[0]], op.options["block_size"])
                nchw.add(out)
            elif name == "CONCATENATION":
                axis = op.options["axis"]
                parts = [self._value(values, i) for i in ins]
                if all(i in nchw for i in ins):
                    axis = axis % 4
                    values[out] = _activate(torch.cat(parts, {0: 0, 1: 2, 2: 3, 3: 1}[axis]),
                                            op.options["activation"])
                    nchw.add(out)
                else:
                    parts = [as_nhwc(i) if i in values else self._value(values, i) for i in ins]
                    values[out] = _activate(torch.cat(parts, axis), op.options["activation"])
        return tuple(as_nhwc(i) for i in self.output_indices)

    # -- the plan: the replay resolved once per input size -------------------------------------
    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> "TfliteModule":  # .to() / .double() / .cuda()
        # the plans close over the weights: build them afresh for the moved ones
        self._plans = {}
        return super()._apply(fn, *args, **kwargs)

    def forward(self, image: Tensor) -> tuple[Tensor, ...]:
        """The replay (see the class docstring) by a plan resolved once per input size
        (`_build_plan`): each operator a closure over its weights, paddings and layouts, constants'
        DEQUANTIZE dropped, registers freed after their last use. Same values as
        `forward_reference` to float rounding (measured: at most 1e-6 of the output's scale).

        Each image of the batch is run alone, so its outputs do not depend on the batch it came
        in: a 1 x 1 convolution done as a matrix product over B x H x W rows blocks its sums by
        the row count (the face mesh's points of one crop moved by up to 4.6e-5 px between a
        batch of 8 and a batch of 1, and fit.Expression, a flat valley, turned that into 0.06 in
        its output between `batch` 8 and 3, so a frame's fit depended on its neighbours). Costs
        about 1 ms a crop of the face mesh on one thread."""
        if image.ndim != 4:
            raise ValueError(f"{self.graph.source}: image: expected shape (B, H, W, C), found {tuple(image.shape)}")
        if image.shape[0] > 1:
            rows = [self._forward_one(image[i:i + 1]) for i in range(image.shape[0])]
            return tuple(torch.cat(parts) for parts in zip(*rows))
        return self._forward_one(image)

    def _forward_one(self, image: Tensor) -> tuple[Tensor, ...]:
        """`forward` of a (1, H, W, C) image (any batch runs, but its sums depend on the batch)."""
        key = tuple(image.shape[1:])
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = self._build_plan(*key)
        steps, size, input_index, outputs = plan
        regs: list[Any] = [None] * size
        regs[input_index] = image.contiguous().permute(0, 3, 1, 2)
        for step in steps:
            step(regs)
        return tuple(out(regs) for out in outputs)

    def _build_plan(self, height: int, width: int, channels: int) -> tuple[list, int, int, list]:
        """Steps for an input of (height, width, channels): shapes propagated through the graph
        so every TF "SAME" padding is known; a symmetric one goes into the convolution, an
        asymmetric one stays an explicit pad; 1 x 1 convolutions (stride 1) and convolutions
        whose kernel covers their whole input are matrix products on the NHWC memory (torch
        sends a 1 x 1 convolution on one thread to its unblocked kernel, which first copies a
        channels-last input to NCHW)."""
        g = self.graph
        params = dict(self.weights.items())
        nchw: set[int] = {g.inputs[0]}
        hwc: dict[int, tuple[int, int, int]] = {g.inputs[0]: (height, width, channels)}  # image tensors' sizes
        last_use: dict[int, int] = {}
        for k, op in enumerate(g.operators):
            for i in op.inputs:
                last_use[i] = k
        keep = set(self.output_indices)
        computed = {g.inputs[0]}
        fresh: set[int] = set()
        viewed = {op.inputs[0] for op in g.operators if op.name in ("RESHAPE", "DEQUANTIZE", "DENSIFY")}
        steps: list = []

        def getter(i: int):
            if i in self._const:
                value = params[self._const[i]]
                return lambda r: value
            return lambda r: r[i]

        def nhwc_getter(i: int):
            if i in nchw:
                return lambda r: r[i].permute(0, 2, 3, 1)
            return getter(i)

        def activation(code: int):
            if code == 0:
                return None
            _activate(torch.zeros(1), code)  # unknown codes fail here, at plan time
            return lambda y: _activate(y, code)

        for k, op in enumerate(g.operators):
            name, ins, out = op.name, op.inputs, op.outputs[0]
            if name in ("DEQUANTIZE", "DENSIFY"):
                if g.tensors[ins[0]].data is not None or ins[0] not in computed:  # weights: done in __init__
                    continue
                if name == "DENSIFY":
                    raise ValueError(f"{g.source}: DENSIFY of a computed tensor is not supported")
                src = ins[0]
                steps.append(lambda r, src=src, out=out: r.__setitem__(out, r[src].float()))
                if src in nchw:
                    nchw.add(out)
                    hwc[out] = hwc[src]
            elif name in ("CONV_2D", "DEPTHWISE_CONV_2D"):
                h, w, c = hwc[ins[0]]
                w_key, b_key = self._conv[k]
                weight = params[w_key]
                bias = params[b_key] if b_key else None
                o = op.options
                (sh, sw), (dh, dw) = o["stride"], o["dilation"]
                cout, kh, kw = weight.shape[0], weight.shape[2], weight.shape[3]
                ph, pw = ((_same_pad(h, kh, sh, dh), _same_pad(w, kw, sw, dw)) if o["padding"] == "SAME"
                          else ((0, 0), (0, 0)))
                hp, wp = h + sum(ph), w + sum(pw)
                oh, ow = (hp - (kh - 1) * dh - 1) // sh + 1, (wp - (kw - 1) * dw - 1) // sw + 1
                act = activation(o["activation"])
                groups = c if name == "DEPTHWISE_CONV_2D" else 1
                src = ins[0]
                if groups == 1 and not any(ph + pw) and (dh, dw) == (1, 1) and (
                        (kh, kw, sh, sw) == (1, 1, 1, 1) or (kh, kw) == (h, w)):
                    # a matrix product on NHWC memory: (B H W, C) x (C, O), or the whole input (B, H W C) x (H W C, O)
                    whole = (kh, kw) != (1, 1)

                    def step(r, src=src, out=out, weight=weight, bias=bias, act=act, whole=whole, oh=oh, ow=ow,
                             cout=cout):
                        x = r[src].permute(0, 2, 3, 1)
                        flat = x.reshape(len(x), -1) if whole else x.reshape(-1, x.shape[3])
                        y = F.linear(flat, weight.permute(0, 2, 3, 1).reshape(cout, -1), bias)
                        y = y.reshape(len(x), oh, ow, cout).permute(0, 3, 1, 2)
                        r[out] = y if act is None else act(y)
                else:
                    symmetric = ph[0] == ph[1] and pw[0] == pw[1]
                    padding = (ph[0], pw[0]) if symmetric else (0, 0)
                    explicit = None if symmetric else (pw[0], pw[1], ph[0], ph[1])

                    def step(r, src=src, out=out, weight=weight, bias=bias, act=act, padding=padding,
                             explicit=explicit, stride=(sh, sw), dilation=(dh, dw), groups=groups):
                        x = r[src]
                        if explicit is not None:
                            x = F.pad(x, explicit)
                        y = F.conv2d(x, weight, bias, stride, padding, dilation, groups)
                        r[out] = y if act is None else act(y)
                steps.append(step)
                nchw.add(out)
                hwc[out] = (oh, ow, cout)
            elif name == "PRELU":
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: PRELU on a non-image tensor is not supported")
                alpha = params[self._conv[k][0]]
                src = ins[0]
                if alpha.numel() == hwc[src][2]:  # one slope per channel: torch's fused kernel
                    steps.append(lambda r, src=src, out=out, alpha=alpha:
                                 r.__setitem__(out, F.prelu(r[src], alpha.reshape(-1))))
                else:
                    steps.append(lambda r, src=src, out=out, alpha=alpha:
                                 r.__setitem__(out, torch.where(r[src] >= 0, r[src], r[src] * alpha)))
                nchw.add(out)
                hwc[out] = hwc[src]
            elif name == "RELU":
                src = ins[0]
                steps.append(lambda r, src=src, out=out: r.__setitem__(out, F.relu(r[src])))
                if src in nchw:
                    nchw.add(out)
                    hwc[out] = hwc[src]
            elif name == "ADD":
                if (ins[0] in nchw) != (ins[1] in nchw):
                    raise ValueError(f"{g.source}: ADD of an image and a non-image tensor is not supported")
                a, b = getter(ins[0]), getter(ins[1])
                code = op.options.get("activation", 0)
                act = activation(code)
                if ins[0] in nchw:
                    nchw.add(out)
                    ha, wa, ca = hwc[ins[0]]
                    hb, wb, cb = hwc[ins[1]]
                    hwc[out] = (max(ha, hb), max(wa, wb), max(ca, cb))
                # without autograd, the sum goes into an operand that dies here (a tensor a step of
                # this plan made, of the output's size): no new tensor
                into = [i for i in ins if i in fresh and last_use.get(i) == k and i not in keep and i not in viewed
                        and hwc.get(i) == hwc.get(out)]
                if into and code in (0, 1):
                    target, other = into[0], getter(ins[1] if into[0] == ins[0] else ins[0])

                    def step(r, a=a, b=b, out=out, act=act, target=target, other=other, relu=code == 1):
                        if torch.is_grad_enabled():
                            y = a(r) + b(r)
                            r[out] = y if act is None else act(y)
                            return
                        y = r[target].add_(other(r))
                        r[out] = y.relu_() if relu else y
                else:
                    def step(r, a=a, b=b, out=out, act=act):
                        y = a(r) + b(r)
                        r[out] = y if act is None else act(y)
                steps.append(step)
            elif name == "MAX_POOL_2D":
                h, w, c = hwc[ins[0]]
                o = op.options
                (sh, sw), (kh, kw) = o["stride"], o["filter"]
                ph, pw = ((_same_pad(h, kh, sh, 1), _same_pad(w, kw, sw, 1)) if o["padding"] == "SAME"
                          else ((0, 0), (0, 0)))
                explicit = (pw[0], pw[1], ph[0], ph[1]) if any(ph + pw) else None
                act = activation(o["activation"])

                def step(r, src=ins[0], out=out, explicit=explicit, kernel=(kh, kw), stride=(sh, sw), act=act):
                    x = r[src]
                    if explicit is not None:
                        x = F.pad(x, explicit, value=float("-inf"))
                    y = F.max_pool2d(x, kernel, stride)
                    r[out] = y if act is None else act(y)
                steps.append(step)
                nchw.add(out)
                hwc[out] = ((h + sum(ph) - kh) // sh + 1, (w + sum(pw) - kw) // sw + 1, c)
            elif name == "PAD":
                pads = g.tensors[ins[1]].data
                if pads is None:
                    raise ValueError(f"{g.source}: PAD with computed paddings is not supported")
                pads = np.asarray(pads).reshape(-1, 2).tolist()
                src = ins[0]
                if src in nchw:  # NHWC paddings -> F.pad order (W, H, C)
                    (_, _), (h0, h1), (w0, w1), (c0, c1) = pads
                    order = (w0, w1, h0, h1, c0, c1)
                    h, w, c = hwc[src]
                    nchw.add(out)
                    hwc[out] = (h + h0 + h1, w + w0 + w1, c + c0 + c1)
                else:
                    order = tuple(p for pair in reversed(pads) for p in pair)
                steps.append(lambda r, src=src, out=out, order=order: r.__setitem__(out, F.pad(r[src], order)))
            elif name == "RESHAPE":
                shape = op.options.get("new_shape")
                if shape is None and len(ins) > 1:
                    shape = [int(v) for v in np.asarray(g.tensors[ins[1]].data).reshape(-1)]
                rest = list(shape[1:])
                x_of = nhwc_getter(ins[0])
                steps.append(lambda r, x_of=x_of, out=out, rest=rest:
                             r.__setitem__(out, (lambda x: x.reshape([x.shape[0]] + rest))(x_of(r))))
            elif name == "RESIZE_BILINEAR":
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: RESIZE_BILINEAR of a non-image tensor is not supported")
                size = g.tensors[ins[1]].data
                if size is None:
                    raise ValueError(f"{g.source}: RESIZE_BILINEAR with a computed size is not supported")
                size = tuple(int(v) for v in np.asarray(size).reshape(-1))
                corners, half = op.options["align_corners"], op.options["half_pixel_centers"]
                steps.append(lambda r, src=ins[0], out=out, size=size, corners=corners, half=half:
                             r.__setitem__(out, resize_bilinear_tf(r[src], size, corners, half)))
                nchw.add(out)
                hwc[out] = (size[0], size[1], hwc[ins[0]][2])
            elif name == "DEPTH_TO_SPACE":
                if ins[0] not in nchw:
                    raise ValueError(f"{g.source}: DEPTH_TO_SPACE of a non-image tensor is not supported")
                block = op.options["block_size"]
                steps.append(lambda r, src=ins[0], out=out, block=block:
                             r.__setitem__(out, depth_to_space(r[src], block)))
                nchw.add(out)
                h, w, c = hwc[ins[0]]
                hwc[out] = (h * block, w * block, c // (block * block))
            elif name == "CONCATENATION":
                axis = op.options["axis"]
                act = activation(op.options["activation"])
                if all(i in nchw for i in ins):
                    axis = {0: 0, 1: 2, 2: 3, 3: 1}[axis % 4]
                    parts = [getter(i) for i in ins]
                    nchw.add(out)
                    sizes = [hwc[i] for i in ins]
                    h, w, c = sizes[0]
                    hwc[out] = {1: (h, w, sum(v[2] for v in sizes)), 2: (sum(v[0] for v in sizes), w, c),
                                3: (h, sum(v[1] for v in sizes), c)}.get(axis, (h, w, c))
                else:
                    parts = [nhwc_getter(i) for i in ins]

                def step(r, parts=parts, axis=axis, out=out, act=act):
                    y = torch.cat([p(r) for p in parts], axis)
                    r[out] = y if act is None else act(y)
                steps.append(step)
            else:  # pragma: no cover - __init__ refused it
                raise ValueError(f"{g.source}: unsupported TFLite operator {name}")
            computed.update(op.outputs)
            if name in ("CONV_2D", "DEPTHWISE_CONV_2D", "PRELU", "ADD", "MAX_POOL_2D", "PAD") and out in nchw:
                fresh.add(out)  # a tensor of its own (no view of another register)
            dead = [i for i in ins if last_use.get(i) == k and i not in keep and i not in self._const]
            if dead:
                steps.append(lambda r, dead=dead: [r.__setitem__(i, None) for i in dead])
        outputs = [nhwc_getter(i) for i in self.output_indices]
        return steps, len(g.tensors), g.inputs[0], outputs
