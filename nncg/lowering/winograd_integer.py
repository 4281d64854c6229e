"""Integer Winograd F(2x2, 3x3) for QLinearConv (and the QDQ Convs the front end makes QLinearConv):
exact, so bit-identical to the direct integer kernel (quantized.py) and to onnxruntime.

The float transforms (winograd.py) have halves in G; with G' = 2G every operand is an integer:
  U' = G' g G'^T = 4 G g G^T      (compile time; |U'| <= 9 max|w| <= 2295: int16)
  V  = B^T (x - x_zero_point) B   (adds only; the padding reads nothing, as x - x_zero_point = 0
                                   there; |V| <= 4 * 255: int16)
  M  = sum over input channels of U' . V   (int32)
  Y' = A^T M A + 4 b = 4 (b + sum (x - x_zero_point) w)   (int32, exactly 4 times the direct sum)
and Y' is requantised with the multipliers divided by 4: float32(4 s) * (m / 4) is float32(s) * m to
the bit (scaling by a power of two is exact in float32, short of overflow and subnormals, which
integer_winograd_fits rules out), and in the fixed-point form m / 4 is the same significand with
the shift 2 larger. V's and M's scratch are int16 and int32 arena buffers (ir/arena.py keeps them
apart from the float ones). The nests are winograd.py's: tiles, chunks and border loops; a layer run
whole is chunked along its tile rows (winograd.WHOLE_CHUNKS), so its scratch is a few tiles'."""

from __future__ import annotations

import numpy as np

from ..ir.graph import Graph, Node, QConvAttrs
from ..ir.kinds import DType
from ..ir.loops import Affine, Binary, Cast, Const, Expr, Load
from .context import LoweringContext
from .quantized import centred
from .requantize import Scales
from .winograd import (
    BAND_CHUNKS,
    PATCH,
    SCRATCH_DTYPES,
    Chunking,
    WinogradNests,
    block_width,
    blocked_filters,
    emit_band,
    emit_layer,
    resolved_chunking,
    scratch_buffer,
)

G2 = np.array(((2, 0, 0), (1, 1, 1), (1, -1, 1), (0, 0, 2)), np.int64)  # 2G: integers
SCALE = 4  # Y' = SCALE * the direct sum (G' = 2G on both sides)
INT32_MAX = 2**31 - 1
WINOGRAD_OP = "QLinearConvWinograd"  # the kernel's op: not one the vectorize pass takes (its scratch is int16)


def integer_filters(w: np.ndarray) -> np.ndarray:
    """U'[e][ci][co] = (G' g G'^T)[e] of filter g = w[co, ci], as int16."""
    u = np.einsum("ak,oikl,bl->abio", G2, w.astype(np.int64), G2)
    return u.reshape(PATCH * PATCH, w.shape[1], w.shape[0]).astype(np.int16)


def integer_winograd_fits(graph: Graph, node: Node) -> bool:
    """Whether the arithmetic stays exact in the scratch's types: U' in int16 (weights within
    [-3640, 3640]: int8, or int16 minus a zero point), every M and Y' within int32 (bounded per output
    channel by the largest input deviation times the sum of |U'| over input channels and the 9
    products A^T M A adds), and the multipliers / 4 normal float32 values."""
    w = graph.constants[node.inputs[1]].astype(np.int64)
    u = np.abs(integer_filters(w).astype(np.int64)) if np.abs(w).max() * 9 <= 2**15 - 1 else None
    if u is None:
        return False
    low, high = graph.dtype(node.inputs[0]).range
    zx = node.attrs.x_zero_point
    deviation = PATCH * max(zx - low, high - zx)  # |V|
    bias = np.abs(graph.constants[node.inputs[2]].astype(np.int64))
    worst = 9 * deviation * u.max(axis=0).sum(axis=0) + SCALE * bias  # |Y'| per output channel
    multipliers = np.asarray(graph.constants[node.inputs[3]], np.float32).reshape(-1)
    quarter = multipliers / np.float32(SCALE)
    normal = bool(np.all((quarter == 0) | (np.abs(quarter) >= np.finfo(np.float32).tiny)))
    return int(worst.max()) <= INT32_MAX and deviation <= 2**15 - 1 and normal


class _IntegerLayer(WinogradNests):
    """One QLinearConv's Winograd nests in integers (the module's docstring)."""

    zero = Const.integer(0)

    def __init__(self, ctx: LoweringContext, node: Node, chunking: Chunking | None = None, shared: dict | None = None):
        attrs: QConvAttrs = node.attrs
        c_out = ctx.graph.shape(node.inputs[1])[0]
        block = block_width(c_out, c_out, resolved_chunking(node, chunking))
        self.u_blocked = block < c_out  # blocked_filters keeps a single block whole
        filters = blocked_filters(integer_filters(ctx.graph.constants[node.inputs[1]]), block)
        self.u = ctx.add_constant(f"u_{node.name}", filters)
        bias = ctx.graph.constants[node.inputs[2]].astype(np.int64) * SCALE
        self.bias = ctx.add_constant(f"b_{node.name}", bias.astype(np.int32))
        multipliers = np.asarray(ctx.graph.constants[node.inputs[3]], np.float32) / np.float32(SCALE)
        self.scales = Scales(ctx, node.name, multipliers)
        dtypes = dict(zip("vm", SCRATCH_DTYPES[node.op]))

        def scratch(name: str, shape: tuple[int, ...]):
            return scratch_buffer(ctx, name, shape, shared, dtypes[name[0]])

        super().__init__(ctx, node, c_out, chunking, scratch)
        self.zero_point = attrs.x_zero_point

    def input_value(self, load: Load) -> Expr:
        return centred(load, self.zero_point)

    def scratch_value(self, value: Expr) -> Expr:
        return Cast(DType.INT16, value)

    def product(self, v: Load, u: Load) -> Expr:
        return Binary("*", Cast(DType.INT32, v), Cast(DType.INT32, u))

    def output_value(self, value: Expr, channel, index) -> Expr:
        biased = Binary("+", value, Load(self.bias.buffer, self.bias.at([channel])))
        return self.scales.requantized(biased, channel, self.attrs.out)


def lower_integer_winograd(ctx: LoweringContext, node: Node) -> None:
    emit_layer(ctx, node, _IntegerLayer(ctx, node), WINOGRAD_OP)


def lower_integer_winograd_band(
    ctx: LoweringContext, node: Node, first_tile_row: Affine, tile_rows: int, scratch: dict[str, str]
) -> None:
    """As winograd.lower_winograd_band: the layer over a band's tile rows, its scratch the group's
    (int16 V and int32 M, apart from a float layer's)."""
    emit_band(ctx, node, _IntegerLayer(ctx, node, BAND_CHUNKS[node.op], scratch), first_tile_row, tile_rows)
