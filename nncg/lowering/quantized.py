"""Lowering of the int8 path: integer Conv, matrix product and global average pool (int32
accumulators in locals, requantised at the store: requantize.py), QuantizeLinear and
DequantizeLinear, and MaxPool of integers. Every integer load is widened to int32 before any
arithmetic, so no product or sum wraps; int32 values never leave the kernel (the arena holds 8-bit
values only, see backends/c_file.py)."""

from __future__ import annotations

import math

import numpy as np

from ..ir.graph import Node, QAveragePoolAttrs, QConvAttrs, QDenseAttrs, QPoolAttrs, QuantAttrs
from ..ir.kinds import DType
from ..ir.loops import Affine, Assign, Binary, Cast, Const, Expr, Let, Load, LocalRef, Loop, Requantize, Stmt, Store
from .context import LoweringContext, TensorRef, channels_last, nest, row_major
from .elementwise import elementwise
from .pool import window_counts
from .requantize import Scales
from .window import spatial_names, window_nest

INT32, FLOAT32 = DType.INT32, DType.FLOAT32


def widened(ref: TensorRef, index, zero_point: int = 0) -> Expr:
    """ref[index] as int32, minus its zero point."""
    value: Expr = Cast(INT32, Load(ref.buffer, ref.at(index)))
    return Binary("-", value, Const.integer(zero_point)) if zero_point else value


def accumulate(product: Expr) -> Assign:
    return Assign("acc", Binary("+", LocalRef("acc"), product))


def lower_qlinear_conv(ctx: LoweringContext, node: Node) -> None:
    """As lower_conv (conv.py), in integers: taps outside the image are skipped, which is reading
    the zero point there (x - x_zero_point = 0)."""
    attrs: QConvAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    rank = len(attrs.kernel)
    weights = ctx.graph.constants[node.inputs[1]]  # [c_out, c_in/group, k...] -> [k..., c_in/group, c_out]
    c_out, c_in = weights.shape[:2]
    c_out_g = c_out // attrs.group
    w = ctx.add_constant(f"w_{node.name}", np.transpose(weights, (*range(2, rank + 2), 1, 0)))
    bias = ctx.add_constant(f"b_{node.name}", ctx.graph.constants[node.inputs[2]])
    scales = Scales(ctx, node.name, ctx.graph.constants[node.inputs[3]])
    out = ctx.output(node.outputs[0], channels_last(rank + 2))
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, co = env["n"], env["g"] * c_out_g + env["co"]
        ci = Affine.of("ci") if c_in > 1 else Affine()

        def tap(positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            x_value = widened(x, [n, env["g"] * c_in + ci, *positions], attrs.x_zero_point)
            update = (accumulate(Binary("*", x_value, widened(w, [*k_vars, ci, co]))),)
            return (Loop("ci", c_in, update),) if c_in > 1 else update

        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        index = [n, co, *(env["o" + s] for s in names)]
        store = Store(out.buffer, out.at(index), scales.requantized(LocalRef("acc"), co, attrs.out))
        return (Let("acc", Load(bias.buffer, bias.at([co])), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("g", attrs.group), ("co", c_out_g)]
    ctx.emit(node.name, "QLinearConv", nest(loops, body, parallel=True))


def lower_qlinear_dense(ctx: LoweringContext, node: Node) -> None:
    """y[m, n] = requantized(b[n] + sum_k (x[m, k] - x_zero_point) * w[k, n])."""
    attrs: QDenseAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    w = ctx.add_constant(f"w_{node.name}", ctx.graph.constants[node.inputs[1]])
    bias = ctx.add_constant(f"b_{node.name}", ctx.graph.constants[node.inputs[2]])
    scales = Scales(ctx, node.name, ctx.graph.constants[node.inputs[3]])
    out = ctx.output(node.outputs[0], row_major(2))
    k = w.shape[0]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        m, n = env["m"], env["n"]
        kk = Affine.of("k") if k > 1 else Affine()
        update = (accumulate(Binary("*", widened(x, [m, kk], attrs.x_zero_point), widened(w, [kk, n]))),)
        reduce = (Loop("k", k, update),) if k > 1 else update
        store = Store(out.buffer, out.at([m, n]), scales.requantized(LocalRef("acc"), n, attrs.out))
        return (Let("acc", Load(bias.buffer, bias.at([n])), (*reduce, store)),)

    ctx.emit(node.name, "QLinearDense", nest([("m", out.shape[0]), ("n", out.shape[1])], body, parallel=True))


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
    sum / y_scale + y_zp rounded half to even and saturated."""
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
            dequantized = Cast(FLOAT32, widened(x, [env["n"], env["c"], *positions], attrs.x_zero_point))
            return (accumulate(Binary("*", Const.splat(attrs.x_scale), dequantized)),)

        window = window_nest(attrs.pool, env, dict(out_loops), x.spatial_ranges, tap)
        spatial = [env["o" + s] for s in names]
        count = Const.splat(float(counts.flat[0])) if uniform else Load(count_ref.buffer, count_ref.at(spatial))
        mean = Binary("/", LocalRef("acc"), count)
        value = Binary("+", Binary("/", mean, Const.splat(attrs.y_scale)), Const.splat(float(attrs.out.zero_point)))
        requantized = Requantize(value, 0, attrs.out.low, attrs.out.high, attrs.out.dtype)
        store = Store(out.buffer, out.at([env["n"], env["c"], *spatial]), requantized)
        return (Let("acc", Const.splat(0.0), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("c", out.shape[1])]
    ctx.emit(node.name, "QLinearAveragePool", nest(loops, body, parallel=True))


def lower_quantize_linear(ctx: LoweringContext, node: Node) -> None:
    """QuantizeLinear as onnxruntime computes it: x / scale, clamped, rounded half to even, plus the
    zero point (MLAS's MlasQuantizeLinear)."""
    attrs: QuantAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    low, high = attrs.dtype.range

    def value(idx: list[Affine]) -> Expr:
        scaled = Binary("/", Load(x.buffer, x.at(idx)), Const.splat(attrs.scale))
        return Requantize(scaled, attrs.zero_point, low, high, attrs.dtype)

    elementwise(ctx, node, x.order, value)


def lower_dequantize_linear(ctx: LoweringContext, node: Node) -> None:
    """(q - zero_point) * scale, the difference exact in int32, the product rounded once in float32."""
    attrs: QuantAttrs = node.attrs
    x = ctx.ref(node.inputs[0])

    def value(idx: list[Affine]) -> Expr:
        return Binary("*", Cast(FLOAT32, widened(x, idx, attrs.zero_point)), Const.splat(attrs.scale))

    elementwise(ctx, node, x.order, value)


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
