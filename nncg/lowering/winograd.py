"""Winograd F(2x2, 3x3) convolution (Lavin & Gray, 2015): 2.25x fewer multiplies than direct.

Each 2x2 block of outputs (a tile) comes from a 4x4 patch d of the input:
    Y = A^T [ (G g G^T) . (B^T d B) ] A
with g a 3x3 filter and `.` elementwise over the 16 positions e of the 4x4 Winograd domain. The
filters are transformed once, at compile time (U[e][ci][co]); at run time one kernel does three
nests in turn:
  1. input transform   V[e][t][ci] = (B^T d B)[e] for every tile t and input channel: adds only;
  2. 16 GEMMs           M[e][t][co] = sum_ci V[e][t][ci] * U[e][ci][co]: the multiplies, in the same
                        shape as a 1x1 convolution (tiles are its pixels), so vectorize and
                        register-block treat it like one;
  3. output transform  Y = A^T M A per tile and output channel, then bias, residual and activation
                        at the store, as the direct lowering does.
Channels are innermost everywhere, so every nest vectorises over them. Border tiles are cut into
their own loops where a patch row or column falls into the padding (those reads are zeros and are
left out of the sums) or where the tile's second output row or column lies past the output (not
stored), so the loops have no border checks. Multiplies per output: 16/4 * C_in instead of 9 * C_in."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from itertools import groupby

import numpy as np

from ..ir.graph import ConvAttrs, Graph, Node
from ..ir.kinds import DType
from ..ir.loops import (
    Affine,
    Assign,
    Binary,
    Bound,
    Const,
    Expr,
    If,
    Let,
    Load,
    LocalRef,
    Loop,
    Stmt,
    Store,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from .activation import apply_activation
from .context import LoweringContext, TensorRef, channels_last, nest, row_major
from .conv import conv_extras
from .weights import weight_operand

TILE, PATCH = 2, 4  # outputs per tile side, inputs per patch side
B_T = ((1, 0, -1, 0), (0, 1, 1, 0), (0, -1, 1, 0), (0, 1, 0, -1))
G = ((1.0, 0.0, 0.0), (0.5, 0.5, 0.5), (0.5, -0.5, 0.5), (0.0, 0.0, 1.0))
A_T = ((1, 1, 1, 0), (0, 1, -1, -1))
TILE_ROW = "tr"  # the loop over a band's (or a layer's) tile rows
SCRATCH_DTYPES = {"Conv": (DType.FLOAT32,) * 2, "QLinearConv": (DType.INT16, DType.INT32)}  # V's and M's


@dataclass(frozen=True)
class Chunking:
    """How the tiles are cut into chunks, the scratch one chunk's: at least `tiles` tiles in whole
    tile rows (`whole_rows`), or at most `tiles` along one tile row (a long row in parts). With
    `channels`, a chunk's GEMMs and output transform run that many output channels at a time (the
    last block the rest), so M holds one block: V is transformed once per chunk and read by every
    block, the multiplies are the same (0: all channels at once)."""

    tiles: int
    whole_rows: bool
    channels: int = 0


CHUNK_TILES = 24  # float: tiles per chunk, rounded up to whole tile rows: scratch that stays in L1
INTEGER_CHUNK_TILES = 1  # integer: tiles per chunk along a tile row (winograd_integer.py)
INTEGER_BLOCK = 8  # integer in bands: output channels per GEMM and output transform (an avx2 int32 vector)
WHOLE_CHUNKS = {"Conv": Chunking(CHUNK_TILES, True), "QLinearConv": Chunking(INTEGER_CHUNK_TILES, False)}
BAND_CHUNKS = {"Conv": Chunking(8, False), "QLinearConv": Chunking(INTEGER_CHUNK_TILES, False, INTEGER_BLOCK)}
BLOCK = "cb"  # the loop over a chunk's blocks of output channels
FLOAT_ZERO = Const.splat(0.0)
Scratch = Callable[[str, tuple[int, ...]], TensorRef]  # a scratch buffer of a name and shape


def transformed_filters(w: np.ndarray) -> np.ndarray:
    """U[e][ci][co] = (G g G^T)[e] of filter g = w[co, ci], computed in double precision."""
    g = np.asarray(G, dtype=np.float64)
    u = np.einsum("ak,oikl,bl->abio", g, w.astype(np.float64), g)
    return u.reshape(PATCH * PATCH, w.shape[1], w.shape[0]).astype(np.float32)


def lower_winograd(ctx: LoweringContext, node: Node) -> None:
    emit_layer(ctx, node, _Layer(ctx, node, None), "Conv")


def emit_layer(ctx: LoweringContext, node: Node, layer: WinogradNests, op: str) -> None:
    """The kernel of a layer run whole: its chunks of tiles (whole tile rows or parts of one), image
    after image."""
    batch, grid = layer.out.shape[0], layer.grid
    n = Affine.of("n") if batch > 1 else Affine()
    body = grid.chunks(n, layer.chunk) if grid.chunking.whole_rows else grid.row_chunks(n, layer.row_chunk)
    ctx.emit(node.name, op, (Loop("n", batch, body),) if batch > 1 else body)  # serial: shared scratch


def lower_winograd_band(
    ctx: LoweringContext, node: Node, first_tile_row: Affine, tile_rows: int, scratch: dict[str, str]
) -> None:
    """The layer's nest over `tile_rows` tile rows from `first_tile_row` (an affine in the band loops;
    rows outside the output are skipped), for a group of bands (stream.py): per tile row, chunks of
    BAND_CHUNKS along it, so its scratch is a band's, not the whole layer's. The layers of one group
    run one after the other and share their scratch: `scratch` names its buffers (filled in by the
    first)."""
    emit_band(ctx, node, _Layer(ctx, node, BAND_CHUNKS[node.op], scratch), first_tile_row, tile_rows)


def emit_band(ctx: LoweringContext, node: Node, layer: WinogradNests, first_tile_row: Affine, tile_rows: int) -> None:
    """The kernel of a layer in a group of bands (lower_winograd_band), whatever its arithmetic."""
    row = first_tile_row + Affine.of(TILE_ROW) if tile_rows > 1 else first_tile_row
    body = layer.grid.band_row(row, layer.row_chunk)
    ctx.emit(node.name, "Conv", (Loop(TILE_ROW, tile_rows, body),) if tile_rows > 1 else body)


class WinogradNests(ABC):
    """The three nests of a chunk of Winograd tiles, whatever the arithmetic: a subclass gives the
    scratch's type and fills in the values (input_value, scratch_value, multiply, output_value). The
    scratch holds a chunk of `chunking`, by default (None) the op's when run whole (WHOLE_CHUNKS)."""

    zero: Const = FLOAT_ZERO
    # U held as U[b][e][ci][c], in blocks of self.block output channels (blocked_filters), not U[e][ci][co]
    u_blocked = False

    def __init__(self, ctx: LoweringContext, node: Node, width: int, chunking: Chunking | None, scratch: Scratch):
        self.attrs = node.attrs
        self.x = ctx.ref(node.inputs[0])
        self.c_out, self.c_in = ctx.graph.shape(node.inputs[1])[:2]
        self.width = width
        self.out = ctx.output(node.outputs[0], channels_last(4))
        chunking = resolved_chunking(node, chunking)
        self.grid = TileGrid(self.out.shape[2:], self.attrs.pads_begin, self.x.spatial_ranges, chunking)
        v_shape, m_shape = scratch_shapes(self.out.shape[2:], self.c_in, self.c_out, width, chunking)
        self.block = m_shape[-1]
        self.v = scratch(f"v_{node.name}", v_shape)
        self.m = scratch(f"m_{node.name}", m_shape)

    def input_value(self, load: Load) -> Expr:
        """A patch value as the input transform sums it."""
        return load

    def scratch_value(self, value: Expr) -> Expr:
        """A transformed input value as V holds it."""
        return value

    @abstractmethod
    def output_value(self, value: Expr, channel: Affine, index: list[Affine]) -> Expr:
        """A tile's output (A^T M A) as the output holds it."""

    def transform_input(self, at: TileAt, rows, cols) -> tuple[Stmt, ...]:
        x, pads = self.x, self.attrs.pads_begin

        def patch(i: int, j: int) -> Expr | None:
            if not (rows[i] and cols[j]):
                return None
            h = at.row * TILE + (i - pads[0])
            w = at.col * TILE + (j - pads[1])
            return self.input_value(Load(x.buffer, x.at([at.n, at.channel, h, w])))

        # r = B^T d, row by row, in locals: each patch value is loaded once
        zero = self.zero
        r = {
            (a, j): combine(B_T[a], [patch(i, j) for i in range(PATCH)], zero)
            for a in range(PATCH)
            for j in range(PATCH)
        }
        v = self.v
        stores = tuple(
            Store(
                v.buffer,
                v.at([a * PATCH + b, at.tile, at.channel]),
                self.scratch_value(or_zero(combine(B_T[b], row, zero), zero)),
            )
            for a in range(PATCH)
            for b in range(PATCH)
            for row in [[local("r", r, (a, j)) for j in range(PATCH)]]
        )
        return with_locals("r", r, stores)

    def multiply(self, number: Affine, env: dict[str, Affine]) -> tuple[Stmt, ...]:
        """M of output channel co of block `number` (M's channel co); U blocked (u_blocked) or not."""
        e, t, co = env["e"], env["t"], env["co"]
        v, u, m = self.v, self.u, self.m
        ci = Affine.of("ci") if self.c_in > 1 else Affine()
        weight = u.at([number, e, ci, co]) if self.u_blocked else u.at([e, ci, number * self.block + co])
        product = self.product(Load(v.buffer, v.at([e, t, ci])), Load(u.buffer, weight))
        update = Assign("acc", Binary("+", LocalRef("acc"), product))
        reduction = (Loop("ci", self.c_in, (update,)),) if self.c_in > 1 else (Assign("acc", product),)
        return (Let("acc", self.zero, (*reduction, Store(m.buffer, m.at([e, t, co]), LocalRef("acc")))),)

    def product(self, v: Load, u: Load) -> Expr:
        """One term of a GEMM's sum over input channels."""
        return Binary("*", v, u)

    def transform_output(self, number: Affine, block_at: TileAt, rows, cols) -> tuple[Stmt, ...]:
        """The outputs of output channel block_at.channel of block `number` (M's channel that)."""
        m, out, zero = self.m, self.out, self.zero
        at = replace(block_at, channel=number * self.block + block_at.channel)

        def product(a: int, b: int) -> Expr:
            return Load(m.buffer, m.at([a * PATCH + b, at.tile, block_at.channel]))

        # s = A^T M for the rows that are stored, in locals: each product is loaded once
        kept_rows = [i for i in range(TILE) if rows[i]]
        s = {
            (i, b): combine(A_T[i], [product(a, b) for a in range(PATCH)], zero)
            for i in kept_rows
            for b in range(PATCH)
        }
        stores = []
        for i in kept_rows:
            for j in (j for j in range(TILE) if cols[j]):
                index = [at.n, at.channel, at.row * TILE + i, at.col * TILE + j]
                value = or_zero(combine(A_T[j], [local("s", s, (i, b)) for b in range(PATCH)], zero), zero)
                stores.append(Store(out.buffer, out.at(index), self.output_value(value, at.channel, index)))
        return with_locals("s", s, tuple(stores))

    def chunk(self, n: Affine, first_row: Affine, rows: tuple[RowKind, ...]) -> tuple[Stmt, ...]:
        grid, tiles = self.grid, len(rows) * self.grid.tiles[1]

        def block(number: Affine, width: int, stored: int) -> tuple[Stmt, ...]:
            writes = [kind.writes for kind in rows]
            return (
                *gemms(tiles, width, partial(self.multiply, number)),
                *grid.transform(n, first_row, writes, 1, ("co", stored), partial(self.transform_output, number)),
            )

        return (
            *grid.transform(n, first_row, [kind.reads for kind in rows], 0, ("ci", self.c_in), self.transform_input),
            *self.channel_blocks(block),
        )

    def row_chunk(self, at: TileAt, kind: RowKind, cols: tuple[RowKind, ...]) -> tuple[Stmt, ...]:
        """The nests of a chunk along one tile row: `at` gives its image, row and first column."""
        grid = self.grid

        def block(number: Affine, width: int, stored: int) -> tuple[Stmt, ...]:
            return (
                *gemms(len(cols), width, partial(self.multiply, number)),
                *grid.row_transform(at, kind.writes, cols, 1, ("co", stored), partial(self.transform_output, number)),
            )

        return (
            *grid.row_transform(at, kind.reads, cols, 0, ("ci", self.c_in), self.transform_input),
            *self.channel_blocks(block),
        )

    def channel_blocks(self, block: Callable[[Affine, int, int], tuple[Stmt, ...]]) -> tuple[Stmt, ...]:
        """block(block number, GEMM width, output channels stored) for every block of
        self.block channels of the GEMMs' width, the whole ones in one loop (serial: they share M),
        then the rest; of a padded GEMM (one block) only the channels below c_out are stored."""
        size, width, out = self.block, self.width, []
        whole, rest = divmod(width, size)
        if whole > 1:
            out.append(Loop(BLOCK, whole, block(Affine.of(BLOCK), size, size)))
        elif whole == 1:
            out.extend(block(Affine(), size, min(size, self.c_out)))
        if rest:
            out.extend(block(Affine.of(whole), rest, rest))
        return tuple(out)


