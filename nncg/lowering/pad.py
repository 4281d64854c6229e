"""Pad lowering (constant, reflect, edge, wrap; negative pads crop) without runtime branches.

Along each dim the output splits into up to three segments: the border before, the interior and
the border after. In every segment the input position is affine in the position within it
(interior: kept start + i; edge: a constant; reflect: a mirror, coefficient -1; wrap: a shifted
copy) or there is none (the constant border). Each box of the segments' cross product is one loop
nest, in the input's layout for an internal output, so the interior copy stays contiguous and
vectorises (a graph output is written row-major directly).

As in onnxruntime, negative pads crop first and the borders mirror, repeat or wrap the cropped
input."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

from ..ir.graph import Node, PadAttrs
from ..ir.loops import Affine, Const, Expr, Load, Stmt, Store
from .context import LoweringContext, TensorRef
from .reshape import box_nest, copy_order


@dataclass(frozen=True)
class Segment:
    """Output positions out_start + i for i < length read input position src_start + src_step * i,
    or the constant value when src_start is None."""

    out_start: int
    length: int
    src_start: int | None
    src_step: int = 1


def lower_pad(ctx: LoweringContext, node: Node) -> None:
    attrs: PadAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], copy_order(ctx, node.outputs[0], x.order))
    per_dim = [segments(n, b, e, attrs.mode) for n, b, e in zip(x.shape, attrs.pads_begin, attrs.pads_end)]
    dtype = ctx.graph.dtype(node.outputs[0])
    literal = Const.integer(int(attrs.value), dtype) if dtype.is_integer else Const.splat(attrs.value)
    value = Load(ctx.ref(node.inputs[1]).buffer, Affine()) if len(node.inputs) > 1 else literal
    body: list[Stmt] = []
    for box in itertools.product(*per_dim):
        reads = all(s.src_start is not None for s in box)
        body += box_nest([s.length for s in box], out.order, _filler(x, out, box, value), x.order if reads else None)
    ctx.emit(node.name, node.op, tuple(body))


def _filler(x: TensorRef, out: TensorRef, box: tuple[Segment, ...], value: Expr):
    """The store of one box: the constant value (a literal, or the load of the runtime scalar) if any
    dim is in a constant border, else a load."""

    def store(idx: list[Affine]) -> Store:
        at = out.at([i + s.out_start for i, s in zip(idx, box)])
        if any(s.src_start is None for s in box):
            return Store(out.buffer, at, value)
        src = [i * s.src_step + s.src_start for i, s in zip(idx, box)]
        return Store(out.buffer, at, Load(x.buffer, x.at(src)))

    return store


def segments(n: int, begin: int, end: int, mode: str) -> list[Segment]:
    """The segments of one dim of size n padded by begin/end (the front end checked that reflect
    and wrap borders do not exceed the cropped input)."""
    lo, hi = max(0, -begin), n - max(0, -end)  # the input range kept after cropping
    kept = hi - lo
    out: list[Segment] = []
    if begin > 0:
        source = {"constant": (None, 1), "edge": (lo, 0), "reflect": (lo + begin, -1), "wrap": (hi - begin, 1)}
        out.append(Segment(0, begin, *source[mode]))
    out.append(Segment(max(0, begin), kept, lo))
    if end > 0:
        source = {"constant": (None, 1), "edge": (hi - 1, 0), "reflect": (hi - 2, -1), "wrap": (lo, 1)}
        out.append(Segment(max(0, begin) + kept, end, *source[mode]))
    return out
