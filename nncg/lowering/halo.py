"""Zero halos: a tensor that only padded convolutions read is stored inside a border of zeros as
wide as their padding, so they read the border instead of checking bounds: no branch in the loop
nest, and the register-block pass jams every output pixel, the image's edges included. The producer
writes the inside; a small kernel before it zeroes the border, once per inference (the arena lends
the same memory to other buffers in between)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..ir.graph import Graph
from ..ir.loops import Affine, Const, Loop, Stmt, Store

if TYPE_CHECKING:  # context.py imports this module
    from .context import TensorRef

# Producers whose lowerings address their output only through TensorRef.at, so a halo, or a slab
# of a larger tensor (slabs.py), is invisible to them.
VIEW_WRITERS = ("Conv", "MaxPool", "AveragePool")
# A halo's readers must all be Convs, which treat it as their zero padding; a Concat's copies address
# its output through TensorRef.at too.
HALO_PRODUCERS = (*VIEW_WRITERS, "Concat")

Halo = tuple[tuple[int, int], ...]


def conv_halos(graph: Graph, blocked_only: bool = False) -> dict[str, Halo]:
    """Value -> its halo ((before, after) per logical dim) for every value worth one; with
    `blocked_only`, only for values whose padded readers are all cache-blocked Convs (where a border
    check costs most: on a small image every pixel is at the border, and the register block would be
    a single pixel)."""
    outputs = {v.name for v in graph.outputs}
    halos = {}
    for node in graph.nodes:
        if node.op not in HALO_PRODUCERS:
            continue
        for value in node.outputs:
            consumers = graph.consumers(value)
            if value in outputs or not consumers or any(c.op != "Conv" for c in consumers):
                continue
            readers = [c for c in consumers if c.inputs[0] == value]
            if blocked_only and not all(c.attrs.panel for c in readers if any(c.attrs.pads_begin + c.attrs.pads_end)):
                continue
            spatial = range(len(graph.shape(value)) - 2)
            before = [max((c.attrs.pads_begin[d] for c in readers), default=0) for d in spatial]
            after = [max((c.attrs.pads_end[d] for c in readers), default=0) for d in spatial]
            if any(before) or any(after):
                halos[value] = ((0, 0), (0, 0), *zip(before, after))
    return halos


def zero_halo(ref: TensorRef) -> tuple[Stmt, ...]:
    """Stores zeros over the halo of `ref`: per spatial dim d, the slabs before and after the inside
    along d, spanning the inside along the dims before d and everything along the dims after it."""
    stored = ref.stored_shape
    stmts: list[Stmt] = []
    for d in range(2, len(stored)):
        before, after = ref.halo[d]
        for start, count in ((0, before), (before + ref.shape[d], after)):
            if count == 0:
                continue
            ranges = [
                (start, count) if e == d else (ref.halo[e][0], ref.shape[e]) if 2 <= e < d else (0, stored[e])
                for e in range(len(stored))
            ]
            stmts += _zeros(ref, ranges)
    return tuple(stmts)


def _zeros(ref: TensorRef, ranges: list[tuple[int, int]]) -> tuple[Stmt, ...]:
    """Zeros over a box of stored coordinates [start, start + count) per dim, innermost dim last."""
    index = Affine()
    for d, (stride, (start, count)) in enumerate(zip(ref.strides, ranges)):
        index = index + ((Affine.of(f"z{d}") if count > 1 else Affine()) + start) * stride
    body: tuple[Stmt, ...] = (Store(ref.buffer, index, Const.splat(0.0)),)
    for d in reversed(ref.order):
        if ranges[d][1] > 1:
            body = (Loop(f"z{d}", ranges[d][1], body, parallel=True),)
    return body
