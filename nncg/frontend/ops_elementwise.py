"""ONNX front end (ONNX -> graph IR), step 3: the pointwise activations (Sigmoid, Tanh, HardSigmoid,
HardSwish, Elu, Erf, Gelu), PRelu, the variadic Max/Min/Sum, Where, LogSoftmax, LRN and ReduceMean.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from nncg.frontend.context import SHAPE_HINT, Context, OnnxOp
from nncg.frontend.ops_nn import convert_global_pool, convert_softmax
from nncg.frontend.ops_rearrange import CONSTANT_HINT, broadcast_to
from nncg.ir.graph import Activation, LrnAttrs, Node, ReduceAttrs, Shape
from nncg.ir.kinds import GeluApproximation
from nncg.safe_text import shown


def _gelu(op: OnnxOp) -> Activation:
    """Gelu (opset 20): exact (approximate="none") or with the tanh approximation."""
    approximate = op.attr("approximate", "none")
    if approximate not in set(GeluApproximation):
        raise op.error(f"has approximate {shown(approximate)}; NNCG supports none and tanh")
    return Activation("gelu", approximate=approximate)


# The Activation record of each pointwise op, ONNX defaults filled in.
ACTIVATIONS: dict[str, Callable[[OnnxOp], Activation]] = {
    "Sigmoid": lambda op: Activation("sigmoid"),
    "Tanh": lambda op: Activation("tanh"),
    "HardSigmoid": lambda op: Activation(
        "hard_sigmoid", alpha=float(op.attr("alpha", 0.2)), beta=float(op.attr("beta", 0.5))
    ),
    "HardSwish": lambda op: Activation("hard_swish", alpha=1 / 6, beta=0.5),
    "Elu": lambda op: Activation("elu", alpha=float(op.attr("alpha", 1.0))),
    "Erf": lambda op: Activation("erf"),
    "Gelu": _gelu,
}


def convert_activation(op: OnnxOp, ctx: Context) -> Node:
    return op.ir_node(op.type, [op.input(0)], ACTIVATIONS[op.type](op))


def convert_prelu(op: OnnxOp, ctx: Context) -> Node:
    """The slope (constant or not) broadcasts to x in one direction: the output has x's shape."""
    x, slope = op.input(0), op.input(1)
    x_shape = ctx.shape(x)
    if _broadcast_shape(op, ctx, [x, slope]) != x_shape:
        raise op.error(f"has slope of shape {list(ctx.shape(slope))}, which does not broadcast to X {list(x_shape)}")
    ctx.set_shape(op, op.node.output[0], x_shape)
    return op.ir_node("PRelu", [x, slope])


def convert_variadic(op: OnnxOp, ctx: Context) -> Node:
    """Max/Min/Sum of any number of inputs, broadcast together. One input is an Identity; Max or Min
    of a tensor and a scalar constant is a Clip, which a producer can then apply at its store."""
    inputs = [name for name in op.node.input if name]
    shape = _broadcast_shape(op, ctx, inputs)
    ctx.set_shape(op, op.node.output[0], shape)
    if len(inputs) == 1:
        return op.ir_node("Identity", inputs)
    clip = _scalar_clip(op, ctx, inputs, shape)
    return clip if clip is not None else op.ir_node(op.type, inputs)


def convert_where(op: OnnxOp, ctx: Context) -> Node | tuple[Node, ...]:
    """Where(condition, X, Y) with a constant condition, as 0/1 floats; X and Y broadcast with it. A
    condition that picks one runtime side everywhere is that side, broadcast."""
    condition = ctx.constant_input(op, 0, "condition", CONSTANT_HINT)
    if condition.dtype != np.bool_:
        raise op.error(f"has a condition of type {condition.dtype.name}; Where needs a bool condition")
    x, y = op.input(1), op.input(2)
    out = _broadcast_shape(op, ctx, [op.input(0), x, y])
    ctx.set_shape(op, op.node.output[0], out)
    side = x if condition.all() else y if not condition.any() else None
    if side is not None and ctx.const(side) is None:
        return broadcast_to(op, ctx, side, out)
    mask = ctx.add_constant(f"{op.name}_condition", condition.astype(np.float32))
    return op.ir_node("Where", [mask, x, y])


