"""ONNX front end: ConvInteger and MatMulInteger whose int32 result a Cast to float32 and a Mul by a
constant (and possibly an Add of one) dequantise: qdq.py rewrites the four into one node (domain
nncg, inputs x, w, x_zero_point, w_zero_point, the Mul's constant, the Add's or ""), computed with
the integer kernels and dequantised in their store (lowering/integer_products.py). The importer
refuses any other ConvInteger or MatMulInteger (INT32_RESULT): NNCG writes no int32 tensors."""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_nn import conv_geometry
from nncg.frontend.ops_quantized import QUANTIZATION_HINT, centred_weights
from nncg.ir.graph import IntegerConvAttrs, IntegerDenseAttrs, Node

# Why the importer refuses any other ConvInteger or MatMulInteger.
INT32_RESULT = (
    "writes an int32 tensor, which NNCG does not compile: its result must be read only by a Cast to float32, "
    "that only by a Mul by a constant (and that by an Add of a constant, or by nothing else)"
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


def _per_channel(op: OnnxOp, ctx: Context, slot: int, channels: int, rank: int, role: str) -> np.ndarray:
    """The float32 constant at `slot`, NumPy-broadcast over the result (rank `rank`, channels on
    axis 1): one value, or one per channel."""
    value = ctx.const(op.input(slot))
    shape = (1,) * (rank - value.ndim) + value.shape
    if value.ndim > rank or any(n != 1 for axis, n in enumerate(shape) if axis != 1) or shape[1] not in (1, channels):
        raise op.error(
            f"is dequantised by a {role} of shape {list(value.shape)}; NNCG takes one value or one per output channel"
        )
    return np.ascontiguousarray(np.broadcast_to(value.reshape(-1), (channels,)), np.float32)


def _constants(op: OnnxOp, ctx: Context, w: np.ndarray, channels: int, rank: int) -> list[str]:
    """The weights, a zero int32 bias (the kernels fold the input zero point into it), the scale and
    the bias (if the Add was fused)."""
    if len(ctx.shape(op.node.output[0])) != rank:
        raise op.error("is dequantised by a constant of a higher rank than its result, which NNCG does not take")
    base = op.node.output[0]
    names = [
        ctx.add_constant(f"{base}_w", w),
        ctx.add_constant(f"{base}_b", np.zeros(channels, np.int32)),
        ctx.add_constant(f"{base}_scale", _per_channel(op, ctx, 4, channels, rank, "scale")),
    ]
    if op.input(5):
        names.append(ctx.add_constant(f"{base}_bias", _per_channel(op, ctx, 5, channels, rank, "bias")))
    return names


def convert_conv_integer(op: OnnxOp, ctx: Context) -> Node:
    """ConvInteger: x, w, x_zero_point, w_zero_point (then qdq.py's scale and bias)."""
    x = op.input(0)
    w_shape = ctx.shape(op.input(1))
    geometry = conv_geometry(op, ctx.shape(x), w_shape)
    x_zero = _x_zero_point(op, ctx)
    w = centred_weights(op, ctx, 1, 3, w_shape[0], 0)
    attrs = IntegerConvAttrs.of(geometry, x_zero, bool(op.input(5)))
    return op.ir_node("ConvInteger", [x, *_constants(op, ctx, w, w_shape[0], len(ctx.shape(x)))], attrs)


def convert_matmul_integer(op: OnnxOp, ctx: Context) -> Node:
    """MatMulInteger: A [M, K], B [K, N] (constant), a_zero_point, b_zero_point (per tensor or per
    column), then qdq.py's scale and bias."""
    x = op.input(0)
    x_shape, w_shape = ctx.shape(x), ctx.shape(op.input(1))
    if len(x_shape) != 2 or len(w_shape) != 2:
        raise op.error("multiplies inputs that are not both 2-D; NNCG's integer matrix product takes 2-D inputs")
    x_zero = _x_zero_point(op, ctx)
    w = centred_weights(op, ctx, 1, 3, w_shape[1], 1)
    attrs = IntegerDenseAttrs(x_zero, bool(op.input(5)))
    return op.ir_node("MatMulInteger", [x, *_constants(op, ctx, w, w_shape[1], 2)], attrs)
