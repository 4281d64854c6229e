"""Lowering of the int8 path: integer Conv, matrix product and global average pool (int32
accumulators in locals, requantised at the store: requantize.py), QuantizeLinear and
DequantizeLinear, and MaxPool of integers. Every integer load is widened to int32 before any
arithmetic, so no product or sum wraps; int32 values never leave the kernel (the arena holds 8-bit
values only, see backends/c_file.py)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..ir.graph import (
    IntegerConvAttrs,
    IntegerDenseAttrs,
    Node,
    QAveragePoolAttrs,
    QConvAttrs,
    QDenseAttrs,
    QPoolAttrs,
    QuantAttrs,
)
from ..ir.kinds import DType
from ..ir.loops import Affine, Assign, Binary, Cast, Const, Expr, Let, Load, LocalRef, Loop, Requantize, Stmt, Store
from .context import LoweringContext, TensorRef, channels_last, nest, row_major
from .elementwise import elementwise
from .pool import lower_maxpool, window_counts
from .requantize import Scales
from .reshape import reshaped_view
from .window import outside_window_nest, spatial_names, window_nest

INT32, FLOAT32, FLOAT64 = DType.INT32, DType.FLOAT32, DType.FLOAT64
FOLD_MIN_CHANNELS = 4


def centred(value: Expr, zero_point: int = 0) -> Expr:
    """An 8-bit value as int32, minus its zero point."""
    widened_value: Expr = Cast(INT32, value)
    return Binary("-", widened_value, Const.integer(zero_point)) if zero_point else widened_value


def widened(ref: TensorRef, index, zero_point: int = 0) -> Expr:
    """ref[index] as int32, minus its zero point."""
    return centred(Load(ref.buffer, ref.at(index)), zero_point)


def accumulate(product: Expr) -> Assign:
    return Assign("acc", Binary("+", LocalRef("acc"), product))


def folded_bias(bias: np.ndarray, x_zero_point: int, weight_sums: np.ndarray) -> np.ndarray | None:
    """b - x_zero_point * sum(w) per output channel: sum (x - zx) * w = sum x * w - zx * sum w, so the
    zero point costs nothing per tap. None where the folded bias leaves int32 (then it is not folded)."""
    folded = bias.astype(np.int64) - int(x_zero_point) * weight_sums.astype(np.int64)
    info = np.iinfo(np.int32)
    return folded.astype(np.int32) if folded.min() >= info.min and folded.max() <= info.max else None


# What an integer kernel stores: the int32 sum of an output channel, as the output's type.
Finish = Callable[[Expr, Affine], Expr]


def lower_qlinear_conv(ctx: LoweringContext, node: Node) -> None:
    scales = Scales(ctx, node.name, ctx.graph.constants[node.inputs[3]])
    integer_conv(ctx, node, lambda acc, co: scales.requantized(acc, co, node.attrs.out))


def integer_conv(ctx: LoweringContext, node: Node, finish: Finish) -> None:
    """As lower_conv (conv.py), in integers, each sum stored as `finish` makes it. A tap outside the
    image reads the zero point (x - x_zero_point = 0). The zero point is folded into the bias
    (folded_bias) for every tap; the taps outside the image then add back x_zero_point *
    sum_ci w[tap, ci, co], a constant per tap (a dense Conv of 2 or more input channels, or at least
    FOLD_MIN_CHANNELS per group)."""
    attrs: QConvAttrs | IntegerConvAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    rank = len(attrs.kernel)
    weights = ctx.graph.constants[node.inputs[1]]  # [c_out, c_in/group, k...] -> [k..., c_in/group, c_out]
    c_out, c_in = weights.shape[:2]
    c_out_g = c_out // attrs.group
    packed = np.transpose(weights, (*range(2, rank + 2), 1, 0))
    w = ctx.add_constant(f"w_{node.name}", packed)
    zx = attrs.x_zero_point
    tap_sums = packed.astype(np.int64).sum(axis=rank)  # [k..., c_out]
    # the border table holds an int32 per tap and output channel, no more than the int8 weights from
    # FOLD_MIN_CHANNELS input channels on. A first layer's 2 or 3 channels fold too: its dots then take
    # uint8 quads (vpdpbusd) instead of signed pairs, resnet8's stem 3x faster for a table of under 1 KB.
    # A depthwise's (one channel per group) and a one-channel stem's taps are the dots (tap_dots): those
    # keep x - zero point (folding dscnn's 10x4 stem made it slower).
    fold = zx and (c_in >= FOLD_MIN_CHANNELS or (attrs.group == 1 and c_in > 1))
    b = ctx.graph.constants[node.inputs[2]]
    folded = folded_bias(b, zx, tap_sums.sum(axis=tuple(range(rank)))) if fold else None
    bias = ctx.add_constant(f"b_{node.name}", b if folded is None else folded)
    border = ctx.add_constant(f"zw_{node.name}", (zx * tap_sums).astype(np.int32)) if folded is not None else None
    x_zero_point = 0 if folded is not None else zx
    out = ctx.output(node.outputs[0], channels_last(rank + 2))
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, co = env["n"], env["g"] * c_out_g + env["co"]
        ci = Affine.of("ci") if c_in > 1 else Affine()

        def tap(positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            x_value = widened(x, [n, env["g"] * c_in + ci, *positions], x_zero_point)
            update = (accumulate(Binary("*", x_value, widened(w, [*k_vars, ci, co]))),)
            return (Loop("ci", c_in, update),) if c_in > 1 else update

        def outside_tap(_positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            return (accumulate(Load(border.buffer, border.at([*k_vars, co]))),)

        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        if border is not None:
            window += outside_window_nest(attrs, env, dict(out_loops), x.spatial_ranges, outside_tap)
        index = [n, co, *(env["o" + s] for s in names)]
        store = Store(out.buffer, out.at(index), finish(LocalRef("acc"), co))
        return (Let("acc", Load(bias.buffer, bias.at([co])), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("g", attrs.group), ("co", c_out_g)]
    ctx.emit(node.name, node.op, nest(loops, body, parallel=True))


def lower_qlinear_dense(ctx: LoweringContext, node: Node) -> None:
    scales = Scales(ctx, node.name, ctx.graph.constants[node.inputs[3]])
    integer_dense(ctx, node, lambda acc, n: scales.requantized(acc, n, node.attrs.out))


def integer_dense(ctx: LoweringContext, node: Node, finish: Finish) -> None:
    """y[m, n] = finish(b[n] + sum_k (x[m, k] - x_zero_point) * w[k, n]), the zero point folded
    into the bias (folded_bias); a y of another rank (a batched MatMulInteger's) is seen as [M, N]."""
    attrs: QDenseAttrs | IntegerDenseAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    weights = ctx.graph.constants[node.inputs[1]]
    w = ctx.add_constant(f"w_{node.name}", weights)
    b = ctx.graph.constants[node.inputs[2]]
    folded = folded_bias(b, attrs.x_zero_point, weights.astype(np.int64).sum(axis=0)) if attrs.x_zero_point else None
    bias = ctx.add_constant(f"b_{node.name}", b if folded is None else folded)
    x_zero_point = attrs.x_zero_point if folded is None else 0
    y_shape, matrix = ctx.graph.shape(node.outputs[0]), (x.shape[0], w.shape[1])
    out = ctx.output(node.outputs[0], row_major(len(y_shape)))
    out = out if y_shape == matrix else reshaped_view(out, matrix)
    k = w.shape[0]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        m, n = env["m"], env["n"]
        kk = Affine.of("k") if k > 1 else Affine()
        update = (accumulate(Binary("*", widened(x, [m, kk], x_zero_point), widened(w, [kk, n]))),)
        reduce = (Loop("k", k, update),) if k > 1 else update
        store = Store(out.buffer, out.at([m, n]), finish(LocalRef("acc"), n))
        return (Let("acc", Load(bias.buffer, bias.at([n])), (*reduce, store)),)

    ctx.emit(node.name, node.op, nest([("m", out.shape[0]), ("n", out.shape[1])], body, parallel=True))


def lower_qlinear_global_average_pool(ctx: LoweringContext, node: Node) -> None:
    """The int32 sum of each channel, biased by -count * x_zero_point, times x_scale / (y_scale *
    count), as onnxruntime's QLinearGlobalAveragePool (MLAS) computes it."""
    attrs: QPoolAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    spatial = x.shape[2:]
    count = math.prod(spatial)
    scale = np.float32(attrs.x_scale) / (np.float32(attrs.y_scale) * np.float32(count))
    scales = Scales(ctx, node.name, np.array([scale], np.float32))
    out = ctx.output(node.outputs[0], channels_last(len(x.shape)))
    taps = [(f"i{d}", extent) for d, extent in enumerate(spatial)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, c = env["n"], env["c"]

        def tap(position: dict[str, Affine]) -> tuple[Stmt, ...]:
            return (accumulate(widened(x, [n, c, *(position[v] for v, _ in taps)])),)

        index = [n, c, *[0] * len(spatial)]
        store = Store(out.buffer, out.at(index), scales.requantized(LocalRef("acc"), c, attrs.out))
        return (Let("acc", Const.integer(-count * attrs.x_zero_point), (*nest(taps, tap, parallel=False), store)),)

    ctx.emit(node.name, "QLinearGlobalAveragePool", nest([("n", x.shape[0]), ("c", x.shape[1])], body, parallel=True))


def lower_qlinear_average_pool(ctx: LoweringContext, node: Node) -> None:
    """As onnxruntime's QLinearAveragePool: the float32 sum, in tap order, of x_scale * (x - x_zp)
    over the taps inside the input, divided by the window's count (window_counts), then
    sum / y_scale + y_zp rounded half to even and saturated. Each product is spelled in double
    (exact: 24 by 9 bits) and rounded to float32, so no C compiler can contract it into the sum
    (GCC does in GNU mode, clang by default), which onnxruntime rounds twice."""
    attrs: QAveragePoolAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    rank = len(attrs.pool.kernel)
    out = ctx.output(node.outputs[0], channels_last(rank + 2))
    counts = window_counts(attrs.pool, x.shape[2:], out.shape[2:]).astype(np.float32)
    uniform = bool(np.all(counts == counts.flat[0]))
    count_ref = None if uniform else ctx.add_constant(f"count_{node.name}", counts)
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def tap(positions: list[Affine], _k: list[Affine]) -> tuple[Stmt, ...]:
            difference = Cast(FLOAT64, widened(x, [env["n"], env["c"], *positions], attrs.x_zero_point))
            product = Binary("*", difference, Const((float(np.float32(attrs.x_scale)),), FLOAT64))
            return (accumulate(Cast(FLOAT32, product)),)

        window = window_nest(attrs.pool, env, dict(out_loops), x.spatial_ranges, tap)
        spatial = [env["o" + s] for s in names]
        count = Const.splat(float(counts.flat[0])) if uniform else Load(count_ref.buffer, count_ref.at(spatial))
        mean = Binary("/", LocalRef("acc"), count)
        offset = attrs.zero_point_offset
        zero_point = Const.splat(float(attrs.out.zero_point + offset))
        value = Binary("+", Binary("/", mean, Const.splat(attrs.y_scale)), zero_point)
        requantized = Requantize(value, -offset, attrs.out.low, attrs.out.high, attrs.out.dtype)
        store = Store(out.buffer, out.at([env["n"], env["c"], *spatial]), requantized)
        return (Let("acc", Const.splat(0.0), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("c", out.shape[1])]
    ctx.emit(node.name, "QLinearAveragePool", nest(loops, body, parallel=True))


def lower_quantize_linear(ctx: LoweringContext, node: Node, order: tuple[int, ...] | None = None) -> None:
    """QuantizeLinear as onnxruntime computes it: x / scale, clamped, rounded half to even, plus the
    zero point (MLAS's MlasQuantizeLinear); the output in `order` (None: the input's)."""
    x = ctx.ref(node.inputs[0])
    elementwise(ctx, node, x.order if order is None else order, lambda idx: _quantized(node.attrs, x, idx))


def lower_banded_quantize_linear(ctx: LoweringContext, node: Node) -> None:
    """QuantizeLinear of a planar (N = 1) image into a line buffer, channels last (lowering/stream.py),
    a row at a time: quantised along the row into a planar scratch row, contiguous on both sides like
    the nest of the layer run whole (vectorize.py takes it), then interleaved into the line buffer, a
    byte copy per element, instead of a quotient and a rounding per element at a stride of C."""
    attrs: QuantAttrs = node.attrs
    _, channels, height, width = ctx.graph.shape(node.outputs[0])
    if channels == 1:  # channels last is planar
        lower_quantize_linear(ctx, node, channels_last(4))
        return
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], channels_last(4))
    row = ctx.add_buffer(f"row_{node.name}", "internal", (channels, width), row_major(2), dtype=attrs.dtype)

    def per_row(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def quantized(inner: dict[str, Affine]) -> tuple[Stmt, ...]:
            c, w = inner["c"], inner["w"]
            return (Store(row.buffer, row.at([c, w]), _quantized(attrs, x, [Affine(), c, env["h"], w])),)

        def interleaved(inner: dict[str, Affine]) -> tuple[Stmt, ...]:
            c, w = inner["c"], inner["w"]
            return (Store(out.buffer, out.at([Affine(), c, env["h"], w]), Load(row.buffer, row.at([c, w]))),)

        planar, last = [("c", channels), ("w", width)], [("w", width), ("c", channels)]
        return (*nest(planar, quantized, parallel=True), *nest(last, interleaved, parallel=True))

    # the row loop is serial: its iterations share the scratch row
    ctx.emit(node.name, node.op, (Loop("h", height, per_row({"h": Affine.of("h")})),))


def _quantized(attrs: QuantAttrs, x: TensorRef, idx: list[Affine]) -> Expr:
    """x[idx] / scale, clamped, rounded half to even, plus the zero point."""
    low, high = attrs.dtype.range
    scaled = Binary("/", Load(x.buffer, x.at(idx)), Const.splat(attrs.scale))
    return Requantize(scaled, attrs.zero_point, low, high, attrs.dtype)


def lower_dequantize_linear(ctx: LoweringContext, node: Node) -> None:
    """(q - zero_point) * scale, the difference exact in int32, the product rounded once in float32."""
    attrs: QuantAttrs = node.attrs
    x = ctx.ref(node.inputs[0])

    def value(idx: list[Affine]) -> Expr:
        return Binary("*", Cast(FLOAT32, widened(x, idx, attrs.zero_point)), Const.splat(attrs.scale))

    # a graph output (the usual place of the last DequantizeLinear) is written in its own order: no copy
    output = ctx.graph.is_graph_output(node.outputs[0])
    elementwise(ctx, node, row_major(len(x.shape)) if output else x.order, value)


def lower_integer_maxpool(ctx: LoweringContext, node: Node) -> None:
    """MaxPool of 8-bit values: the int32 maximum of the taps inside the input (a window wholly in
    the padding gives the type's minimum)."""
    attrs = node.attrs
    x = ctx.ref(node.inputs[0])
    dtype = ctx.graph.dtype(node.inputs[0])
    rank = len(attrs.kernel)
    out = ctx.output(node.outputs[0], channels_last(rank + 2))
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def tap(positions: list[Affine], _k: list[Affine]) -> tuple[Stmt, ...]:
            value = widened(x, [env["n"], env["c"], *positions])
            return (Assign("acc", Binary("max", LocalRef("acc"), value)),)

        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        index = [env["n"], env["c"], *(env["o" + s] for s in names)]
        store = Store(out.buffer, out.at(index), Cast(dtype, LocalRef("acc")))
        return (Let("acc", Const.integer(dtype.range[0]), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("c", out.shape[1])]
    ctx.emit(node.name, "MaxPool", nest(loops, body, parallel=True))


def lower_any_maxpool(ctx: LoweringContext, node: Node) -> None:
    """MaxPool of floats, or of the integers of an int8 model."""
    if ctx.graph.dtype(node.inputs[0]).is_integer:
        lower_integer_maxpool(ctx, node)
    else:
        lower_maxpool(ctx, node)
