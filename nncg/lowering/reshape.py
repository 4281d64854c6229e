"""Reshape and Identity lowerings, and the layout-converting copy for graph outputs.

A reshape keeps the row-major element order: when its input is already row-major it is free (the
output names the same buffer); otherwise a copy kernel writes the elements in row-major order."""

from __future__ import annotations

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
    names = dim_vars(len(src.shape))

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        idx = [env[v] for v in names]
        return (Store(dst.buffer, dst.at(idx), Load(src.buffer, src.at(idx))),)

    return nest([(names[d], src.shape[d]) for d in dst.order], body, parallel=True)
