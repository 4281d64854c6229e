"""ONNX front end: onnxruntime's QLinearConcat (com.microsoft), and the QDQ Concat that qdq.py
rewrites into it, as its CPU kernel computes it (contrib_ops/cpu/quantization/qlinear_concat.cc): an
input quantised as the output is (the same float32 scale and zero point) is copied; any other is
requantised through a 256-entry table built as for QLinearLeakyRelu with the identity
(ops_qlookup.py), then copied. A constant input is requantised here, at generation time."""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_data import concat_node
from nncg.frontend.ops_qlookup import lookup_table
from nncg.frontend.ops_quantized import quantization
from nncg.ir.graph import Node, QLookupAttrs


def convert_qlinear_concat(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    """QLinearConcat: Y_scale, Y_zero_point, then X, X_scale, X_zero_point per input; axis."""
    count = len(op.node.input) - 2
    if count < 3 or count % 3:
        raise op.error("has inputs that are not (tensor, scale, zero point) triples after Y_scale, Y_zero_point")
    out = quantization(op, ctx, 0, "output")
    steps, parts = [], []
    for i in range(count // 3):
        slot = 2 + 3 * i
        x, quantized = op.input(slot), quantization(op, ctx, slot + 1, f"input {i}")
        if quantized[2] != out[2]:
            raise op.error("mixes int8 and uint8; QLinearConcat's inputs and output have one type")
        if quantized == out:
            parts.append(x)
            continue
        table = lookup_table(lambda v: v, quantized, out)
        base = f"{op.node.output[0]}_in{i}"
        constant = ctx.const(x)
        if constant is not None:
            parts.append(ctx.add_constant(base, table[constant.astype(np.int32) - out[2].range[0]]))
            continue
        requantized = ctx.intermediate(op, f"in{i}", ctx.shape(x))
        lut = ctx.add_constant(f"{base}_lut", table)
        steps.append(op.ir_step("QLinearLookup", f"in{i}", [x, lut], requantized, QLookupAttrs("Identity", out[2])))
        parts.append(requantized)
    return (*steps, concat_node(op, ctx, parts))
