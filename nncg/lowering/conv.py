"""Conv lowering: direct convolution with output channels innermost, so they vectorise; or, for a
layer the vectorize-pixels pass marked, a planar (NCHW) output with its rows innermost.

Weights are read as [k_1..k_d][c_in/group][c_out], packed in that order when constant (a runtime
weight is read in place through a strided view, see weights.py). With groups, output channel
g*C_out_g + co reads input channels g*C_in_g + ci; a depthwise conv has one channel per group, so
the group loop is the contiguous one and vectorises. A fused residual is added at the store. With
`planes_outside_row` (a planar input), the input-channel loop wraps the taps along a row instead of
sitting inside them (see passes/vectorize_pixels.py)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..ir.graph import ConvAttrs, Node
from ..ir.kinds import VectorAxis
from ..ir.loops import Affine, Assign, Binary, Const, Expr, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, channels_last, nest, row_major
from .weights import by_panels, permuted, weight_operand
from .window import around_row_taps, spatial_names, window_nest

# The load of a weight at (tap variables, input channel, output channel).
WeightLoad = Callable[[list[Affine], Affine, Affine], Expr]


def conv_extras(node: Node) -> tuple[str | None, str | None]:
    """The bias and the residual a Conv node reads, each None when absent."""
    extras = list(node.inputs[2:])
    residual = extras.pop() if node.attrs.residual else None
    return (extras[0] if extras else None), residual


def lower_conv(ctx: LoweringContext, node: Node) -> None:
    """With `channel_block` (the cache-block pass chose it), a depthwise Conv runs that many channels at
    a time outside its pixel loops, each block's weights packed together."""
    attrs: ConvAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    groups, rank = attrs.group, len(attrs.kernel)
    c_out, c_in = ctx.graph.shape(node.inputs[1])[:2]  # [c_out, c_in/group, k_1..k_d]
    c_out_g = c_out // groups
    pixels = attrs.vector_axis == VectorAxis.PIXELS
    in_blocks = attrs.channel_block > 0  # only ever set on a depthwise Conv over channels
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

        ctx.emit(node.name, "Conv", by_panels(ctx, f"w_{node.name}", groups, attrs.channel_block, pack, nests))
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