class _Layer(WinogradNests):
    """One float Winograd Conv: transformed filters, bias, residual and activation at the store."""

    def __init__(
        self, ctx: LoweringContext, node: Node, chunking: Chunking | None, shared: dict[str, str] | None = None
    ):
        c_out = ctx.graph.shape(node.inputs[1])[0]
        width = gemm_width(ctx.graph, node)
        filters = transformed_filters(ctx.graph.constants[node.inputs[1]])
        filters = np.pad(filters, ((0, 0), (0, 0), (0, width - c_out)))  # padded channels compute zeros
        self.u = ctx.add_constant(f"u_{node.name}", filters)
        bias_name, residual_name = conv_extras(node)
        self.bias = weight_operand(ctx, bias_name, f"b_{node.name}") if bias_name else None
        self.residual = ctx.ref(residual_name) if residual_name else None
        super().__init__(ctx, node, width, chunking, lambda name, shape: scratch_buffer(ctx, name, shape, shared))

    def output_value(self, value: Expr, channel: Affine, index: list[Affine]) -> Expr:
        if self.bias:
            value = Binary("+", value, Load(self.bias.buffer, self.bias.at([channel])))
        if self.residual:
            value = Binary("+", value, Load(self.residual.buffer, self.residual.at(index)))
        return apply_activation(value, self.attrs.activation)


