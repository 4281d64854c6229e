"""ReduceMean lowering: per kept position, a sum over the reduced dims divided by their count. Both
loop groups run in the input's memory order, the kept dims outside, so that over a channels-last
input (the spatial mean after a Conv) the channel loop is the innermost parallel one and vectorises."""

from __future__ import annotations

import math

from ..ir.graph import Node, ReduceAttrs
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Stmt, Store
from .context import LoweringContext, dim_vars, nest


def lower_reduce_mean(ctx: LoweringContext, node: Node) -> None:
    attrs: ReduceAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    rank = len(x.shape)
    kept = [d for d in range(rank) if d not in attrs.axes]
    # The output's dims: all of x's with keepdims (the reduced ones of size 1), else the kept ones.
    out_dims = list(range(rank)) if attrs.keepdims else kept
    out = ctx.output(node.outputs[0], tuple(out_dims.index(d) for d in x.order if d in out_dims))
    names = dim_vars(rank)
    outer = [(names[d], x.shape[d]) for d in x.order if d in kept]
    inner = [(names[d], x.shape[d]) for d in x.order if d in attrs.axes]
    count = math.prod(x.shape[d] for d in attrs.axes)

    def body(outer_env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def add(inner_env: dict[str, Affine]) -> tuple[Stmt, ...]:
            env = outer_env | inner_env
            return (Assign("s", Binary("+", LocalRef("s"), Load(x.buffer, x.at([env[v] for v in names])))),)

        at = [outer_env[names[d]] if d in kept else Affine() for d in out_dims]
        mean = Store(out.buffer, out.at(at), Binary("/", LocalRef("s"), Const.splat(count)))
        return (Let("s", Const.splat(0.0), (*nest(inner, add, parallel=False), mean)),)

    ctx.emit(node.name, node.op, nest(outer, body, parallel=True))
