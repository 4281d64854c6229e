"""Element-wise lowerings: standalone activations, per-channel scale and shift (BatchNorm), the
arithmetic ops (binary Add/Sub/Mul/Div, variadic Max/Min/Sum), PRelu, Where and Pow by an exponent per
element with NumPy broadcasting.
Loops run in the output's memory order."""

from __future__ import annotations

from collections.abc import Callable

from ..ir.batchnorm import scale_shift_of_batchnorm
from ..ir.graph import Activation, Node, ScaleShiftAttrs
from ..ir.loops import Affine, Binary, Call, Const, Expr, Load, Select, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, dim_vars, nest, row_major

# Each op folds its operands left to right with one IR operator.
BINARY = {"Add": "+", "Sub": "-", "Mul": "*", "Div": "/", "Max": "max", "Min": "min", "Sum": "+"}


def elementwise(ctx: LoweringContext, node: Node, order, value: Callable[[list[Affine]], Expr]) -> None:
    """out[idx] = value(idx) for every logical idx, looping in the output's physical dim order."""
    out = ctx.output(node.outputs[0], order)
    names = dim_vars(len(out.shape))

    def body(env: dict[str, Affine]) -> tuple:
        idx = [env[v] for v in names]
        return (Store(out.buffer, out.at(idx), value(idx)),)

    loops = [(names[d], out.shape[d]) for d in out.order]
    ctx.emit(node.name, node.op, nest(loops, body, parallel=True))


def broadcast_load(ref: TensorRef, idx: list[Affine]) -> Load:
    """Reads ref at the output index, NumPy-broadcast: dims aligned right, size-1 dims pinned to 0."""
    skip = len(idx) - len(ref.shape)
    return Load(ref.buffer, ref.at([i if d != 1 else 0 for i, d in zip(idx[skip:], ref.shape)]))


def lower_activation(ctx: LoweringContext, node: Node) -> None:
    x = ctx.ref(node.inputs[0])
    act: Activation = node.attrs
    elementwise(ctx, node, x.order, lambda idx: apply_activation(Load(x.buffer, x.at(idx)), act))


def lower_scale_shift(ctx: LoweringContext, node: Node) -> None:
    attrs: ScaleShiftAttrs = node.attrs
    scale, shift = (ctx.graph.constants[name] for name in node.inputs[1:3])
    _scale_shift(ctx, node, scale, shift, attrs.activation)


def lower_batchnorm(ctx: LoweringContext, node: Node) -> None:
    """A BatchNorm that no pass folded away still compiles: as its scale and shift, or from its
    statistics per element when they are computed at runtime."""
    if all(ctx.graph.is_constant(name) for name in node.inputs[1:5]):
        _scale_shift(ctx, node, *scale_shift_of_batchnorm(ctx.graph.constants, node), None)
    else:
        _runtime_batchnorm(ctx, node)


def _runtime_batchnorm(ctx: LoweringContext, node: Node) -> None:
    """y = (x - mean) * (gamma / sqrt(var + eps)) + beta."""
    x = ctx.ref(node.inputs[0])
    gamma, beta, mean, var = (ctx.ref(name) for name in node.inputs[1:5])

    def value(idx: list[Affine]) -> Expr:
        def at_channel(ref: TensorRef) -> Load:
            return Load(ref.buffer, ref.at([idx[1]]))

        std = Call("sqrt", Binary("+", at_channel(var), Const.splat(node.attrs.epsilon)))
        centred = Binary("-", Load(x.buffer, x.at(idx)), at_channel(mean))
        return Binary("+", Binary("*", centred, Binary("/", at_channel(gamma), std)), at_channel(beta))

    elementwise(ctx, node, x.order, value)


def _scale_shift(ctx: LoweringContext, node: Node, scale, shift, act: Activation | None) -> None:
    x = ctx.ref(node.inputs[0])
    scale_ref = ctx.add_constant(f"scale_{node.name}", scale)
    shift_ref = ctx.add_constant(f"shift_{node.name}", shift)

    def value(idx: list[Affine]) -> Expr:
        c = idx[1]
        scaled = Binary("*", Load(x.buffer, x.at(idx)), Load(scale_ref.buffer, scale_ref.at([c])))
        return apply_activation(Binary("+", scaled, Load(shift_ref.buffer, shift_ref.at([c]))), act)

    elementwise(ctx, node, x.order, value)


def lower_binary(ctx: LoweringContext, node: Node) -> None:
    """Add, Sub, Mul, Div and the variadic Max, Min, Sum: ((in0 op in1) op in2) ..."""
    op = BINARY[node.op]

    def fold(loads: list[Load]) -> Expr:
        value: Expr = loads[0]
        for load in loads[1:]:
            value = Binary(op, value, load)
        return value

    broadcast(ctx, node, fold)


def lower_prelu(ctx: LoweringContext, node: Node) -> None:
    """y = x > 0 ? x : slope * x, the slope broadcast to x."""

    def prelu(loads: list[Load]) -> Expr:
        x, slope = loads
        return Select(">", x, Const.splat(0.0), x, Binary("*", slope, x))

    broadcast(ctx, node, prelu)


def lower_pow_per_element(ctx: LoweringContext, node: Node) -> None:
    """x^y with a constant exponent y per element and the sign s of a negative base's power (-1, 1,
    or 0 where y is no integer): exp(y log|x|) times s below 0, or exp(y log x), whose negative x
    give log's NaN; 1 where y is 0, as pow (even for x = 0, Inf or NaN). Unlike pow, x = -0 counts as
    +0 and -Inf to an exponent that is no integer is NaN."""

    def power(loads: list[Load]) -> Expr:
        x, y, sign = loads
        zero = Const.splat(0.0)
        base = Select(">", Binary("*", sign, sign), zero, Call("abs", x), x)
        magnitude = Call("exp", Binary("*", Call("log", base), y))
        signed = Select("<", x, zero, Binary("*", magnitude, sign), magnitude)
        return Select(">", Call("abs", y), zero, signed, Const.splat(1.0))

    broadcast(ctx, node, power)


def lower_where(ctx: LoweringContext, node: Node) -> None:
    """condition ? x : y per element, the condition a constant of 0s and 1s."""

    def where(loads: list[Load]) -> Expr:
        condition, x, y = loads
        return Select(">", condition, Const.splat(0.0), x, y)

    broadcast(ctx, node, where)


def broadcast(ctx: LoweringContext, node: Node, combine: Callable[[list[Load]], Expr]) -> None:
    """out[idx] = combine(the inputs read at idx with NumPy broadcasting)."""
    refs = [ctx.ref(name) for name in node.inputs]
    out_shape = ctx.graph.shape(node.outputs[0])
    # Follow the layout of a full-size runtime operand so its loads stay contiguous.
    full = [r for name, r in zip(node.inputs, refs) if not ctx.graph.is_constant(name) and r.shape == out_shape]
    order = full[0].order if full else row_major(len(out_shape))
    elementwise(ctx, node, order, lambda idx: combine([broadcast_load(r, idx) for r in refs]))