def scratch_buffer(
    ctx: LoweringContext,
    name: str,
    shape: tuple[int, ...],
    shared: dict[str, str] | None,
    dtype: DType = DType.FLOAT32,
) -> TensorRef:
    """A scratch buffer of `shape` and `dtype`; with `shared`, the one its first user of that dtype named
    (by the name's prefix), grown to the largest shape."""
    kind = f"{name[:2]}{dtype}"
    if shared is None or kind not in shared:
        ref = ctx.add_buffer(name, "internal", shape, row_major(len(shape)), dtype=dtype)
        if shared is not None:
            shared[kind] = ref.buffer
        return ref
    buffer = shared[kind]
    for i, buf in enumerate(ctx.buffers):
        if buf.name == buffer and buf.size < math.prod(shape):
            ctx.buffers[i] = replace(buf, size=math.prod(shape), shape=shape)
    return TensorRef(buffer, shape, row_major(len(shape)))


def gemms(count: int, c_out: int, multiply) -> tuple[Stmt, ...]:
    """for e { for t [parallel] { for co [parallel] { multiply } } }. The loop over the 16 GEMMs is
    not marked parallel, though it is: register blocking across it would reuse no operand (each
    GEMM has its own inputs and weights), so it blocks tiles x output channels instead."""
    (loop,) = nest([("e", PATCH * PATCH), ("t", count), ("co", c_out)], multiply, parallel=True)
    return (replace(loop, parallel=False),)


