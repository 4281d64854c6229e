"""LRN lowering: per element, the sum of squares over a window of channels (a border check drops the
channels outside the input), then y = x * exp(-beta * log(bias + alpha / size * sum)), the power
through the two math.h functions the IR has."""

from __future__ import annotations

from ..ir.graph import LrnAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Bound, Call, Const, If, Let, Load, LocalRef, Loop, Stmt, Store
from .context import LoweringContext, dim_vars, nest


def lower_lrn(ctx: LoweringContext, node: Node) -> None:
    attrs: LrnAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], x.order)
    names = dim_vars(len(x.shape))
    channels = x.shape[1]
    before = (attrs.size - 1) // 2  # the window is c - before .. c + size - 1 - before, as in ONNX

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        idx = [env[v] for v in names]
        j = Affine.of("kc") if attrs.size > 1 else Affine()
        channel = idx[1] + j - before
        neighbour = Load(x.buffer, x.at([idx[0], channel, *idx[2:]]))
        add: tuple[Stmt, ...] = (Assign("s", Binary("+", LocalRef("s"), Binary("*", neighbour, neighbour))),)
        lo, hi = channel.bounds({names[1]: channels, "kc": attrs.size})
        if lo < 0 or hi >= channels:
            add = (If((Bound(channel, 0 if lo < 0 else None, channels if hi >= channels else None),), add),)
        window = (Loop("kc", attrs.size, add),) if attrs.size > 1 else add
        base = Binary("+", Const.splat(attrs.bias), Binary("*", Const.splat(attrs.alpha / attrs.size), LocalRef("s")))
        factor = Call("exp", Binary("*", Const.splat(-attrs.beta), Call("log", base)))
        store = Store(out.buffer, out.at(idx), Binary("*", Load(x.buffer, x.at(idx)), factor))
        return (Let("s", Const.splat(0.0), (*window, store)),)

    ctx.emit(node.name, node.op, nest([(names[d], x.shape[d]) for d in out.order], body, parallel=True))
