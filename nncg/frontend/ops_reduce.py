"""ONNX front end (ONNX -> graph IR), step 3: the reductions (ReduceSum, ReduceMean, ReduceMax,
ReduceMin, ReduceL1, ReduceL2, ReduceSumSquare, ReduceLogSum, ReduceLogSumExp), ArgMax and ArgMin."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nncg.frontend.context import SHAPE_HINT, Context, OnnxOp
from nncg.frontend.empty_reductions import EMPTY_VALUES
from nncg.frontend.ops_nn import convert_global_pool
from nncg.ir.graph import ArgMaxAttrs, Node, ReduceAttrs, Shape
from nncg.limits import INT32_MAX

# Reductions that leave one element as it is: over no axes (noop_with_empty_axes) an Identity. The
# others still apply their function to each element (ReduceL2: |x|, ReduceSumSquare: x * x).
_ELEMENT_UNCHANGED = ("ReduceSum", "ReduceMean", "ReduceMax", "ReduceMin")


def convert_reduce(op: OnnxOp, ctx: Context) -> Node:
    """Reduce* over constant axes; the mean over the spatial dims with keepdims is a global AveragePool."""
    x = op.input(0)
    shape = ctx.shape(x)
    rank = len(shape)
    axes = _reduce_axes(op, ctx, rank)
    if not axes and op.attr("noop_with_empty_axes", 0):
        if op.type in _ELEMENT_UNCHANGED:
            ctx.set_shape(op, op.node.output[0], shape)
            return op.ir_node("Identity", [x])
    else:
        axes = axes or tuple(range(rank))  # no axes: reduce them all
    keepdims = bool(op.attr("keepdims", 1))
    if any(shape[a] == 0 for a in axes):
        return _over_nothing(op, ctx, _reduced_shape(shape, axes, keepdims))
    if op.type == "ReduceMean" and keepdims and rank >= 3 and axes == tuple(range(2, rank)):
        # convert_global_pool names the op after the ONNX type without "Global": set the pool here.
        return replace(convert_global_pool(op, ctx), op="AveragePool")
    ctx.set_shape(op, op.node.output[0], _reduced_shape(shape, axes, keepdims))
    return op.ir_node(op.type, [x], ReduceAttrs(axes, keepdims))


def _over_nothing(op: OnnxOp, ctx: Context, shape: Shape) -> Node:
    """A reduction over an empty axis: its value over no elements, a constant (load_model admits an
    empty input only for this)."""
    if op.type not in EMPTY_VALUES:
        raise op.error("reduces an empty axis, which NNCG compiles only for " + ", ".join(EMPTY_VALUES))
    ctx.set_shape(op, op.node.output[0], shape)
    value = ctx.add_constant(f"{op.node.output[0]}_empty", np.full(shape, EMPTY_VALUES[op.type], np.float32))
    return op.ir_node("Identity", [value])


def convert_arg_extreme(op: OnnxOp, ctx: Context) -> Node:
    """ArgMax / ArgMin. ONNX's int64 indices are written as int32 (C89 has no guaranteed 64-bit
    integer type). No supported op reads an int64 tensor, so the indices reach only graph outputs,
    which load_model lets be int64 for this op alone; the header says they are int32."""
    x = op.input(0)
    shape = ctx.shape(x)
    axis = op.attr("axis", 0) % len(shape)  # in [-rank, rank): ONNX shape inference checks it
    if shape[axis] - 1 > INT32_MAX:
        raise op.error(
            f"reduces an axis of {shape[axis]} elements; NNCG writes the indices as int32, at most "
            f"{INT32_MAX}: reduce a shorter axis"
        )
    keepdims = bool(op.attr("keepdims", 1))
    ctx.set_shape(op, op.node.output[0], _reduced_shape(shape, (axis,), keepdims))
    return op.ir_node(op.type, [x], ArgMaxAttrs(axis, keepdims, bool(op.attr("select_last_index", 0))))


def _reduced_shape(shape: Shape, axes: Shape, keepdims: bool) -> Shape:
    return tuple(1 if d in axes else n for d, n in enumerate(shape) if keepdims or d not in axes)


def _reduce_axes(op: OnnxOp, ctx: Context, rank: int) -> Shape:
    """The reduced axes, sorted and non-negative: an attribute, then (from opset 13 for ReduceSum, 18
    for the others) a constant input."""
    if ctx.opset < (13 if op.type == "ReduceSum" else 18):
        raw = op.attr("axes", [])
    else:
        raw = ctx.constant_input(op, 1, "axes", SHAPE_HINT).tolist() if op.input(1) else []
    if any(not -rank <= a < rank for a in raw) or len({a % rank for a in raw}) != len(raw):
        raise op.error(
            f"has axes {list(raw)}; they must be distinct and in [-{rank}, {rank}) for its rank-{rank} input"
        )
    return tuple(sorted(a % rank for a in raw))