# ---------------------------------------------------------------------------- tiles and chunks


@dataclass(frozen=True)
class RowKind:
    """Which patch rows of a tile row lie in the readable input, which output rows in the output."""

    reads: tuple[bool, ...]
    writes: tuple[bool, ...]


@dataclass(frozen=True)
class TileAt:
    """Where a transform is: image n, tile row and column, the tile's index in the chunk's scratch,
    the channel."""

    n: Affine
    row: Affine
    col: Affine
    tile: Affine
    channel: Affine


def resolved_chunking(node: Node, chunking: Chunking | None = None) -> Chunking:
    """The chunking a layer's nests run: `chunking`, or the op's when run whole (WHOLE_CHUNKS)."""
    return chunking or WHOLE_CHUNKS[node.op]


def scratch_bytes(graph: Graph, node: Node) -> int:
    """The bytes of a Winograd layer's two scratch buffers run whole (resolved_chunking: what the
    nests allocate, and what the band planner counts)."""
    return sum(_scratch_sizes(graph, node, resolved_chunking(node)))


def _scratch_sizes(graph: Graph, node: Node, chunking: Chunking) -> tuple[int, int]:
    """The bytes of V and M of a chunk of `chunking`, each in its SCRATCH_DTYPES type."""
    c_out, c_in = graph.shape(node.inputs[1])[:2]
    shapes = scratch_shapes(graph.shape(node.outputs[0])[2:], c_in, c_out, gemm_width(graph, node), chunking)
    return tuple(math.prod(shape) * dtype.bytes for shape, dtype in zip(shapes, SCRATCH_DTYPES[node.op]))


