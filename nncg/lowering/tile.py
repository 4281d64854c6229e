"""Tile lowering (Tile, Expand): a broadcast copy. An output dim of extent repeats x n is two loops,
over the repeat r and over the input's extent i, so both sides stay affine: output r * n + i reads
input i. Loops run in the output's memory order (an internal output keeps the input's layout), the
input's extent innermost of each pair, so the copy of a whole input row is contiguous on both sides."""

from __future__ import annotations

from ..ir.graph import Node, TileAttrs
from ..ir.loops import Affine, Load, Store
from .context import LoweringContext, dim_vars, nest
from .reshape import copy_order


def lower_tile(ctx: LoweringContext, node: Node) -> None:
    attrs: TileAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], copy_order(ctx, node.outputs[0], x.order))
    inner, outer = dim_vars(len(x.shape)), dim_vars(len(x.shape), "r")
    loops = [loop for d in out.order for loop in ((outer[d], attrs.repeats[d]), (inner[d], x.shape[d]))]

    def body(env: dict[str, Affine]) -> tuple[Store, ...]:
        at = [env[v] for v in inner]
        repeated = [env[r] * n + i for r, n, i in zip(outer, x.shape, at)]
        return (Store(out.buffer, out.at(repeated), Load(x.buffer, x.at(at))),)

    ctx.emit(node.name, node.op, nest(loops, body, parallel=True))
