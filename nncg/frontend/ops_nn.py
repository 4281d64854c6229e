"""ONNX front end (ONNX -> graph IR), step 3: convert the CNN layers (Conv, pools, activations,
BatchNormalization, Softmax) into graph IR nodes with fully resolved attribute records.
"""

from __future__ import annotations

import math
from dataclasses import replace

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_conv import bias_input, check_groups, weight_kernel
from nncg.frontend.windows import (
    check_window_fits,
    checked_pool_output_shape,
    pool_attrs,
    resolve_pads,
    window_steps,
)
from nncg.ir.graph import (
    Activation,
    BatchNormAttrs,
    ConvAttrs,
    Node,
    PoolAttrs,
    SoftmaxAttrs,
)
from nncg.safe_text import shown


def convert_conv(op: OnnxOp, ctx: Context) -> Node:
    x, w = op.input(0), op.input(1)
    attrs = conv_geometry(op, ctx.shape(x), ctx.shape(w))
    return op.ir_node("Conv", [x, w, *bias_input(op, ctx, ctx.shape(w)[0])], attrs)


def conv_geometry(op: OnnxOp, x_shape: tuple[int, ...], w_shape: tuple[int, ...]) -> ConvAttrs:
    """The window of a Conv or QLinearConv (w: [C_out, C_in/group, k...]), checked against x."""
    group = int(op.attr("group", 1))
    check_groups(op, group, x_shape[1], w_shape[0], w_shape, w_shape[1] * group == x_shape[1])
    kernel = weight_kernel(op, w_shape)
    strides, dilations = window_steps(op, len(kernel))
    begin, end = resolve_pads(op, x_shape[2:], kernel, strides, dilations)
    check_window_fits(op, x_shape[2:], kernel, dilations, begin, end)
    return ConvAttrs(kernel, strides, dilations, begin, end, group)


def convert_maxpool(op: OnnxOp, ctx: Context) -> Node:
    if op.attr("storage_order", 0) != 0:
        raise op.error("has storage_order=1 (column-major indices); only storage_order=0 is supported")
    if ctx.is_used(op.output(1)):
        raise op.error(
            f"has its Indices output {shown(op.output(1))} used; NNCG computes only the pooled values: "
            "remove the use of the indices"
        )
    x = op.input(0)
    in_shape = ctx.shape(x)
    attrs = pool_attrs(op, in_shape)
    ctx.set_shape(op, op.node.output[0], checked_pool_output_shape(op, attrs, in_shape))
    return op.ir_node("MaxPool", [x], attrs)


def convert_averagepool(op: OnnxOp, ctx: Context) -> Node:
    x = op.input(0)
    in_shape = ctx.shape(x)
    attrs = replace(pool_attrs(op, in_shape), count_include_pad=bool(op.attr("count_include_pad", 0)))
    ctx.set_shape(op, op.node.output[0], checked_pool_output_shape(op, attrs, in_shape))
    return op.ir_node("AveragePool", [x], attrs)


def convert_global_pool(op: OnnxOp, ctx: Context) -> Node:
    """GlobalAveragePool / GlobalMaxPool: a pool whose window is the whole spatial extent."""
    x = op.input(0)
    in_shape = ctx.shape(x)
    n = len(in_shape) - 2
    attrs = PoolAttrs(tuple(in_shape[2:]), (1,) * n, (1,) * n, (0,) * n, (0,) * n)
    ctx.set_shape(op, op.node.output[0], tuple(in_shape[:2]) + (1,) * n)
    return op.ir_node(op.node.op_type.removeprefix("Global"), [x], attrs)


def convert_clip(op: OnnxOp, ctx: Context) -> Node | tuple[Node, ...]:
    """Clip's bounds: attributes before opset 11, optional scalar inputs from 11 on. Constant bounds
    make a clip activation (fused into the producer's store); a bound computed at run time (a graph
    input, say) a Max with it, then a Min with the upper one."""
    if ctx.opset < 11:
        low, high = float(op.attr("min", float("-inf"))), float(op.attr("max", float("inf")))
        return op.ir_node("Clip", [op.input(0)], Activation("clip", low=low, high=high))
    bounds = (op.input(1), op.input(2))
    for bound in bounds:
        if bound and math.prod(ctx.shape(bound)) != 1:
            raise op.error(f"has a min or max of shape {list(ctx.shape(bound))}; Clip's bounds are scalars")
    if any(bound and ctx.const(bound) is None for bound in bounds):
        return _runtime_clip(op, ctx, bounds)
    low, high = (float(ctx.const(b).reshape(())) if b else default for b, default in zip(bounds, (-math.inf, math.inf)))
    return op.ir_node("Clip", [op.input(0)], Activation("clip", low=low, high=high))


def _runtime_clip(op: OnnxOp, ctx: Context, bounds: tuple[str | None, str | None]) -> tuple[Node, ...]:
    """max(x, min), then min(that, max): the bounds broadcast as scalars (ONNX Clip gives NaN bounds
    no meaning, so the order of max and min does not matter)."""
    steps = [(kind, bound) for kind, bound in zip(("Max", "Min"), bounds) if bound]
    shape = ctx.shape(op.input(0))
    ctx.set_shape(op, op.node.output[0], shape)
    if len(steps) == 1:
        return (op.ir_node(steps[0][0], [op.input(0), steps[0][1]]),)
    low = ctx.intermediate(op, "low", shape)
    return (op.ir_step("Max", "low", [op.input(0), bounds[0]], low, None), op.ir_node("Min", [low, bounds[1]]))


def convert_relu(op: OnnxOp, ctx: Context) -> Node:
    return op.ir_node("Relu", [op.input(0)], Activation("relu"))


def convert_leaky_relu(op: OnnxOp, ctx: Context) -> Node:
    return op.ir_node("LeakyRelu", [op.input(0)], Activation("leaky_relu", float(op.attr("alpha", 0.01))))


def convert_batchnorm(op: OnnxOp, ctx: Context) -> Node:
    if op.attr("training_mode", 0) != 0:
        raise op.error("has training_mode=1; only inference is supported: export the model in eval mode")
    for index, output in enumerate(op.node.output[1:], start=1):
        if ctx.is_used(output):
            raise op.error(
                f"has its output {index} ({shown(output)}, running statistics) used; only the normalized "
                "output may be used: export the model in eval mode"
            )
    x = op.input(0)
    shape = ctx.shape(x)
    if op.attr("spatial", 1) == 0 and len(shape) > 2:
        raise op.error("has spatial=0 (per-position statistics); only per-channel BatchNormalization is supported")
    roles = ("scale", "bias", "mean", "variance")
    for index, role in enumerate(roles, start=1):  # constant or computed at runtime
        param = ctx.shape(op.input(index))
        if param != (shape[1],):
            raise op.error(f"has {role} of shape {list(param)}; expected [{shape[1]}] (one per channel)")
    return op.ir_node("BatchNormalization", [x, *(op.input(i) for i in range(1, 5))], BatchNormAttrs(_epsilon(op)))


def convert_softmax(op: OnnxOp, ctx: Context) -> Node:
    x = op.input(0)
    rank = len(ctx.shape(x))
    legacy = ctx.opset < 13  # before 13: flatten to 2-D at axis, default axis 1
    axis = op.attr("axis", 1 if legacy else -1)
    if not -rank <= axis < rank:
        raise op.error(f"has axis={axis}, out of range for its rank-{rank} input")
    return op.ir_node("Softmax", [x], SoftmaxAttrs(axis=axis % rank, coerce_2d=legacy))


def _epsilon(op: OnnxOp) -> float:
    return float(op.attr("epsilon", 1e-5))
