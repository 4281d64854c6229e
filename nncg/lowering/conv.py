"""Conv lowering: direct convolution with output channels innermost, so they vectorise.

Weights are packed [k_1..k_d][c_in/group][c_out], the order in which the loop nest reads them. With
groups, output channel g*C_out_g + co reads input channels g*C_in_g + ci; a depthwise conv has one
channel per group, so the group loop is the contiguous one and vectorises."""

from __future__ import annotations

import numpy as np

from ..ir.graph import ConvAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, channels_last, nest
from .window import spatial_names, window_nest


def lower_conv(ctx: LoweringContext, node: Node) -> None:
    attrs: ConvAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    weight = ctx.graph.constants[node.inputs[1]]  # [c_out, c_in/group, k_1..k_d]
    groups = attrs.group
    c_out_g, c_in = weight.shape[0] // groups, weight.shape[1]
    rank = weight.ndim - 2
    w = ctx.add_constant(f"w_{node.name}", np.moveaxis(weight, (0, 1), (-1, -2)))
    bias = None
    if len(node.inputs) > 2:
        bias = ctx.add_constant(f"b_{node.name}", ctx.graph.constants[node.inputs[2]])
    out = ctx.output(node.outputs[0], channels_last(rank + 2))
    names = spatial_names(rank)
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, co = env["n"], env["g"] * c_out_g + env["co"]
        ci = Affine.of("ci") if c_in > 1 else Affine()
        ci_global = env["g"] * c_in + ci

        def tap(positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            x_load = Load(x.buffer, x.at([n, ci_global, *positions]))
            product = Binary("*", x_load, Load(w.buffer, w.at([*k_vars, ci, co])))
            update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
            return (Loop("ci", c_in, update),) if c_in > 1 else update

        init = Load(bias.buffer, bias.at([co])) if bias else Const.splat(0.0)
        window = window_nest(attrs, env, dict(out_loops), x.shape[2:], tap)
        value = apply_activation(LocalRef("acc"), attrs.activation)
        store = Store(out.buffer, out.at([n, co, *(env["o" + s] for s in names)]), value)
        return (Let("acc", init, (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("g", groups), ("co", c_out_g)]
    ctx.emit(node.name, "Conv", nest(loops, body, parallel=True))
