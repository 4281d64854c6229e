"""ONNX front end, step 3: the quantized ops (QOperator format, and QDQ groups that qdq.py rewrote
into it) become integer graph IR nodes. Activations are quantized per tensor (int8 or uint8), weights
per tensor or per output channel; the scales are folded into one float32 multiplier per output
channel, computed as onnxruntime computes it (x_scale * w_scale / y_scale, in float32)."""

from __future__ import annotations

import math

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_nn import conv_geometry
from nncg.frontend.windows import checked_pool_output_shape, pool_attrs
from nncg.ir.graph import (
    Node,
    QAveragePoolAttrs,
    QConvAttrs,
    QDenseAttrs,
    QPoolAttrs,
    QuantAttrs,
    Requantization,
    ReshapeAttrs,
)
from nncg.ir.kinds import DType
from nncg.safe_text import shown

F32 = np.float32
QUANTIZATION_HINT = "NNCG specialises the code to the scales and zero points: make them constants"
# ONNX's TensorProto element types of QuantizeLinear's output_dtype attribute (opset 21)
OUTPUT_DTYPES = {2: DType.UINT8, 3: DType.INT8}


def quantization(op: OnnxOp, ctx: Context, scale_slot: int, role: str) -> tuple[float, int, DType]:
    """(scale, zero point, dtype) of a per-tensor quantized value: the scale at `scale_slot`, the
    zero point after it (omitted: 0, uint8 unless output_dtype says otherwise)."""
    scale = ctx.constant_input(op, scale_slot, f"{role} scale", QUANTIZATION_HINT)
    zero = (
        ctx.constant_input(op, scale_slot + 1, f"{role} zero point", QUANTIZATION_HINT)
        if op.input(scale_slot + 1)
        else None
    )
    if scale.size != 1 or (zero is not None and zero.size != 1):
        raise op.error(f"quantizes its {role} per axis; NNCG quantizes activations per tensor only")
    if zero is None:
        dtype = OUTPUT_DTYPES.get(int(op.attr("output_dtype", 2)))
    else:
        dtype = DType(zero.dtype.name) if zero.dtype.name in ("int8", "uint8") else None
    if dtype is None:
        raise op.error(
            f"quantizes its {role} to {zero.dtype.name if zero is not None else 'that type'}; NNCG takes int8 and uint8"
        )
    value = F32(scale.reshape(()))
    if not (np.isfinite(value) and value > 0):
        raise op.error(f"has {role} scale {float(value)!r}; a scale is positive and finite")
    return float(value), 0 if zero is None else int(zero.reshape(())), dtype


def quantize(value: float, scale: float, zero_point: int, dtype: DType) -> int:
    """QuantizeLinear of one real value: value / scale in float32, rounded half to even, saturated."""
    low, high = dtype.range
    with np.errstate(over="ignore"):
        q = np.rint(F32(value) / F32(scale))
    return int(np.clip(q + zero_point, low, high)) if np.isfinite(q) else (low if q < 0 else high)


def requantization(op: OnnxOp, ctx: Context, scale: float, zero_point: int, dtype: DType) -> Requantization:
    """The output range: the type's, narrowed by a Relu or Clip that qdq.py folded into the op (its
    real bounds, noted in ctx.output_ranges, quantized as QuantizeLinear would)."""
    low, high = dtype.range
    real_low, real_high = ctx.output_ranges.get(op.node.output[0], (-np.inf, np.inf))
    if real_low > -np.inf:
        low = max(low, quantize(real_low, scale, zero_point, dtype))
    if real_high < np.inf:
        high = min(high, quantize(real_high, scale, zero_point, dtype))
    return Requantization(zero_point, low, min(max(low, high), dtype.range[1]), dtype)


def convert_quantize_linear(op: OnnxOp, ctx: Context) -> Node:
    scale, zero, dtype = quantization(op, ctx, 1, "output")
    ctx.set_shape(op, op.node.output[0], ctx.shape(op.input(0)))  # after a contrib op, ONNX infers none
    return op.ir_node("QuantizeLinear", [op.input(0)], QuantAttrs(scale, zero, dtype))


def convert_dequantize_linear(op: OnnxOp, ctx: Context) -> Node:
    scale, zero, dtype = quantization(op, ctx, 1, "input")
    ctx.set_shape(op, op.node.output[0], ctx.shape(op.input(0)))  # after a contrib op, ONNX infers none
    return op.ir_node("DequantizeLinear", [op.input(0)], QuantAttrs(scale, zero, dtype))


