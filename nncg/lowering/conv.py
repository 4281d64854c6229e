"""Conv lowering: direct convolution with output channels innermost, so they vectorise; or, for a
layer the vectorize-pixels pass marked, a planar (NCHW) output with its rows innermost.

Weights are read as [k_1..k_d][c_in/group][c_out], packed in that order when constant (a runtime
weight is read in place through a strided view, see weights.py). With groups, output channel
g*C_out_g + co reads input channels g*C_in_g + ci; a depthwise conv has one channel per group, so
the group loop is the contiguous one and vectorises. A fused residual is added at the store. With
`planes_outside_row` (a planar input), the input-channel loop wraps the taps along a row instead of
sitting inside them (see passes/vectorize_pixels.py)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..ir.graph import ConvAttrs, Node
from ..ir.kinds import DType, VectorAxis
from ..ir.loops import Affine, Assign, Binary, Const, Expr, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, channels_last, nest, row_major
from .weights import by_panels, permuted, weight_operand
from .window import around_row_taps, spatial_names, window_nest

# Channels a depthwise Conv computes over all its pixels at a time (depthwise_weights_exceed_l1): 4
# vectors of 16, their 5x5 weights 6.4 KB.
DEPTHWISE_CHANNEL_BLOCK = 64

# The load of a weight at (tap variables, input channel, output channel).
WeightLoad = Callable[[list[Affine], Affine, Affine], Expr]


def conv_extras(node: Node) -> tuple[str | None, str | None]:
    """The bias and the residual a Conv node reads, each None when absent."""
    extras = list(node.inputs[2:])
    residual = extras.pop() if node.attrs.residual else None
    return (extras[0] if extras else None), residual


def lower_conv(ctx: LoweringContext, node: Node, channels_outermost: bool = False) -> None:
    """With `channels_outermost`, a depthwise Conv runs DEPTHWISE_CHANNEL_BLOCK channels at a time
    outside its pixel loops, each block's weights packed together (see depthwise_weights_exceed_l1)."""
    attrs: ConvAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    groups, rank = attrs.group, len(attrs.kernel)
    c_out, c_in = ctx.graph.shape(node.inputs[1])[:2]  # [c_out, c_in/group, k_1..k_d]
    c_out_g = c_out // groups
    pixels = attrs.vector_axis == VectorAxis.PIXELS
    in_blocks = channels_outermost and not pixels and c_in == c_out_g == 1
    # the weights are packed block by block below; otherwise in tap order, before the bias
    w = (
        None
        if in_blocks
        else weight_operand(ctx, node.inputs[1], f"w_{node.name}", lambda r: permuted(r, (*range(2, rank + 2), 1, 0)))
    )
    bias_name, residual_name = conv_extras(node)
    bias = weight_operand(ctx, bias_name, f"b_{node.name}") if bias_name else None
    residual = ctx.ref(residual_name) if residual_name else None
    out = ctx.output(node.outputs[0], row_major(rank + 2) if pixels else channels_last(rank + 2))
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    planes_outside = attrs.planes_outside_row and c_in > 1

    def body(env: dict[str, Affine], weight: WeightLoad) -> tuple[Stmt, ...]:
        n, co = env["n"], env["g"] * c_out_g + env["co"]
        ci = Affine.of("ci") if c_in > 1 else Affine()
        ci_global = env["g"] * c_in + ci

        def tap(positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            x_load = Load(x.buffer, x.at([n, ci_global, *positions]))
            product = Binary("*", x_load, weight(k_vars, ci, co))
            update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
            return (Loop("ci", c_in, update),) if c_in > 1 and not planes_outside else update

        init = Load(bias.buffer, bias.at([co])) if bias else Const.splat(0.0)
        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        if planes_outside:
            window = around_row_taps(window, rank, ("ci", c_in))
        index = [n, co, *(env["o" + s] for s in names)]
        value: Expr = LocalRef("acc")
        if residual:
            value = Binary("+", value, Load(residual.buffer, residual.at(index)))
        store = Store(out.buffer, out.at(index), apply_activation(value, attrs.activation))
        return (Let("acc", init, (*window, store)),)

    if in_blocks:
        weights = ctx.graph.constants[node.inputs[1]]

        def pack(start: int, stop: int, panels: int) -> np.ndarray:
            """[channels, 1, k...] -> [block][k...][channel of the block]."""
            block = weights[start:stop].reshape(panels, (stop - start) // panels, *attrs.kernel)
            return block.transpose(0, *range(2, rank + 2), 1)

        def nests(w: TensorRef, block: Affine, first: Affine, width: int) -> tuple[Stmt, ...]:
            def in_block(env: dict[str, Affine]) -> tuple[Stmt, ...]:
                local = env["g"]
                return body(env | {"g": local + first}, lambda k, ci, co: Load(w.buffer, w.at([block, *k, local])))

            return nest([("n", out.shape[0]), *out_loops, ("g", width), ("co", 1)], in_block, parallel=True)

        ctx.emit(node.name, "Conv", by_panels(ctx, f"w_{node.name}", groups, DEPTHWISE_CHANNEL_BLOCK, pack, nests))
        return
    channel_loops = [("g", groups), ("co", c_out_g)]
    if pixels:  # the output row innermost, contiguous in the planar output: vectorize takes it
        loops = [("n", out.shape[0]), *out_loops[:-1], *channel_loops, out_loops[-1]]
    else:
        loops = [("n", out.shape[0]), *out_loops, *channel_loops]

    def unpacked(k_vars: list[Affine], ci: Affine, co: Affine) -> Expr:
        assert w is not None
        return Load(w.buffer, w.at([*k_vars, ci, co]))

    ctx.emit(node.name, "Conv", nest(loops, lambda env: body(env, unpacked), parallel=True))


def depthwise_weights_exceed_l1(ctx: LoweringContext, node: Node) -> bool:
    """Whether a (constant) depthwise Conv's weights pass the target's L1, so lower_conv runs it a
    block of channels at a time: a block's weights, packed together, stay in L1 while it sweeps every
    pixel, where channels innermost read all the layer's weights again at each pixel (from L2 once
    they pass L1: efficientnet_b0's 1152-channel 5x5 layers on 3x3 pixels, 115 KB, ran 1.9x slower on
    avx512 alone, loaded); packed, the block's weights stream from memory in one run. Where
    they fit, channels innermost were as fast or faster (a 96-channel stride-2 3x3 layer on 48x48
    pixels: 1.1x-1.2x slower with channel blocks outermost on avx2 and avx512, loaded)."""
    c_out, c_in_g, *kernel = ctx.graph.shape(node.inputs[1])
    depthwise = c_in_g == 1 and node.attrs.group == c_out > 1 and ctx.graph.is_constant(node.inputs[1])
    return depthwise and 0 < ctx.l1_bytes < DType.FLOAT32.bytes * c_out * math.prod(kernel)
