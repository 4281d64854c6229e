"""Pool lowerings on the window skeleton: MaxPool keeps a running max (padding is skipped; a
window wholly in the padding gives -FLT_MAX as in onnxruntime, so such layers start from -FLT_MAX
instead of -inf); AveragePool sums and multiplies by 1/count, the count per output position precomputed here
from the ONNX rules (padding counted or not, ceil_mode windows clipped) into a table that unrolling
turns into literals."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir.graph import Node, PoolAttrs
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Stmt, Store
from .context import LoweringContext, channels_last, nest
from .window import spatial_names, window_nest


def lower_maxpool(ctx: LoweringContext, node: Node) -> None:
    attrs: PoolAttrs = node.attrs
    x_shape, out_shape = ctx.graph.shape(node.inputs[0]), ctx.graph.shape(node.outputs[0])
    empty = window_counts(replace(attrs, count_include_pad=False), x_shape[2:], out_shape[2:]).min() == 0
    start = float(np.finfo(np.float32).min) if empty else float("-inf")
    _lower_pool(ctx, node, "m", Const.splat(start), "max", None)


def lower_averagepool(ctx: LoweringContext, node: Node) -> None:
    attrs: PoolAttrs = node.attrs
    x_shape, out_shape = ctx.graph.shape(node.inputs[0]), ctx.graph.shape(node.outputs[0])
    counts = window_counts(attrs, x_shape[2:], out_shape[2:])
    # a window wholly in the padding (count 0) averages to 0, as in onnxruntime
    inverse = np.divide(1.0, counts, out=np.zeros_like(counts), where=counts > 0)
    inverse = ctx.add_constant(f"inv_count_{node.name}", inverse)
    _lower_pool(ctx, node, "s", Const.splat(0.0), "+", inverse)


def window_counts(attrs: PoolAttrs, in_spatial, out_spatial) -> np.ndarray:
    """How many inputs each output averages: per dim the taps inside the input (or inside the padded
    input with count_include_pad), multiplied over the dims."""
    counts = np.ones(out_spatial)
    for d, (size, out) in enumerate(zip(in_spatial, out_spatial)):
        lo, hi = (-attrs.pads_begin[d], size + attrs.pads_end[d]) if attrs.count_include_pad else (0, size)
        starts = np.arange(out)[:, None] * attrs.strides[d] - attrs.pads_begin[d]
        taps = starts + np.arange(attrs.kernel[d])[None, :] * attrs.dilations[d]
        per_dim = ((taps >= lo) & (taps < hi)).sum(axis=1)
        counts = counts * per_dim.reshape([-1 if i == d else 1 for i in range(len(out_spatial))])
    return counts


def _lower_pool(ctx: LoweringContext, node: Node, acc: str, init: Const, op: str, inverse) -> None:
    attrs: PoolAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], channels_last(len(attrs.kernel) + 2))
    names = spatial_names(len(attrs.kernel))
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, c = env["n"], env["c"]
        o = [env["o" + s] for s in names]

        def tap(positions: list[Affine], _k_vars: list[Affine]) -> tuple[Stmt, ...]:
            load = Load(x.buffer, x.at([n, c, *positions]))
            return (Assign(acc, Binary(op, LocalRef(acc), load)),)

        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        value = LocalRef(acc)
        if inverse is not None:
            value = Binary("*", value, Load(inverse.buffer, inverse.at(o)))
        return (Let(acc, init, (*window, Store(out.buffer, out.at([n, c, *o]), value))),)

    loops = [("n", out.shape[0]), *out_loops, ("c", out.shape[1])]
    ctx.emit(node.name, node.op, nest(loops, body, parallel=True))
