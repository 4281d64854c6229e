"""Band lowering: a group of layers (bands.py) as one kernel, a loop over bands whose body runs each
layer's own loop nest over the rows that band computes.

A Winograd layer the group keeps (bands.py) is lowered over the band's 2-row tiles directly
(winograd.py lower_winograd_band, winograd_integer.py lower_integer_winograd_band); every other layer
is lowered as usual (direct convolution, channels last) and then rebanded: its output-row loop
becomes the band's rows of it (row = step * band + first, skipped outside the tensor), and every
access to a line buffer is moved by the buffer's origin, so the indices stay affine in the loop
variables: a line buffer's rows are shifted up by `step` before its producer writes the new ones
(an ascending copy; nothing when the readers need only the new rows, as a stride-2 pool's input),
instead of a ring whose index would need a modulo. The per-layer nests keep their shape, so
vectorize, register-block, unroll and the backends treat them as any other layer."""

from __future__ import annotations

from dataclasses import replace

from ..errors import NncgError
from ..ir.graph import ConvAttrs, Graph, Node
from ..ir.kinds import ConvAlgorithm, VectorAxis
from ..ir.loops import Affine, Bound, If, Load, Loop, Stmt, Store, map_body, map_stmt_exprs
from ..ir.rename import substitute_body
from .bands import POINTWISE, BandGroup, Geometry, Rows, geometry
from .context import LoweringContext, dim_vars
from .conv import lower_conv
from .pool import lower_averagepool
from .quantized import lower_any_maxpool, lower_banded_quantize_linear, lower_qlinear_average_pool, lower_qlinear_conv
from .quantized_add import lower_qlinear_add
from .quantized_lookup import lower_qlinear_lookup
from .winograd import TILE, lower_winograd_band
from .winograd_integer import lower_integer_winograd_band

BAND, SUB, ROW, SHIFT = "band", "sub", "row", "shift"
STAGE_LOWERINGS = {
    "Conv": lower_conv,
    "QLinearConv": lower_qlinear_conv,
    "MaxPool": lower_any_maxpool,
    "AveragePool": lower_averagepool,
    "QLinearAveragePool": lower_qlinear_average_pool,
    "QLinearLookup": lower_qlinear_lookup,
    "QLinearAdd": lower_qlinear_add,
    "QuantizeLinear": lower_banded_quantize_linear,  # into a line buffer's layout, channels last
}
ELEMENTWISE_ROW = dim_vars(4)[2]  # an elementwise nest's row loop (elementwise.py), channels last


