"""Reshape and Identity lowerings, the layout-converting copy for graph outputs, and the box
loop nest that the data-movement lowerings (Concat, Slice, Split, Pad, Transpose) build on.

A reshape keeps the row-major element order: when its input is already row-major it is free (the
output names the same buffer); otherwise a copy kernel writes the elements in row-major order."""

from __future__ import annotations

import itertools
from collections.abc import Callable

from ..ir.graph import Node
from ..ir.loops import Affine, Load, Stmt, Store
from .context import LoweringContext, TensorRef, dim_vars, nest, row_major


def lower_reshape(ctx: LoweringContext, node: Node) -> None:
    x = ctx.ref(node.inputs[0])
    value = node.outputs[0]
    shape = ctx.graph.shape(value)
    view = reshaped_view(x, shape)
    if view is not None and not ctx.graph.is_graph_output(value) and not ctx.graph.is_constant(node.inputs[0]):
        ctx.refs[value] = view
        return
    out = ctx.output(value, row_major(len(shape)))
    # The destination seen with the input's shape: same elements, same row-major order.
    ctx.emit(node.name, node.op, copy_nest(x, TensorRef(out.buffer, x.shape, row_major(len(x.shape)))))


def reshaped_view(x: TensorRef, shape: tuple[int, ...]) -> TensorRef | None:
    """x's buffer seen with `shape` when the reshape moves no element, else None. Split into groups of
    x's dims and the output dims they become (equal products), a reshape moves nothing when each
    group of x's dims lies together in memory, in order: then its output dims take its place."""
    if x.is_row_major:
        return TensorRef(x.buffer, shape, row_major(len(shape)))
    if x.halo:
        return None
    physical = [d for d in x.order if x.shape[d] != 1]
    groups = sorted(_reshape_groups(x.shape, shape), key=lambda group: physical.index(group[0][0]))
    if any(physical[physical.index(dims[0]) : physical.index(dims[0]) + len(dims)] != dims for dims, _ in groups):
        return None
    order = [d for _, dims in groups for d in dims]
    for d in (d for d, n in enumerate(shape) if n == 1):  # anywhere; after the dim before them
        order.insert(order.index(d - 1) + 1 if d else 0, d)
    return TensorRef(x.buffer, shape, tuple(order))


def _reshape_groups(src: tuple[int, ...], dst: tuple[int, ...]) -> list[tuple[list[int], list[int]]]:
    """The dims (other than size 1) of src and of dst paired into the smallest groups of equal
    element count, in row-major order: ([src dims], [dst dims]) each."""
    ins = [d for d, n in enumerate(src) if n != 1]
    outs = [d for d, n in enumerate(dst) if n != 1]
    groups = []
    i = j = 0
    while i < len(ins):
        group = ([ins[i]], [outs[j]])
        have, want = src[ins[i]], dst[outs[j]]
        i, j = i + 1, j + 1
        while have != want:
            if have < want:
                group[0].append(ins[i])
                have, i = have * src[ins[i]], i + 1
            else:
                group[1].append(outs[j])
                want, j = want * dst[outs[j]], j + 1
        groups.append(group)
    return groups


def copy_nest(src: TensorRef, dst: TensorRef) -> tuple[Stmt, ...]:
    """dst[idx] = src[idx] over the logical index space, in the destination's memory order."""

    def copy(idx: list[Affine]) -> Store:
        return Store(dst.buffer, dst.at(idx), Load(src.buffer, src.at(idx)))

    return box_nest(src.shape, dst.order, copy, src.order)


def copy_order(ctx: LoweringContext, value: str, order: tuple[int, ...]) -> tuple[int, ...]:
    """The layout a copying kernel writes `value` in: `order` (its input's) for an internal value;
    a graph output is row-major anyway, and writing it so directly saves the converting copy."""
    return row_major(len(order)) if ctx.graph.is_graph_output(value) else tuple(order)


# Elements per side of a layout-changing copy's tile. An 8x8 tile is unrolled whole (--unroll auto:
# TILE * TILE is AUTO_BUDGET) and the C compiler stores it as 8 row vectors; 16x16 stays scalar and
# was 3.5x slower (loaded, silu0 avx512). Other compilers (1x1 conv 16->96 on 48x48, loaded): clang 14
# makes scalar stores, 1.2-1.7x gcc's time on ssse3/avx2, still 2-3x faster than untiled; with only
# -mavx512f (generic tuning) it vectorises the loop over tiles with gathers and scatters, 5.7-7.7x gcc,
# no faster than untiled (-march=x86-64-v4 or skylake-avx512: no gathers). AArch64 gcc and clang copy
# a tile with scalar ldp/stp; int8 tiles: gcc packs a row into one 8-byte store, clang stores bytes.
TILE = 8


def box_nest(extents, order, stmt: Callable[[list[Affine]], Stmt], read_order=None) -> tuple[Stmt, ...]:
    """stmt(idx) for every logical index idx < extents, loops in `order` (outermost first; the
    destination's memory order keeps the innermost store contiguous). All loops are parallel.

    `read_order` is the memory order of the tensor stmt reads (logical dims of idx, outermost first).
    When its innermost dim differs from `order`'s, the loads would stride across a cache line per
    element; both innermost dims are then tiled (tiled_nest)."""
    names = dim_vars(len(extents))
    write, read = _innermost(extents, order), _innermost(extents, read_order or order)
    if write != read and write is not None and read is not None:
        return tiled_nest(extents, order, stmt, read, write)

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        return (stmt([env[v] for v in names]),)

    return nest([(names[d], extents[d]) for d in order], body, parallel=True)


def _innermost(extents, order) -> int | None:
    """The innermost dim of `order` with more than one element (None: there is none)."""
    return next((d for d in reversed(order) if extents[d] > 1), None)


def tiled_nest(extents, order, stmt: Callable[[list[Affine]], Stmt], read: int, write: int) -> tuple[Stmt, ...]:
    """box_nest's loops for a copy whose loads are contiguous along dim `read` and stores along dim
    `write`: the other dims in `order`, then TILE x TILE tiles of (read, write), so each tile reads
    and writes whole runs of cache lines that stay in L1. Where an extent is no multiple of TILE, a tail
    nest covers the rest (one nest per combination of whole tiles and tail over the two dims)."""
    names = dim_vars(len(extents))
    outer = [(names[d], extents[d]) for d in order if d not in (read, write)]

    def tiles(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        body: list[Stmt] = []
        for read_part, write_part in itertools.product(_tile_parts(extents[read]), _tile_parts(extents[write])):
            parts = {read: read_part, write: write_part}
            loops = [(names[d] + "t", parts[d][0]) for d in (read, write)]
            loops += [(names[d], parts[d][1]) for d in (read, write)]

            def element(inner: dict[str, Affine], parts=parts) -> tuple[Stmt, ...]:
                idx = [env.get(name, Affine()) for name in names]
                for d, (_, size, start) in parts.items():
                    idx[d] = inner[names[d] + "t"] * size + inner[names[d]] + start
                return (stmt(idx),)

            body += nest(loops, element, parallel=True)
        return tuple(body)

    return nest(outer, tiles, parallel=True)


def _tile_parts(extent: int) -> list[tuple[int, int, int]]:
    """(tiles, tile size, start) covering range(extent): the whole TILE-sized tiles, then the tail."""
    whole, tail = divmod(extent, TILE)
    if not whole:
        return [(1, extent, 0)]
    return [(whole, TILE, 0)] + ([(1, tail, whole * TILE)] if tail else [])
