"""ONNX front end: ConvInteger and MatMulInteger. Where a Cast to float32 reads the int32 result,
maybe then a Mul by a constant and an Add of one, qdq.py rewrites them into one node (domain nncg,
inputs x, w, x_zero_point, w_zero_point, the Mul's constant or "", the Add's or ""), computed with
the integer kernels and dequantised in their store (lowering/integer_products.py); otherwise the
int32 result is written as it is, which NNCG does only for a graph output (the importer refuses a
node reading it: INT32_RESULT, since no int32 tensor lives in the arena)."""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_nn import conv_geometry
from nncg.frontend.ops_quantized import QUANTIZATION_HINT, centred_weights, matrix_rows, matrix_weights, product_shape
from nncg.frontend.qdq import NNCG_DOMAIN
from nncg.ir.graph import IntegerConvAttrs, IntegerDenseAttrs, Node

# Why the importer refuses a ConvInteger or MatMulInteger whose int32 result a node reads.
INT32_RESULT = (
    "writes an int32 tensor that a node reads, which NNCG does not compile: its int32 result must be a graph "
    "output, or read only by a Cast to float32, that only by a Mul by a constant (and that by an Add of a "
    "constant, or by nothing else)"
)


def _x_zero_point(op: OnnxOp, ctx: Context) -> int:
    if not op.input(2):
        return 0
    zero = ctx.constant_input(op, 2, "input zero point", QUANTIZATION_HINT)
    if zero.size != 1 or zero.dtype not in (np.int8, np.uint8):
        raise op.error(
            "has an input zero point that is not one int8 or uint8 value; NNCG quantizes activations per tensor"
        )
    return int(zero.reshape(()))


def _dequantized(op: OnnxOp) -> bool:
    """Whether qdq.py fused the Cast to float32 (and Mul, Add) that read the int32 result."""
    return op.node.domain == NNCG_DOMAIN


def _per_channel(op: OnnxOp, ctx: Context, slot: int, channels: int, rank: int, axis: int, role: str) -> np.ndarray:
    """The float32 constant at `slot`, NumPy-broadcast over the result (rank `rank`, channels on
    `axis`): one value, or one per channel."""
    value = ctx.const(op.input(slot))
    shape = (1,) * (rank - value.ndim) + value.shape
    if value.ndim > rank or any(n != 1 for a, n in enumerate(shape) if a != axis) or shape[axis] not in (1, channels):
        raise op.error(
            f"is dequantised by a {role} of shape {list(value.shape)}; NNCG takes one value or one per output channel"
        )
    return np.ascontiguousarray(np.broadcast_to(value.reshape(-1), (channels,)), np.float32)


def _constants(op: OnnxOp, ctx: Context, w: np.ndarray, channels: int, rank: int, axis: int) -> list[str]:
    """The weights, a zero int32 bias (the kernels fold the input zero point into it) and, where the
    result is dequantised, the scale and the bias (if the Add was fused)."""
    base = op.node.output[0]
    names = [ctx.add_constant(f"{base}_w", w), ctx.add_constant(f"{base}_b", np.zeros(channels, np.int32))]
    if not _dequantized(op):
        return names
    if len(ctx.shape(base)) != rank:
        raise op.error("is dequantised by a constant of a higher rank than its result, which NNCG does not take")
    # a lone Cast is a scale of 1: float32(sum) * 1 is float32(sum), in one rounding as the Cast's
    scale = _per_channel(op, ctx, 4, channels, rank, axis, "scale") if op.input(4) else np.ones(channels, np.float32)
    names.append(ctx.add_constant(f"{base}_scale", scale))
    if op.input(5):
        names.append(ctx.add_constant(f"{base}_bias", _per_channel(op, ctx, 5, channels, rank, axis, "bias")))
    return names


def convert_conv_integer(op: OnnxOp, ctx: Context) -> Node:
    """ConvInteger: x, w, x_zero_point, w_zero_point (then qdq.py's scale and bias)."""
    x = op.input(0)
    w_shape = ctx.shape(op.input(1))
    geometry = conv_geometry(op, ctx.shape(x), w_shape)
    x_zero = _x_zero_point(op, ctx)
    w = centred_weights(op, ctx, 1, 3, w_shape[0], 0)
    attrs = IntegerConvAttrs.of(geometry, x_zero, bool(op.input(5)), _dequantized(op))
    return op.ir_node("ConvInteger", [x, *_constants(op, ctx, w, w_shape[0], len(ctx.shape(x)), 1)], attrs)


def convert_matmul_integer(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    """MatMulInteger: A [..., M, K] or [K], B [K, N] or [K] (constant; batch dims of 1 only),
    a_zero_point, b_zero_point (per tensor or per column), then qdq.py's scale and bias. NumPy's
    matmul: A's rows, all batches together (matrix_rows), times B."""
    x = op.input(0)
    x_shape, w_shape = ctx.shape(x), ctx.shape(op.input(1))
    k, n, axis = matrix_weights(op, w_shape)
    if x_shape[-1] != k:
        raise op.error(f"multiplies shapes {list(x_shape)} and {list(w_shape)}, whose inner dims differ")
    shape = product_shape(x_shape, w_shape)
    w = centred_weights(op, ctx, 1, 3, n, axis).reshape(k, n)
    attrs = IntegerDenseAttrs(_x_zero_point(op, ctx), bool(op.input(5)), _dequantized(op))
    constants = _constants(op, ctx, w, n, len(shape), len(shape) - 1)
    steps, rows = matrix_rows(op, ctx, x)
    return (*steps, op.ir_node("MatMulInteger", [rows, *constants], attrs))
