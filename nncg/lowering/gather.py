"""Gather lowering (constant indices along one axis): one kernel of strided copies, one per run of
indices that step evenly (3, 4, 5 or 7, 7 or 6, 4, 2), each a box of the output. An internal output
keeps the input's layout, so a run of unit steps copies contiguously where the axis is not innermost."""

from __future__ import annotations

from ..ir.graph import GatherAttrs, Node
from ..ir.loops import Affine, Load, Stmt, Store
from .context import LoweringContext
from .reshape import box_nest, copy_order


def lower_gather(ctx: LoweringContext, node: Node) -> None:
    attrs: GatherAttrs = node.attrs
    axis = attrs.axis
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], copy_order(ctx, node.outputs[0], x.order))
    body: list[Stmt] = []
    for position, start, step, count in index_runs(attrs.indices):

        def copy(idx: list[Affine], position=position, start=start, step=step) -> Store:
            read = [i * step + start if d == axis else i for d, i in enumerate(idx)]
            written = [i + position if d == axis else i for d, i in enumerate(idx)]
            return Store(out.buffer, out.at(written), Load(x.buffer, x.at(read)))

        extents = tuple(count if d == axis else n for d, n in enumerate(out.shape))
        body += box_nest(extents, out.order, copy, x.order)
    ctx.emit(node.name, node.op, tuple(body))


def index_runs(indices: tuple[int, ...]) -> list[tuple[int, int, int, int]]:
    """(position in indices, first index, step, count) of each run of evenly stepping indices,
    left to right, each as long as it goes."""
    runs = []
    position = 0
    while position < len(indices):
        count, step = 1, 1
        if position + 1 < len(indices):
            step = indices[position + 1] - indices[position]
            count = 2
            while position + count < len(indices) and indices[position + count] - indices[position + count - 1] == step:
                count += 1
        runs.append((position, indices[position], step, count))
        position += count
    return runs
