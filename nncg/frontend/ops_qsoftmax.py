"""ONNX front end: onnxruntime's QLinearSoftmax (com.microsoft), and the QDQ Softmax that qdq.py
rewrites into it, as onnxruntime's CPU kernel computes it (contrib_ops/cpu/quantization/
qlinear_softmax.cc), so the integer results match to the bit.

The kernel reads exp values from a table of 256 float32 entries built from x_scale alone:
table[i] = float(exp((i - 255 + shift) * x_scale)) in double, with shift = max(0, log(FLT_MAX / D) - 5)
/ x_scale and D the number of elements a softmax reduces (the headroom keeps the float sum of D
entries finite). Element x of a row whose maximum is m reads table[255 - (m - x)]; the row's
entries are summed in float32 in order, and each output is round_half_even(entry * floor(1 / y_scale)
/ sum) + y_zero_point (float32 products and quotient), saturated to the output type (onnxruntime
1.32 saturates int8 too, and runs an int8 QDQ Softmax in uint8, +128, which is the same); the input
zero point cancels out."""

from __future__ import annotations

import math

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_quantized import quantization
from nncg.ir.graph import Node, QSoftmaxAttrs, Requantization, SoftmaxAttrs

F32 = np.float32
HEADROOM = 5.0  # onnxruntime's reserve_bit for its float table


def exp_table(x_scale: float, reduced: int) -> np.ndarray:
    """onnxruntime's lookup table (QlinearBuildLookupTableUint32 with a float table): the log and
    the exps in double (C's, through math), each entry rounded once to float32."""
    scale = float(F32(x_scale))
    shift = max(0.0, math.log(float(np.finfo(F32).max / F32(reduced))) - HEADROOM) / scale
    return np.array([math.exp((i - 255 + shift) * scale) for i in range(256)], dtype=F32)


def softmax_axis(op: OnnxOp, rank: int, opset: int) -> SoftmaxAttrs:
    """Softmax's axis rule: before opset 13 the dims from axis on are flattened (default axis 1)."""
    legacy = opset < 13
    axis = op.attr("axis", 1 if legacy else -1)
    if not -rank <= axis < rank:
        raise op.error(f"has axis={axis}, out of range for its rank-{rank} input")
    return SoftmaxAttrs(axis % rank, legacy)


def convert_qlinear_softmax(op: OnnxOp, ctx: Context) -> Node:
    """QLinearSoftmax: X, x_scale, x_zero_point, y_scale, y_zero_point; its `opset` attribute gives
    the axis rule (a Softmax that qdq.py rewrote has none: the model's opset)."""
    x = op.input(0)
    shape = ctx.shape(x)
    x_scale = quantization(op, ctx, 1, "input")[0]  # either type: 255 - (max - x) indexes the table
    y_scale, y_zero, y_dtype = quantization(op, ctx, 3, "output")
    softmax = softmax_axis(op, len(shape), int(op.attr("opset", ctx.opset)))
    reduced = math.prod(shape[softmax.axis :]) if softmax.coerce_2d else shape[softmax.axis]
    table = ctx.add_constant(f"{op.node.output[0]}_exp", exp_table(x_scale, reduced))
    ctx.set_shape(op, op.node.output[0], shape)
    multiplier = float(np.floor(F32(1) / F32(y_scale)))
    out = Requantization(y_zero, *y_dtype.range, y_dtype)
    return op.ir_node("QLinearSoftmax", [x, table], QSoftmaxAttrs(softmax, multiplier, out))
