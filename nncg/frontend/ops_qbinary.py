"""ONNX front end: onnxruntime's QLinearAdd and QLinearMul (com.microsoft), and the QDQ Add and Mul
that qdq.py rewrites into them: two int8/uint8 tensors (or one and a constant), NumPy-broadcast as
onnxruntime broadcasts them, computed as its kernels do (lowering/quantized_add.py,
lowering/quantized_mul.py)."""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_quantized import quantization, requantization
from nncg.ir.graph import Node, QBinaryAttrs


def _convert_qlinear_binary(op: OnnxOp, ctx: Context, verb: str) -> Node:
    """A, A_scale, A_zero_point, B, B_scale, B_zero_point, C_scale, C_zero_point."""
    a, b = op.input(0), op.input(3)
    a_scale, a_zero, a_dtype = quantization(op, ctx, 1, "first input")
    b_scale, b_zero, b_dtype = quantization(op, ctx, 4, "second input")
    y_scale, y_zero, y_dtype = quantization(op, ctx, 6, "output")
    if len({a_dtype, b_dtype, y_dtype}) != 1:
        raise op.error(f"mixes int8 and uint8; {op.type}'s inputs and output have one type")
    for name in (a, b):
        constant = ctx.const(name)
        if constant is not None and constant.dtype != np.dtype(y_dtype.value):
            raise op.error(f"{verb} a constant of type {constant.dtype.name}, not its {y_dtype}")
    try:
        shape = np.broadcast_shapes(ctx.shape(a), ctx.shape(b))
    except ValueError:
        raise op.error(f"{verb} shapes {list(ctx.shape(a))} and {list(ctx.shape(b))}, which do not broadcast") from None
    ctx.set_shape(op, op.node.output[0], shape)
    out = requantization(op, ctx, y_scale, y_zero, y_dtype)
    return op.ir_node(op.type, [a, b], QBinaryAttrs(a_scale, a_zero, b_scale, b_zero, y_scale, out))


def convert_qlinear_add(op: OnnxOp, ctx: Context) -> Node:
    return _convert_qlinear_binary(op, ctx, "adds")


def convert_qlinear_mul(op: OnnxOp, ctx: Context) -> Node:
    return _convert_qlinear_binary(op, ctx, "multiplies")
