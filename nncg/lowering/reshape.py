"""Reshape and Identity lowerings, the layout-converting copy for graph outputs, and the box
loop nest that the data-movement lowerings (Concat, Slice, Split, Pad, Transpose) build on.

A reshape keeps the row-major element order: when its input is already row-major it is free (the
output names the same buffer); otherwise a copy kernel writes the elements in row-major order."""

from __future__ import annotations

from collections.abc import Callable

from ..ir.graph import Node
from ..ir.loops import Affine, Load, Stmt, Store
from .context import LoweringContext, TensorRef, dim_vars, nest, row_major


def lower_reshape(ctx: LoweringContext, node: Node) -> None:
    x = ctx.ref(node.inputs[0])
    value = node.outputs[0]
    shape = ctx.graph.shape(value)
    if x.is_row_major and not ctx.graph.is_graph_output(value) and not ctx.graph.is_constant(node.inputs[0]):
        ctx.refs[value] = TensorRef(x.buffer, shape, row_major(len(shape)))
        return
    out = ctx.output(value, row_major(len(shape)))
    # The destination seen with the input's shape: same elements, same row-major order.
    ctx.emit(node.name, node.op, copy_nest(x, TensorRef(out.buffer, x.shape, row_major(len(x.shape)))))


def copy_nest(src: TensorRef, dst: TensorRef) -> tuple[Stmt, ...]:
    """dst[idx] = src[idx] over the logical index space, in the destination's memory order."""
    return box_nest(src.shape, dst.order, lambda idx: Store(dst.buffer, dst.at(idx), Load(src.buffer, src.at(idx))))


def copy_order(ctx: LoweringContext, value: str, order: tuple[int, ...]) -> tuple[int, ...]:
    """The layout a copying kernel writes `value` in: `order` (its input's) for an internal value;
    a graph output is row-major anyway, and writing it so directly saves the converting copy."""
    return row_major(len(order)) if ctx.graph.is_graph_output(value) else tuple(order)


def box_nest(extents, order, stmt: Callable[[list[Affine]], Stmt]) -> tuple[Stmt, ...]:
    """stmt(idx) for every logical index idx < extents, loops in `order` (outermost first; the
    destination's memory order keeps the innermost store contiguous). All loops are parallel."""
    names = dim_vars(len(extents))

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        return (stmt([env[v] for v in names]),)

    return nest([(names[d], extents[d]) for d in order], body, parallel=True)