def convert_log_softmax(op: OnnxOp, ctx: Context) -> Node:
    """The same axis rules as Softmax (opset < 13: flatten to 2-D at axis)."""
    return replace(convert_softmax(op, ctx), op="LogSoftmax")


def convert_lrn(op: OnnxOp, ctx: Context) -> Node:
    x = op.input(0)
    size, rank = op.attr("size"), len(ctx.shape(x))
    if not isinstance(size, int) or size < 1:
        raise op.error(f"has size={size}; LRN needs its size attribute, a channel count >= 1")
    if rank < 3:
        raise op.error(f"has a rank-{rank} input; LRN needs [N, C, D1, ...]")
    attrs = LrnAttrs(size, float(op.attr("alpha", 1e-4)), float(op.attr("beta", 0.75)), float(op.attr("bias", 1.0)))
    return op.ir_node("LRN", [x], attrs)


def convert_reduce_mean(op: OnnxOp, ctx: Context) -> Node:
    """The mean over the spatial dims with keepdims is a GlobalAveragePool; other axes reduce in place."""
    x = op.input(0)
    shape = ctx.shape(x)
    rank = len(shape)
    axes = _reduce_axes(op, ctx, rank)
    if not axes and op.attr("noop_with_empty_axes", 0):
        ctx.set_shape(op, op.node.output[0], shape)
        return op.ir_node("Identity", [x])
    axes = axes or tuple(range(rank))  # no axes: reduce them all
    keepdims = bool(op.attr("keepdims", 1))
    if keepdims and rank >= 3 and axes == tuple(range(2, rank)):
        # convert_global_pool names the op after the ONNX type without "Global": set the pool here.
        return replace(convert_global_pool(op, ctx), op="AveragePool")
    out_shape = tuple(1 if d in axes else n for d, n in enumerate(shape) if keepdims or d not in axes)
    ctx.set_shape(op, op.node.output[0], out_shape)
    return op.ir_node("ReduceMean", [x], ReduceAttrs(axes, keepdims))


def _reduce_axes(op: OnnxOp, ctx: Context, rank: int) -> Shape:
    """The reduced axes, sorted and non-negative: an attribute before opset 18, then a constant input."""
    if ctx.opset < 18:
        raw = op.attr("axes", [])
    else:
        raw = ctx.constant_input(op, 1, "axes", SHAPE_HINT).tolist() if op.input(1) else []
    if any(not -rank <= a < rank for a in raw) or len({a % rank for a in raw}) != len(raw):
        raise op.error(
            f"has axes {list(raw)}; they must be distinct and in [-{rank}, {rank}) for its rank-{rank} input"
        )
    return tuple(sorted(a % rank for a in raw))


def _broadcast_shape(op: OnnxOp, ctx: Context, inputs: list[str]) -> Shape:
    shapes = [ctx.shape(name) for name in inputs]
    try:
        return tuple(int(d) for d in np.broadcast_shapes(*shapes))
    except ValueError:
        raise op.error(f"has inputs of shapes {[list(s) for s in shapes]}, which do not broadcast together") from None


def _scalar_clip(op: OnnxOp, ctx: Context, inputs: list[str], shape: Shape) -> Node | None:
    """Max(x, c) as clip(low=c) and Min(x, c) as clip(high=c), for a one-element constant c that
    does not change x's shape."""
    if op.type == "Sum" or len(inputs) != 2:
        return None
    consts = [ctx.const(name) for name in inputs]
    if sum(c is None for c in consts) != 1:
        return None
    x = inputs[0] if consts[0] is None else inputs[1]
    c = consts[1] if consts[0] is None else consts[0]
    if c.size != 1 or ctx.shape(x) != shape:
        return None
    bound = float(c.reshape(()))
    act = Activation("clip", low=bound) if op.type == "Max" else Activation("clip", high=bound)
    return op.ir_node("Clip", [x], act)
