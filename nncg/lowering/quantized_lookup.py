"""Lowering of QLinearLookup: each int8/uint8 element replaced by its entry in the op's 256-entry
table (frontend/ops_qlookup.py computes the tables), indexed by the value minus its type's lowest."""

from __future__ import annotations

from ..ir.graph import Node
from ..ir.loops import Affine, Binary, Const, Expr, Lookup
from .context import LoweringContext
from .elementwise import elementwise
from .quantized import widened


def lower_qlinear_lookup(ctx: LoweringContext, node: Node) -> None:
    x = ctx.ref(node.inputs[0])
    table = ctx.add_constant(f"lut_{node.name}", ctx.graph.constants[node.inputs[1]])
    lowest = ctx.graph.dtype(node.inputs[0]).range[0]

    def value(idx: list[Affine]) -> Expr:
        index = widened(x, idx)
        return Lookup(table.buffer, Binary("+", index, Const.integer(-lowest)) if lowest else index)

    elementwise(ctx, node, x.order, value)