def integer_weights(op: OnnxOp, ctx: Context, slot: int, channels: int, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """The weights (constant, int8 or uint8; minus their zero points, as int16, unless those are
    all 0) and their scales, one per output channel along `axis`."""
    w = centred_weights(op, ctx, slot, slot + 2, channels, axis)
    scale = ctx.constant_input(op, slot + 1, "weight scale", QUANTIZATION_HINT)
    if scale.size not in (1, channels):
        raise op.error(f"has {scale.size} weight scales for {channels} output channels; give one or one per channel")
    return w, np.broadcast_to(scale.astype(F32).reshape(-1), (channels,))


def centred_weights(op: OnnxOp, ctx: Context, slot: int, zero_slot: int, channels: int, axis: int) -> np.ndarray:
    """The constant int8 or uint8 weights at `slot` minus their zero points (at `zero_slot`, one or
    one per output channel along `axis`), as int16; as they are where they are int8 and those all 0."""
    w = ctx.const(op.input(slot))
    if w is None:
        raise op.error("has its weights computed at run time; NNCG's integer kernels take constant weights")
    zero = ctx.constant_input(op, zero_slot, "weight zero point", QUANTIZATION_HINT) if op.input(zero_slot) else None
    if w.dtype not in (np.int8, np.uint8):
        raise op.error(f"has weights of type {w.dtype.name}; NNCG takes int8 and uint8")
    if zero is not None and zero.size not in (1, channels):
        raise op.error(f"has {zero.size} weight zero points for {channels} output channels; give one or one each")
    shape = [1] * w.ndim
    shape[axis] = -1
    zero = np.zeros(1, np.int16) if zero is None else zero.astype(np.int16).reshape(-1)
    if w.dtype == np.int8 and not zero.any():
        return w
    return (w.astype(np.int16) - np.broadcast_to(zero, (channels,)).reshape(shape)).astype(np.int16)


def multipliers(x_scale: float, w_scales: np.ndarray, y_scale: float) -> np.ndarray:
    """x_scale * w_scale / y_scale per channel, in float32 as onnxruntime rounds it."""
    return ((F32(x_scale) * w_scales.astype(F32)) / F32(y_scale)).astype(F32)


def int32_bias(op: OnnxOp, ctx: Context, slot: int, channels: int) -> np.ndarray:
    name = op.input(slot)
    if not name:
        return np.zeros(channels, np.int32)
    bias = ctx.const(name)
    if bias is None or bias.dtype != np.int32 or bias.size != channels:
        raise op.error(f"has bias {shown(name)}, which is not a constant int32 vector of {channels} values")
    return bias.reshape(-1)


def convert_qlinear_conv(op: OnnxOp, ctx: Context) -> Node:
    """QLinearConv: x, x_scale, x_zero_point, w, w_scale, w_zero_point, y_scale, y_zero_point, B."""
    x = op.input(0)
    x_scale, x_zero, _ = quantization(op, ctx, 1, "input")
    y_scale, y_zero, y_dtype = quantization(op, ctx, 6, "output")
    w_shape = ctx.shape(op.input(3))
    geometry = conv_geometry(op, ctx.shape(x), w_shape)
    w, w_scales = integer_weights(op, ctx, 3, w_shape[0], 0)
    attrs = QConvAttrs.of(geometry, x_zero, requantization(op, ctx, y_scale, y_zero, y_dtype))
    return op.ir_node(
        "QLinearConv",
        [x, *_parameters(op, ctx, w, int32_bias(op, ctx, 8, w_shape[0]), x_scale, w_scales, y_scale)],
        attrs,
    )


def _parameters(op, ctx: Context, w: np.ndarray, bias: np.ndarray, x_scale, w_scales, y_scale) -> list[str]:
    """The constant inputs of a QLinearConv or QLinearDense: weights, int32 bias, multipliers."""
    base = op.node.output[0]
    return [
        ctx.add_constant(f"{base}_w", w),
        ctx.add_constant(f"{base}_b", bias),
        ctx.add_constant(f"{base}_m", multipliers(x_scale, w_scales, y_scale)),
    ]


def _dense(
    op: OnnxOp, ctx: Context, w_slot: int, trans_w: bool, bias_slot: int | None, y_slot: int
) -> tuple[Node, ...]:
    """QLinearMatMul or QGemm of x [..., K] (NumPy's matmul: the rows of all batches together,
    matrix_rows) and constant weights [..., K, N] or [K] (matrix_weights; [N, K] with trans_w)."""
    x = op.input(0)
    x_scale, x_zero, _ = quantization(op, ctx, 1, "input")
    y_scale, y_zero, y_dtype = quantization(op, ctx, y_slot, "output")
    w_shape = ctx.shape(op.input(w_slot))
    if trans_w:
        if len(w_shape) != 2:
            raise op.error(f"has {len(w_shape)}-D weights; NNCG's integer matrix product takes 2-D weights")
        channels, axis = w_shape[0], 0
    else:
        _, channels, axis = matrix_weights(op, w_shape)
    w, w_scales = integer_weights(op, ctx, w_slot, channels, axis)
    w = np.ascontiguousarray(w.T) if trans_w else w.reshape(-1, channels)
    if ctx.shape(x)[-1] != w.shape[0]:
        raise op.error(f"multiplies shapes {list(ctx.shape(x))} and {list(w_shape)}, whose inner dims differ")
    bias = int32_bias(op, ctx, bias_slot, channels) if bias_slot is not None else np.zeros(channels, np.int32)
    ctx.set_shape(op, op.node.output[0], product_shape(ctx.shape(x), w.shape if trans_w else w_shape))
    attrs = QDenseAttrs(x_zero, requantization(op, ctx, y_scale, y_zero, y_dtype))
    steps, rows = matrix_rows(op, ctx, x)
    parameters = _parameters(op, ctx, w, bias, x_scale, w_scales, y_scale)
    return (*steps, op.ir_node("QLinearDense", [rows, *parameters], attrs))


def matrix_weights(op: OnnxOp, w_shape: tuple[int, ...]) -> tuple[int, int, int]:
    """K, N and the column axis of constant weights [..., K, N] (leading dims of 1: NumPy's matmul
    broadcasts one matrix over x's batches) or [K] (one column)."""
    if any(n != 1 for n in w_shape[:-2]):
        raise op.error(
            f"multiplies by weights of shape {list(w_shape)}; NNCG's integer matrix product takes one [K, N] matrix"
        )
    if len(w_shape) == 1:
        return w_shape[0], 1, 0
    return w_shape[-2], w_shape[-1], len(w_shape) - 1


def matrix_rows(op: OnnxOp, ctx: Context, x: str) -> tuple[tuple[Node, ...], str]:
    """x [..., K] as the matrix [rows, K] an integer matrix product reads: x where it is one, else a
    Reshape (a view) of all its leading dims (none for a 1-D x) into the rows; the product node writes
    the rows in its result's shape."""
    shape = ctx.shape(x)
    if len(shape) == 2:
        return (), x
    rows_shape = (math.prod(shape[:-1]), shape[-1])
    rows = ctx.intermediate(op, "rows", rows_shape)
    return (op.ir_step("Reshape", "rows", [x], rows, ReshapeAttrs(rows_shape)),), rows


def product_shape(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    """The shape of NumPy's matmul of a and b: a 1-D operand gains a dim of 1 to multiply, which the
    product loses."""
    batch = np.broadcast_shapes(a[:-2], b[:-2])
    return (*(int(d) for d in batch), *a[-2:-1], *(b[-1:] if len(b) > 1 else ()))


def convert_qlinear_matmul(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    """QLinearMatMul: a, a_scale, a_zero_point, b, b_scale, b_zero_point, y_scale, y_zero_point."""
    return _dense(op, ctx, 3, False, None, 6)


def convert_qgemm(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    """onnxruntime's QGemm: A, a_scale, a_zero_point, B, b_scale, b_zero_point, C, y_scale,
    y_zero_point; transA 0 and alpha 1 (what qdq.py writes)."""
    if op.attr("transA", 0) or op.attr("alpha", 1.0) != 1.0 or not op.input(7):
        raise op.error(
            "has transA, alpha other than 1 or a float output; NNCG takes QGemm with transA=0, alpha=1, y_scale"
        )
    return _dense(op, ctx, 3, bool(op.attr("transB", 0)), 6, 7)


def convert_qlinear_average_pool(op: OnnxOp, ctx: Context) -> Node:
    """onnxruntime's QLinearAveragePool: X, x_scale, x_zero_point, y_scale, y_zero_point."""
    if op.attr("channels_last", 0):
        raise op.error("has channels_last=1; NNCG takes NCHW inputs")
    x = op.input(0)
    shape = ctx.shape(x)
    pool = pool_attrs(op, shape)
    if set(pool.dilations) != {1}:
        raise op.error("has dilations; onnxruntime's QLinearAveragePool has none")
    if pool.kernel == shape[2:] and not any(pool.pads_begin + pool.pads_end):
        return convert_qlinear_global_average_pool(op, ctx)  # onnxruntime falls back to it too
    x_scale, x_zero, _ = quantization(op, ctx, 1, "input")
    y_scale, y_zero, y_dtype = quantization(op, ctx, 3, "output")
    ctx.set_shape(op, op.node.output[0], checked_pool_output_shape(op, pool, shape))
    out = requantization(op, ctx, y_scale, y_zero, y_dtype)
    offset = 128 if op.node.output[0] in ctx.uint8_pools else 0
    attrs = QAveragePoolAttrs(pool, x_scale, x_zero, y_scale, out, offset)
    return op.ir_node("QLinearAveragePool", [x], attrs)


def convert_qlinear_global_average_pool(op: OnnxOp, ctx: Context) -> Node:
    """onnxruntime's QLinearGlobalAveragePool: X, x_scale, x_zero_point, y_scale, y_zero_point."""
    if op.attr("channels_last", 0):
        raise op.error("has channels_last=1; NNCG takes NCHW inputs")
    x = op.input(0)
    x_scale, x_zero, _ = quantization(op, ctx, 1, "input")
    y_scale, y_zero, y_dtype = quantization(op, ctx, 3, "output")
    shape = ctx.shape(x)
    ctx.set_shape(op, op.node.output[0], (*shape[:2], *[1] * (len(shape) - 2)))
    attrs = QPoolAttrs(x_scale, x_zero, y_scale, requantization(op, ctx, y_scale, y_zero, y_dtype))
    return op.ir_node("QLinearGlobalAveragePool", [x], attrs)
