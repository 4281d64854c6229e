"""ONNX front end (ONNX -> graph IR), step 3: the pointwise activations and unary math ops (Sigmoid,
Tanh, HardSigmoid, HardSwish, Elu, Erf, Gelu, Abs, Neg, Sqrt, Exp, Log, Reciprocal, Softplus,
Softsign, Mish, Selu, Celu, ThresholdedRelu; Pow by constant exponents), PRelu, the variadic
Max/Min/Sum, Where, LogSoftmax and LRN.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_nn import convert_softmax
from nncg.frontend.ops_rearrange import CONSTANT_HINT, broadcast_to
from nncg.ir.graph import Activation, LrnAttrs, Node, Shape
from nncg.ir.kinds import GeluApproximation
from nncg.safe_text import shown


def _gelu(op: OnnxOp) -> Activation:
    """Gelu (opset 20): exact (approximate="none") or with the tanh approximation."""
    approximate = op.attr("approximate", "none")
    if approximate not in set(GeluApproximation):
        raise op.error(f"has approximate {shown(approximate)}; NNCG supports none and tanh")
    return Activation("gelu", approximate=approximate)


# Selu's defaults, the float32 values of the ONNX spec
SELU_ALPHA = 1.67326319217681884765625
SELU_GAMMA = 1.05070102214813232421875
POW_HINT = "NNCG compiles Pow by a constant exponent: make it an initializer or a Constant"

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
    "Abs": lambda op: Activation("abs"),
    "Neg": lambda op: Activation("neg"),
    "Sqrt": lambda op: Activation("sqrt"),
    "Exp": lambda op: Activation("exp"),
    "Log": lambda op: Activation("log"),
    "Reciprocal": lambda op: Activation("reciprocal"),
    "Softplus": lambda op: Activation("softplus"),
    "Softsign": lambda op: Activation("softsign"),
    "Mish": lambda op: Activation("mish"),
    "Selu": lambda op: Activation(
        "selu", alpha=float(op.attr("alpha", SELU_ALPHA)), gamma=float(op.attr("gamma", SELU_GAMMA))
    ),
    "Celu": lambda op: Activation("celu", alpha=float(op.attr("alpha", 1.0))),
    "ThresholdedRelu": lambda op: Activation("thresholded_relu", alpha=float(op.attr("alpha", 1.0))),
}


def convert_activation(op: OnnxOp, ctx: Context) -> Node:
    return op.ir_node(op.type, [op.input(0)], ACTIVATIONS[op.type](op))


def convert_pow(op: OnnxOp, ctx: Context) -> Node:
    """Pow by a constant exponent that keeps x's shape. One exponent for all elements is a pointwise
    activation, which x's producer can apply at its store; an exponent per element a PowPerElement
    node reading it (as float32) and the sign each gives a negative base's power: -1 for an odd
    integer, 1 for an even one, 0 for the rest (their powers of a negative base are NaN)."""
    x, exponent = op.input(0), ctx.constant_input(op, 1, "exponent", POW_HINT)
    if _broadcast_shape(op, ctx, [x, op.input(1)]) != ctx.shape(x):
        raise op.error(f"has an exponent of shape {list(exponent.shape)}, which broadcasts X {list(ctx.shape(x))} up")
    if not np.all(np.isfinite(exponent)):
        raise op.error("has an infinite or NaN exponent; NNCG compiles Pow by finite exponents")
    values = np.unique(exponent)
    if values.size == 1:
        return op.ir_node("Pow", [x], Activation("pow", alpha=float(values[0])))
    y = exponent.astype(np.float32)
    sign = np.where(y % 2 == 0, 1, np.where(y % 2 == 1, -1, 0)).astype(np.float32)
    per_element = [ctx.add_constant(f"{op.name}_exponent", y), ctx.add_constant(f"{op.name}_sign", sign)]
    return op.ir_node("PowPerElement", [x, *per_element])


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
