"""Transpose lowering: a relabelling of dims, free where possible.

A TensorRef records the physical order of its logical dims, so the output can name the input's
buffer with its dims permuted: no element moves (e.g. NCHW -> NHWC of a channels-last conv output
is plain row-major memory). Only a graph output, which must be row-major, gets a copy kernel."""

from __future__ import annotations

from ..ir.graph import Node, TransposeAttrs
from ..ir.loops import Affine, Load, Store
from .context import LoweringContext, TensorRef, row_major
from .reshape import box_nest


def lower_transpose(ctx: LoweringContext, node: Node) -> None:
    attrs: TransposeAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    value = node.outputs[0]
    shape = ctx.graph.shape(value)
    position = {src: dst for dst, src in enumerate(attrs.perm)}  # output dim of each input dim
    x_order = tuple(position[d] for d in x.order)  # x's memory order in output dims
    if not ctx.graph.is_graph_output(value):
        ctx.refs[value] = TensorRef(x.buffer, shape, x_order)
        return
    out = ctx.output(value, row_major(len(shape)))

    def copy(idx: list[Affine]) -> Store:
        at = [Affine()] * len(idx)
        for dst, src in enumerate(attrs.perm):
            at[src] = idx[dst]
        return Store(out.buffer, out.at(idx), Load(x.buffer, x.at(at)))

    ctx.emit(node.name, node.op, box_nest(shape, out.order, copy, x_order))
