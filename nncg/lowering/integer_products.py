"""Lowering of ConvInteger and MatMulInteger: the integer convolution and matrix product of
quantized.py, each int32 sum stored as it is (a graph output), or dequantised in the store (where
frontend/qdq.py fused the Cast to float32, Mul and Add that read it) as float32(sum) * scale[c]
(+ bias[c]). Each step is rounded to float32 as onnxruntime's Cast, Mul and Add round it: the
product of two float32 values is exact in double, so computing it there and rounding once gives
the float32 product; the sum likewise, unless its terms are more than 2^29 apart (then the double
rounding could differ in the last bit at a tie). Where a sum can exceed 2^24 in magnitude (so
float32(sum) rounds), a C compiler contracting float expressions (GCC in its default GNU mode with
-mfma) may fuse the product and the addition: the result can then differ from onnxruntime's in the
last bit; strict C89 does not. Vectors compute the steps as float32 operations, each rounded once
(passes/dequantized_vectors.py)."""

from __future__ import annotations

import numpy as np

from ..ir.graph import Node
from ..ir.kinds import DType
from ..ir.loops import Affine, Binary, Cast, Const, Expr, Load
from .context import LoweringContext
from .quantized import Finish, integer_conv, integer_dense

FLOAT64, FLOAT32 = DType.FLOAT64, DType.FLOAT32


def _in_float32(a: Expr, op: str, b: Expr) -> Expr:
    """float32(a op b) for a float32 or int32 a and a float32 b, computed in double."""
    return Cast(FLOAT32, Binary(op, Cast(FLOAT64, a), Cast(FLOAT64, b)))


def _per_channel(ctx: LoweringContext, name: str, values: np.ndarray):
    """A literal when every channel has one value, else a constant array read by the channel."""
    values = np.asarray(values, np.float32).reshape(-1)
    if np.all(values == values[0]):
        literal = Const.splat(float(values[0]))
        return lambda _channel: literal
    ref = ctx.add_constant(name, values)
    return lambda channel: Load(ref.buffer, ref.at([channel]))


def _sums_are_float32(ctx: LoweringContext, node: Node) -> bool:
    """Whether every int32 sum the node can compute is a float32 value (magnitude at most 2^24)."""
    weights = np.abs(ctx.graph.constants[node.inputs[1]].astype(np.int64))
    per_channel = weights.reshape(weights.shape[0], -1).sum(axis=1) if node.op == "ConvInteger" else weights.sum(axis=0)
    low, high = ctx.graph.dtype(node.inputs[0]).range
    zero_point = node.attrs.x_zero_point
    return int(per_channel.max()) * max(zero_point - low, high - zero_point) <= 2**24


def finished(ctx: LoweringContext, node: Node) -> Finish:
    """The int32 sum as it is, or dequantised (see dequantized)."""
    return dequantized(ctx, node) if node.attrs.dequantized else lambda acc, _channel: acc


def dequantized(ctx: LoweringContext, node: Node) -> Finish:
    """float32(sum) * scale[c] (+ bias[c]): inputs 3 and 4 of the node."""
    scale = _per_channel(ctx, f"s_{node.name}", ctx.graph.constants[node.inputs[3]])
    bias = _per_channel(ctx, f"fb_{node.name}", ctx.graph.constants[node.inputs[4]]) if node.attrs.biased else None
    # The int32 sum where it is its float32 value, so that the product has no float32 operand: C
    # compilers narrow a double product of two floats to a float one, and may then contract it with
    # the bias' addition into a fused multiply-add, which onnxruntime's Mul and Add do not do.
    exact = _sums_are_float32(ctx, node)

    def finish(acc: Expr, channel: Affine) -> Expr:
        product = _in_float32(acc if exact else Cast(FLOAT32, acc), "*", scale(channel))
        return _in_float32(product, "+", bias(channel)) if bias is not None else product

    return finish


def lower_conv_integer(ctx: LoweringContext, node: Node) -> None:
    integer_conv(ctx, node, finished(ctx, node))


def lower_matmul_integer(ctx: LoweringContext, node: Node) -> None:
    integer_dense(ctx, node, finished(ctx, node))
