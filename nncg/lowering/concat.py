"""Concat lowering: one copy nest per input into its slab of the output.

An internal output follows the layout of the first runtime input (all-constant Concats are folded
at import, so there is one), so at least that copy is contiguous on both sides and vectorises; a
graph output is written row-major directly. An input whose producer wrote it straight into its slab
(see slabs.py) needs no copy."""

from __future__ import annotations

from ..ir.graph import ConcatAttrs, Node
from ..ir.loops import Affine, Load, Stmt, Store
from .context import LoweringContext
from .reshape import box_nest, copy_order


def lower_concat(ctx: LoweringContext, node: Node) -> None:
    attrs: ConcatAttrs = node.attrs
    value = node.outputs[0]
    first_runtime = next(ctx.ref(name) for name in node.inputs if not ctx.graph.is_constant(name))
    out = ctx.refs.get(value) or ctx.output(value, copy_order(ctx, value, first_runtime.order))
    body: list[Stmt] = []
    offset = 0
    for src in (ctx.ref(name) for name in node.inputs):
        if src.buffer == out.buffer:  # its producer wrote it in place
            offset += src.shape[attrs.axis]
            continue

        def copy(idx: list[Affine], src=src, offset=offset) -> Store:
            shifted = [i + offset if d == attrs.axis else i for d, i in enumerate(idx)]
            return Store(out.buffer, out.at(shifted), Load(src.buffer, src.at(idx)))

        body += box_nest(src.shape, out.order, copy, src.order)
        offset += src.shape[attrs.axis]
    if body:
        ctx.emit(node.name, node.op, tuple(body))