def lower_band_group(ctx: LoweringContext, group: BandGroup) -> None:
    """Emits the group's kernel (after the zero halo of its output, if that has one)."""
    geo = geometry(ctx.graph, group)
    if geo is None:
        raise NncgError("the band plan names layers that cannot run in bands")
    by_name = {node.name: node for node in ctx.graph.nodes}
    ctx.written_as_is.add(geo.output)
    stages, helpers, scratch = [], [], {}
    for name in group.nodes:
        node = by_name[name]
        y = node.outputs[0]
        start = len(ctx.kernels)
        if name in geo.winograd:
            rows = geo.rows[y]
            lower_band = lower_integer_winograd_band if node.op == "QLinearConv" else lower_winograd_band
            lower_band(ctx, node, _first_tile_row(geo, rows), rows.step // TILE, scratch)
        else:
            STAGE_LOWERINGS[node.op](ctx, _direct(node))
        *helpers_now, stage = ctx.kernels[start:]
        del ctx.kernels[start:]
        helpers += helpers_now
        row_var = ELEMENTWISE_ROW if node.op in POINTWISE else "oh"
        height = ctx.graph.shape(y)[2]
        body = stage.body if name in geo.winograd else _banded(stage.body, geo.rows[y], geo, height, row_var)
        stages.append((y, body))
    strides = _line_buffers(ctx, geo)
    levels = []
    for y, stage in stages:
        level = geo.rows[y].level
        shift = _shift(ctx, y, geo.rows[y]) if y in geo.internal else ()
        levels.append((level, shift + _moved(stage, _moves(geo, level, strides))))
    ctx.kernels += helpers
    ctx.emit(group.nodes[0], "Band", (Loop(BAND, geo.bands, _nested(levels, geo.reps)),))


def _run(geo: Geometry, level: int) -> Affine:
    """The index of the current run of `level` (level 0: the band, from first_band)."""
    run = Affine.of(BAND) + geo.first_band
    for inner in range(1, level + 1):
        run = run * geo.reps[inner] + Affine.of(f"{SUB}{inner}")
    return run


def _nested(levels: list[tuple[int, tuple[Stmt, ...]]], reps: tuple[int, ...], level: int = 0) -> tuple[Stmt, ...]:
    """The stages' code, each run of a deeper level a loop inside the level outside it."""
    out: list[Stmt] = []
    i = 0
    while i < len(levels):
        j = i + 1
        if levels[i][0] == level:
            out += levels[i][1]
        else:
            while j < len(levels) and levels[j][0] > level:
                j += 1
            out.append(Loop(f"{SUB}{level + 1}", reps[level + 1], _nested(levels[i:j], reps, level + 1)))
        i = j
    return tuple(out)


def _first_tile_row(geo: Geometry, rows: Rows) -> Affine:
    """The first 2-row tile a Winograd layer's run computes (its step and ahead are even)."""
    return _run(geo, rows.level) * (rows.step // TILE) + (rows.ahead - rows.step) // TILE


def _direct(node: Node) -> Node:
    """A Conv as a direct, channels-last convolution: the form whose row loop bands (other choices
    of the graph passes, a cache-blocked layer's panels or depthwise channel blocks, or Winograd's
    tiles where the group does not keep them, do not apply)."""
    if not isinstance(node.attrs, ConvAttrs):
        return node
    direct = {"algorithm": ConvAlgorithm.DIRECT, "gemm_channels": 0, "panel": 0, "ci_block": 0, "channel_block": 0}
    return replace(node, attrs=replace(node.attrs, vector_axis=VectorAxis.CHANNELS, **direct))


def _banded(stage: tuple[Stmt, ...], rows: Rows, geo: Geometry, height: int, row_var: str) -> tuple[Stmt, ...]:
    """The layer's nest over one band: its output-row loop `row_var` becomes the band's rows."""
    if len(stage) != 1 or not isinstance(stage[0], Loop) or stage[0].var != row_var:
        raise NncgError("a banded layer's nest must start with its output-row loop")
    row = rows.first(_run(geo, rows.level)) + (Affine.of(ROW) if rows.step > 1 else 0)
    extents = {BAND: geo.bands, ROW: rows.step} | {f"{SUB}{i}": n for i, n in enumerate(geo.reps) if i}
    lo, hi = row.bounds(extents)
    bound = Bound(row, 0 if lo < 0 else None, height if hi >= height else None)
    body = substitute_body(stage[0].body, {row_var: row})
    if bound.lo is not None or bound.hi is not None:
        body = (If((bound,), body),)
    return (Loop(ROW, rows.step, body),) if rows.step > 1 else body


def _shift(ctx: LoweringContext, value: str, rows: Rows) -> tuple[Stmt, ...]:
    """Moves the line buffer's rows up by `step`, dropping the oldest: an ascending copy, each element
    read before the copy reaches it, in scalars or vectors alike (so vectorize may take the loop)."""
    ref = ctx.refs[value]
    kept = (rows.lines - rows.step) * ref.strides[2]
    if not kept:
        return ()
    at = Affine.of(SHIFT)
    moved = Store(ref.buffer, at, Load(ref.buffer, at + rows.step * ref.strides[2]))
    return (Loop(SHIFT, kept, (moved,), parallel=True),)


def _line_buffers(ctx: LoweringContext, geo: Geometry) -> dict[str, tuple[str, int]]:
    """Shrinks the buffers of the group's inner tensors to their lines; tensor -> (buffer, floats
    per row)."""
    strides = {}
    for value in geo.internal:
        ref = ctx.refs[value]
        if ref.halo or ref.order != (0, 2, 3, 1):
            raise NncgError("a tensor inside a band group is not stored channels last without a halo")
        strides[value] = (ref.buffer, ref.strides[2])
        _shrink(ctx, ref.buffer, geo.rows[value].lines)
    return strides


def _moves(geo: Geometry, level: int, strides: dict[str, tuple[str, int]]) -> dict[str, Affine]:
    """Buffer -> what moves an index of the whole tensor into its line buffer, for a stage of
    `level` (it reads a deeper level's tensor after that level's last run nested in its own)."""
    moves = {}
    for value, (buffer, stride) in strides.items():
        rows = geo.rows[value]
        if rows.level >= level:
            moves[buffer] = rows.origin(_run(geo, level), geo.runs(level, rows.level)) * -stride
    return moves


def _moved(body: tuple[Stmt, ...], moves: dict[str, Affine]) -> tuple[Stmt, ...]:
    def move_load(e):
        return replace(e, index=e.index + moves[e.buffer]) if isinstance(e, Load) and e.buffer in moves else e

    def move(stmt: Stmt) -> Stmt:
        stmt = map_stmt_exprs(stmt, move_load)
        if isinstance(stmt, Store) and stmt.buffer in moves:
            return replace(stmt, index=stmt.index + moves[stmt.buffer])
        return stmt

    return map_body(body, move)


def _shrink(ctx: LoweringContext, name: str, lines: int) -> None:
    for i, buf in enumerate(ctx.buffers):
        if buf.name == name:
            n, c, _, w = buf.shape
            ctx.buffers[i] = replace(buf, size=n * c * lines * w, shape=(n, c, lines, w))


def band_values(graph: Graph, groups: tuple[BandGroup, ...]) -> set[str]:
    """The tensors the groups produce: line buffers and the groups' outputs."""
    return {v for group in groups for v in geometry(graph, group).rows}
