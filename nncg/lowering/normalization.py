"""InstanceNormalization, GroupNormalization and LayerNormalization lowerings. Per group of elements
normalised together: the mean, then the variance as the mean of the squared deviations from it (two
passes: no cancellation as in E[x^2] - E[x]^2), then y = (x - mean) * (scale / sqrt(var + epsilon))
+ bias in one store, scale and bias read there and a fused activation applied. Each dim of x splits
into the part that picks the group (outer loops, parallel) and the part that runs inside it (inner
loops): LayerNormalization's dims before `axis` are outer, the others inner; GroupNormalization's
channel c is group c // (C / G) outside and c % (C / G) inside, the spatial dims inner. Both loop
groups run in x's memory order, so a channels-last InstanceNormalization vectorises over channels, a
row-major LayerNormalization's store over its last dim."""

from __future__ import annotations

import math
from collections.abc import Callable

from ..ir.graph import Node, NormAttrs
from ..ir.loops import Affine, Assign, Binary, Call, Const, Expr, Let, Load, LocalRef, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, dim_vars, nest
from .elementwise import broadcast_load


def lower_normalization(ctx: LoweringContext, node: Node) -> None:
    attrs: NormAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], x.order)
    rank = len(x.shape)
    inside = _group_extents(node, x.shape)
    outer_vars, inner_vars = dim_vars(rank), dim_vars(rank, "r")
    outer = [(outer_vars[d], x.shape[d] // inside[d]) for d in x.order]
    inner = [(inner_vars[d], inside[d]) for d in x.order]
    count = Const.splat(math.prod(inside))
    statistics = _statistics_outputs(ctx, node, x.order)
    s, ss, mean, inv = LocalRef("s"), LocalRef("ss"), LocalRef("mean"), LocalRef("inv")

    def body(outer_env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def over(stmt_of: Callable[[list[Affine]], tuple[Stmt, ...]], parallel: bool) -> tuple[Stmt, ...]:
            def at_element(inner_env: dict[str, Affine]) -> tuple[Stmt, ...]:
                idx = [outer_env[o] * inside[d] + inner_env[i] for d, (o, i) in enumerate(zip(outer_vars, inner_vars))]
                return stmt_of(idx)

            return nest(inner, at_element, parallel)

        def deviation(idx: list[Affine]) -> Expr:
            return Binary("-", Load(x.buffer, x.at(idx)), mean)

        def normalised(idx: list[Affine]) -> tuple[Stmt, ...]:
            scale, bias = _affine(ctx, node, idx)
            value = Binary("*", deviation(idx), Binary("*", inv, scale))
            value = value if bias is None else Binary("+", value, bias)
            return (Store(out.buffer, out.at(idx), apply_activation(value, attrs.activation)),)

        add = over(lambda idx: (Assign("s", Binary("+", s, Load(x.buffer, x.at(idx)))),), parallel=False)
        add_squares = over(lambda idx: (Assign("ss", Binary("+", ss, _square(deviation(idx)))),), parallel=False)
        inv_std = Binary(
            "/", Const.splat(1.0), Call("sqrt", Binary("+", Binary("/", ss, count), Const.splat(attrs.epsilon)))
        )
        group_at = [outer_env[v] for v in outer_vars]
        kept = tuple(Store(ref.buffer, ref.at(group_at), value) for ref, value in zip(statistics, (mean, inv)) if ref)
        normalise = Let("inv", inv_std, (*kept, *over(normalised, parallel=True)))
        variance = Let("ss", Const.splat(0.0), (*add_squares, normalise))
        return (Let("s", Const.splat(0.0), (*add, Let("mean", Binary("/", s, count), (variance,)))),)

    ctx.emit(node.name, node.op, nest(outer, body, parallel=True))


def _statistics_outputs(ctx: LoweringContext, node: Node, order: tuple[int, ...]) -> list[TensorRef | None]:
    """Where LayerNormalization's mean and inverse standard deviation go (None: not used)."""
    attrs: NormAttrs = node.attrs
    names = iter(node.outputs[1:])
    return [ctx.output(next(names), order) if used else None for used in (attrs.mean_output, attrs.inv_std_output)]


def _group_extents(node: Node, shape: tuple[int, ...]) -> list[int]:
    """Per dim of x, how many of its positions one group covers."""
    attrs: NormAttrs = node.attrs
    if node.op == "LayerNormalization":
        return [1 if d < attrs.axis else n for d, n in enumerate(shape)]
    return [1, shape[1] // attrs.groups, *shape[2:]]


def _square(value: Expr) -> Expr:
    return Binary("*", value, value)


def _affine(ctx: LoweringContext, node: Node, idx: list[Affine]) -> tuple[Expr, Expr | None]:
    """scale and bias (None: no bias) at x's index `idx`: broadcast to the normalised dims
    (LayerNormalization) or per channel."""
    refs = [ctx.ref(name) for name in node.inputs[1:3]]
    if node.op == "LayerNormalization":
        loads = [broadcast_load(ref, idx) for ref in refs]
    else:
        loads = [Load(ref.buffer, ref.at([idx[1]])) for ref in refs]
    return loads[0], loads[1] if len(loads) > 1 else None
