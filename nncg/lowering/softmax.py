"""Softmax lowering, numerically stable: y = exp(x - max) / sum(exp(x - max)) over the reduced dims."""

from __future__ import annotations

from ..ir.graph import Node, SoftmaxAttrs
from ..ir.loops import Affine, Assign, Binary, Call, Const, Let, Load, LocalRef, Stmt, Store
from .context import LoweringContext, dim_vars, nest


def lower_softmax(ctx: LoweringContext, node: Node) -> None:
    attrs: SoftmaxAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], x.order)
    rank = len(x.shape)
    # Opset < 13 flattens to 2-D at `axis`: all dims from axis on are reduced together.
    reduced = set(range(attrs.axis, rank)) if attrs.coerce_2d else {attrs.axis}
    names = dim_vars(rank)
    outer = [(names[d], x.shape[d]) for d in out.order if d not in reduced]
    inner = [(names[d], x.shape[d]) for d in out.order if d in reduced]

    def body(outer_env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def over_reduced(stmt_of) -> tuple[Stmt, ...]:
            def at_index(inner_env: dict[str, Affine]) -> tuple[Stmt, ...]:
                env = outer_env | inner_env
                idx = [env[v] for v in names]
                return stmt_of(Load(x.buffer, x.at(idx)), Load(out.buffer, out.at(idx)), out.at(idx))

            return nest(inner, at_index, parallel=False)

        find_max = over_reduced(lambda xv, _y, _i: (Assign("mx", Binary("max", LocalRef("mx"), xv)),))
        exponentiate = over_reduced(
            lambda xv, yv, i: (
                Store(out.buffer, i, Call("exp", Binary("-", xv, LocalRef("mx")))),
                Assign("sum", Binary("+", LocalRef("sum"), yv)),
            )
        )
        normalise = over_reduced(lambda _x, yv, i: (Store(out.buffer, i, Binary("*", yv, LocalRef("inv"))),))
        scale = Let("inv", Binary("/", Const.splat(1.0), LocalRef("sum")), normalise)
        return (
            Let("mx", Const.splat(float("-inf")), (*find_max, Let("sum", Const.splat(0.0), (*exponentiate, scale)))),
        )

    ctx.emit(node.name, "Softmax", nest(outer, body, parallel=True))