def scratch_shapes(
    out_hw: tuple[int, int], c_in: int, c_out: int, width: int, chunking: Chunking
) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """The shapes of V (input channels) and M (a block of the GEMMs' `width` output channels) for a
    chunk of `chunking`'s tiles (chunk_tiles, as TileGrid walks them): what WinogradNests allocates
    and the band planner counts."""
    tiles = chunk_tiles(out_hw, chunking)[1]
    return (PATCH * PATCH, tiles, c_in), (PATCH * PATCH, tiles, block_width(width, c_out, chunking))


def gemm_width(graph: Graph, node: Node) -> int:
    """The output channels a Winograd layer's GEMMs compute: a float layer's padded to its
    gemm_channels, an integer one's its own."""
    c_out = graph.shape(node.inputs[1])[0]
    return max(c_out, node.attrs.gemm_channels) if isinstance(node.attrs, ConvAttrs) else c_out


def blocked_filters(u: np.ndarray, block: int) -> np.ndarray:
    """U[e][ci][co] as U[b][e][ci][c] (co = b * block + c; the last block padded with zeros) where
    `block` cuts its output channels in blocks, so a block's GEMMs read whole cache lines of it."""
    e, c_in, c_out = u.shape
    if block >= c_out:
        return u
    count = -(-c_out // block)
    padded = np.pad(u, ((0, 0), (0, 0), (0, count * block - c_out)))
    return np.ascontiguousarray(padded.reshape(e, c_in, count, block).transpose(2, 0, 1, 3))


def block_width(width: int, c_out: int, chunking: Chunking) -> int:
    """The output channels that M holds at a time (Chunking.channels) of a GEMM of `width` channels,
    all of them where width pads c_out (float's gemm_channels)."""
    return min(chunking.channels, width) if chunking.channels and width == c_out else width


def tile_count(size: int) -> int:
    """The 2x2 tiles along an output side of `size`."""
    return -(-size // TILE)


def chunk_tiles(out_hw: tuple[int, int], chunking: Chunking) -> tuple[int, int]:
    """Tile rows per chunk and tiles per chunk: at least chunking.tiles in whole tile rows, or at
    most that along one tile row."""
    tiles = [tile_count(size) for size in out_hw]
    if not chunking.whole_rows:
        return 1, min(chunking.tiles, tiles[1])
    rows = max(1, min(tiles[0], -(-chunking.tiles // tiles[1])))
    return rows, rows * tiles[1]


def band_scratch_bytes(graph: Graph, nodes: list[Node]) -> int:
    """The bytes of the scratch the Winograd layers of one band group share: of each buffer and type
    (a float layer's and an integer one's are apart: scratch_buffer), the largest."""
    largest: dict[tuple[int, DType], int] = {}
    for node in nodes:
        sizes = _scratch_sizes(graph, node, BAND_CHUNKS[node.op])
        for key, size in zip(enumerate(SCRATCH_DTYPES[node.op]), sizes):
            largest[key] = max(largest.get(key, 0), size)
    return sum(largest.values())


class TileGrid:
    """The output's 2x2 tiles, taken a chunk (`chunking`) at a time, so the scratch of the transforms
    and GEMMs stays small and in cache. Tiles whose patch reaches into the padding or whose outputs
    reach past the output get loops of their own (see RowKind), so no loop has a border check."""

    def __init__(
        self, out_hw: tuple[int, int], pads: tuple[int, ...], readable: list[tuple[int, int]], chunking: Chunking
    ):
        self.out_hw, self.pads, self.readable, self.chunking = out_hw, pads, readable, chunking
        self.tiles = tuple(tile_count(size) for size in out_hw)
        self.rows_per_chunk, self.chunk_tiles = chunk_tiles(out_hw, chunking)
        self.col_kinds = [self.kind(1, t) for t in range(self.tiles[1])]

    def kind(self, dim: int, t: int) -> RowKind:
        lo, hi = self.readable[dim]
        reads = tuple(lo <= t * TILE + i - self.pads[dim] < hi for i in range(PATCH))
        return RowKind(reads, tuple(t * TILE + i < self.out_hw[dim] for i in range(TILE)))

    def chunks(self, n: Affine, chunk) -> tuple[Stmt, ...]:
        """chunk(n, first tile row, kinds of its rows) for every chunk; runs of chunks whose rows are
        alike share one loop (serial: the chunks share the scratch)."""
        size, out = self.rows_per_chunk, []
        rows = range(self.tiles[0])
        kinds = [tuple(self.kind(0, r) for r in rows[k : k + size]) for k in range(0, len(rows), size)]
        for start, stop, rows in runs(len(kinds), kinds.__getitem__):
            if stop - start == 1:
                out.extend(chunk(n, Affine.of(start * size), rows))
            else:
                first_row = (Affine.of("tc") + start) * size
                out.append(Loop("tc", stop - start, chunk(n, first_row, rows)))
        return tuple(out)

    def band_row(self, row: Affine, chunk) -> tuple[Stmt, ...]:
        """along_row's chunks of the tile row `row` (an affine of the band loops): one guarded copy
        per run of alike tile rows, as which row a band reaches is known only at run time (rows
        outside the output: none)."""
        return tuple(
            If((Bound(row, start, stop),), self.along_row(Affine(), row, kind, chunk))
            for start, stop, kind in runs(self.tiles[0], lambda r: self.kind(0, r))
        )

    def row_chunks(self, n: Affine, chunk) -> tuple[Stmt, ...]:
        """along_row's chunks of every tile row of image n, one loop per run of alike tile rows
        (serial: the chunks share the scratch)."""
        out: list[Stmt] = []
        for start, stop, kind in runs(self.tiles[0], lambda r: self.kind(0, r)):
            if stop - start == 1:
                out.extend(self.along_row(n, Affine.of(start), kind, chunk))
            else:
                out.append(Loop(TILE_ROW, stop - start, self.along_row(n, Affine.of(TILE_ROW) + start, kind, chunk)))
        return tuple(out)

    def along_row(self, n: Affine, row: Affine, kind: RowKind, chunk) -> tuple[Stmt, ...]:
        """chunk(TileAt of its first tile, the row's kind, kinds of its columns) for every chunk of
        chunk_tiles tiles along tile row `row`; runs of alike chunks share one loop."""
        size, out = self.chunk_tiles, []
        kinds = [tuple(self.col_kinds[k : k + size]) for k in range(0, self.tiles[1], size)]
        for start, stop, cols in runs(len(kinds), kinds.__getitem__):
            if stop - start == 1:
                out.extend(chunk(TileAt(n, row, Affine.of(start * size), Affine(), Affine()), kind, cols))
            else:
                first_col = (Affine.of("tk") + start) * size
                out.append(Loop("tk", stop - start, chunk(TileAt(n, row, first_col, Affine(), Affine()), kind, cols)))
        return tuple(out)

    def row_transform(self, first: TileAt, row_flags, cols, side, channel, body) -> tuple[Stmt, ...]:
        """body(TileAt, row flags, column flags) over a chunk along a tile row (image, row and first
        column of `first`) and its channels, one loop nest per run of alike columns."""
        flags = [(kind.reads, kind.writes)[side] for kind in cols]
        out: list[Stmt] = []
        for col_start, col_stop, col_flags in runs(len(flags), flags.__getitem__):
            loops = [("tw", col_stop - col_start), channel]

            def inner(env, col_start=col_start, col_flags=col_flags):
                tile = env["tw"] + col_start
                at = TileAt(first.n, first.row, first.col + tile, tile, env[channel[0]])
                return body(at, row_flags, col_flags)

            out.extend(nest(loops, inner, parallel=True))
        return tuple(out)

    def transform(self, n, first_row, rows, side, channel, body) -> tuple[Stmt, ...]:
        """body(TileAt, row flags, column flags) over a chunk's tiles and channels, one loop nest per
        run of alike rows x run of alike columns; side 0 is the input's flags, 1 the output's."""
        cols = [(kind.reads, kind.writes)[side] for kind in self.col_kinds]
        out: list[Stmt] = []
        for row_start, row_stop, row_flags in runs(len(rows), rows.__getitem__):
            for col_start, col_stop, col_flags in runs(len(cols), cols.__getitem__):
                loops = [("i", row_stop - row_start), ("tw", col_stop - col_start), channel]

                def inner(env, row_start=row_start, col_start=col_start, flags=(row_flags, col_flags)):
                    i, col = env["i"] + row_start, env["tw"] + col_start
                    at = TileAt(n, first_row + i, col, i * self.tiles[1] + col, env[channel[0]])
                    return body(at, *flags)

                out.extend(nest(loops, inner, parallel=True))
        return tuple(out)


def runs(count: int, key) -> list[tuple[int, int, object]]:
    """[start, stop, key] of the runs of consecutive indices in range(count) with equal key."""
    out, start = [], 0
    for value, group in groupby(range(count), key=key):
        stop = start + len(list(group))
        out.append((start, stop, value))
        start = stop
    return out


# ---------------------------------------------------------------------------- expressions


def combine(coeffs: tuple[int, ...], terms: list[Expr | None], zero: Const = FLOAT_ZERO) -> Expr | None:
    """sum(c * term) for coefficients in {-1, 0, 1}; None terms are zeros (`zero` in the terms' type);
    None if nothing is left."""
    plus = [t for c, t in zip(coeffs, terms) if c == 1 and t is not None]
    minus = [t for c, t in zip(coeffs, terms) if c == -1 and t is not None]
    if not plus and not minus:
        return None
    value = plus[0] if plus else Binary("-", zero, minus.pop(0))
    for t in plus[1:]:
        value = Binary("+", value, t)
    for t in minus:
        value = Binary("-", value, t)
    return value


def or_zero(value: Expr | None, zero: Const = FLOAT_ZERO) -> Expr:
    return zero if value is None else value


def local_name(prefix: str, key: tuple[int, int]) -> str:
    return f"{prefix}{key[0]}{key[1]}"


def local(prefix: str, values: dict[tuple[int, int], Expr | None], key: tuple[int, int]) -> Expr | None:
    """The local holding values[key], or None when that value is zero."""
    return None if values[key] is None else LocalRef(local_name(prefix, key))


def with_locals(prefix: str, values: dict[tuple[int, int], Expr | None], body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    """body inside one Let per non-zero value it uses."""
    exprs = (e for stmt in walk_stmts(body) for top in stmt_exprs(stmt) for e in walk_exprs(top))
    used = {e.name for e in exprs if isinstance(e, LocalRef)}
    for key in reversed(list(values)):
        if values[key] is not None and local_name(prefix, key) in used:
            body = (Let(local_name(prefix, key), values[key], body),)
    return body
