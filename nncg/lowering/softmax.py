"""Softmax and LogSoftmax lowerings, numerically stable: with m the max over the reduced dims,
softmax is exp(x - m) / sum(exp(x - m)) and log-softmax is x - (m + log(sum(exp(x - m))))."""

from __future__ import annotations

from collections.abc import Callable

from ..ir.graph import Node, SoftmaxAttrs
from ..ir.loops import Affine, Assign, Binary, Call, Const, Expr, Let, Load, LocalRef, Stmt, Store
from .context import LoweringContext, dim_vars, nest

# over(stmt_of): a loop nest over the reduced dims running stmt_of(x_at, y_at, store_at) per element:
# the input and output loads there and a function making the store of a value there.
Over = Callable[[Callable[[Load, Load, Callable[[Expr], Store]], tuple[Stmt, ...]]], tuple[Stmt, ...]]


def lower_softmax(ctx: LoweringContext, node: Node) -> None:
    def phases(over: Over) -> tuple[Stmt, ...]:
        exponentiate = over(
            lambda xv, yv, store: (
                store(Call("exp", Binary("-", xv, LocalRef("mx")))),
                Assign("sum", Binary("+", LocalRef("sum"), yv)),
            )
        )
        normalise = over(lambda _x, yv, store: (store(Binary("*", yv, LocalRef("inv"))),))
        scale = Let("inv", Binary("/", Const.splat(1.0), LocalRef("sum")), normalise)
        return (Let("sum", Const.splat(0.0), (*exponentiate, scale)),)

    _lower_normalizer(ctx, node, phases)


def lower_log_softmax(ctx: LoweringContext, node: Node) -> None:
    def phases(over: Over) -> tuple[Stmt, ...]:
        add_exp = over(
            lambda xv, _y, _store: (
                Assign("sum", Binary("+", LocalRef("sum"), Call("exp", Binary("-", xv, LocalRef("mx"))))),
            )
        )
        subtract = over(lambda xv, _y, store: (store(Binary("-", xv, LocalRef("lse"))),))
        log_sum = Let("lse", Binary("+", LocalRef("mx"), Call("log", LocalRef("sum"))), subtract)
        return (Let("sum", Const.splat(0.0), (*add_exp, log_sum)),)

    _lower_normalizer(ctx, node, phases)


def _lower_normalizer(ctx: LoweringContext, node: Node, phases: Callable[[Over], tuple[Stmt, ...]]) -> None:
    """Per position of the kept dims: mx = the max over the reduced dims, then `phases`."""
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
        def over(stmt_of) -> tuple[Stmt, ...]:
            def at_index(inner_env: dict[str, Affine]) -> tuple[Stmt, ...]:
                env = outer_env | inner_env
                i = out.at([env[v] for v in names])
                x_at = Load(x.buffer, x.at([env[v] for v in names]))
                return stmt_of(x_at, Load(out.buffer, i), lambda value: Store(out.buffer, i, value))

            return nest(inner, at_index, parallel=False)

        find_max = over(lambda xv, _y, _store: (Assign("mx", Binary("max", LocalRef("mx"), xv)),))
        return (Let("mx", Const.splat(float("-inf")), (*find_max, *phases(over))),)

    ctx.emit(node.name, node.op, nest(outer, body, parallel=True))
