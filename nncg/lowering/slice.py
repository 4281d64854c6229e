"""Slice and Split lowerings: strided copies of a box of the input.

Output element idx reads input element starts + steps * idx, affine in the loop variables (a
negative step is a negative coefficient). Internal outputs keep the input's layout, so a unit-step
copy is contiguous on both sides and vectorises; graph outputs are written row-major directly."""

from __future__ import annotations

from ..ir.graph import Node, SliceAttrs, SplitAttrs
from ..ir.loops import Affine, Load, Stmt, Store
from .context import LoweringContext, TensorRef
from .reshape import box_nest, copy_order


def lower_slice(ctx: LoweringContext, node: Node) -> None:
    attrs: SliceAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], copy_order(ctx, node.outputs[0], x.order))
    ctx.emit(node.name, node.op, strided_copy(x, out, attrs.starts, attrs.steps))


def lower_split(ctx: LoweringContext, node: Node) -> None:
    """All outputs in one kernel: each is a unit-step slice starting at its offset on the axis."""
    attrs: SplitAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    ones = (1,) * len(x.shape)
    body: list[Stmt] = []
    for value, start in zip(node.outputs, attrs.starts):
        out = ctx.output(value, copy_order(ctx, value, x.order))
        starts = tuple(start if d == attrs.axis else 0 for d in range(len(x.shape)))
        body += strided_copy(x, out, starts, ones)
    ctx.emit(node.name, node.op, tuple(body))


def strided_copy(src: TensorRef, dst: TensorRef, starts, steps) -> tuple[Stmt, ...]:
    """dst[idx] = src[starts + steps * idx] over dst's logical index space."""

    def copy(idx: list[Affine]) -> Store:
        at = [i * step + start for i, start, step in zip(idx, starts, steps)]
        return Store(dst.buffer, dst.at(idx), Load(src.buffer, src.at(at)))

    return box_nest(dst.shape, dst.order, copy, src.order)
