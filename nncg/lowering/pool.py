"""MaxPool lowering: the window skeleton with a running max; padding never wins (it is -inf)."""

from __future__ import annotations

from ..ir.graph import Node, PoolAttrs
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Stmt, Store
from .context import LoweringContext, channels_last, nest
from .window import spatial_names, window_nest


def lower_maxpool(ctx: LoweringContext, node: Node) -> None:
    attrs: PoolAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], channels_last(len(attrs.kernel) + 2))
    names = spatial_names(len(attrs.kernel))
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, c = env["n"], env["c"]

        def tap(positions: list[Affine], _k_vars: list[Affine]) -> tuple[Stmt, ...]:
            load = Load(x.buffer, x.at([n, c, *positions]))
            return (Assign("m", Binary("max", LocalRef("m"), load)),)

        window = window_nest(attrs, env, dict(out_loops), x.shape[2:], tap)
        store = Store(out.buffer, out.at([n, c, *(env["o" + s] for s in names)]), LocalRef("m"))
        return (Let("m", Const.splat(float("-inf")), (*window, store)),)

    loops = [("n", out.shape[0]), *out_loops, ("c", out.shape[1])]
    ctx.emit(node.name, "MaxPool", nest(loops, body, parallel=True))
