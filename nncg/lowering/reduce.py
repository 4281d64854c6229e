"""Reduce* and ArgMax/ArgMin lowerings: per kept position, an accumulator over the reduced dims, then
one store. Both loop groups run in the input's memory order, the kept dims outside, so that over a
channels-last input (the spatial mean after a Conv) the channel loop is the innermost parallel one
and vectorises."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..ir.graph import ArgMaxAttrs, Node, ReduceAttrs
from ..ir.loops import Affine, Assign, Binary, Call, Const, Expr, Let, Load, LocalRef, Select, Stmt, Store
from .context import LoweringContext, TensorRef, dim_vars, nest


def _add(acc: Expr, x: Expr) -> Expr:
    return Binary("+", acc, x)


def _abs(x: Expr) -> Expr:
    return Binary("max", x, Binary("-", Const.splat(0.0), x))


@dataclass(frozen=True)
class Reduction:
    """acc = init; acc = accumulate(acc, x) per reduced element; the result is finish(acc, count).
    `shifted`: x - max is accumulated and max added back after finish (log-sum-exp, without overflow)."""

    init: float
    accumulate: Callable[[Expr, Expr], Expr]
    finish: Callable[[Expr, int], Expr] = lambda acc, count: acc
    shifted: bool = False


REDUCTIONS: dict[str, Reduction] = {
    "ReduceSum": Reduction(0.0, _add),
    "ReduceMean": Reduction(0.0, _add, lambda acc, count: Binary("/", acc, Const.splat(count))),
    "ReduceMax": Reduction(float("-inf"), lambda acc, x: Binary("max", acc, x)),
    "ReduceMin": Reduction(float("inf"), lambda acc, x: Binary("min", acc, x)),
    "ReduceL1": Reduction(0.0, lambda acc, x: _add(acc, _abs(x))),
    "ReduceL2": Reduction(0.0, lambda acc, x: _add(acc, Binary("*", x, x)), lambda acc, count: Call("sqrt", acc)),
    "ReduceSumSquare": Reduction(0.0, lambda acc, x: _add(acc, Binary("*", x, x))),
    "ReduceLogSum": Reduction(0.0, _add, lambda acc, count: Call("log", acc)),
    "ReduceLogSumExp": Reduction(
        0.0, lambda acc, x: _add(acc, Call("exp", x)), lambda acc, count: Call("log", acc), shifted=True
    ),
}

# over(stmt_of): a loop nest over the reduced dims running stmt_of(x there, the loop variables).
Over = Callable[[Callable[[Load, dict[str, Affine]], tuple[Stmt, ...]]], tuple[Stmt, ...]]
# result(over): the reduction's value and the scope its store runs in (the accumulating loops before it).
Result = Callable[[Over], tuple[Expr, Callable[[Stmt], Stmt]]]


def lower_reduce(ctx: LoweringContext, node: Node) -> None:
    attrs: ReduceAttrs = node.attrs
    reduction = REDUCTIONS[node.op]
    x = ctx.ref(node.inputs[0])
    count = math.prod(x.shape[d] for d in attrs.axes)
    s, mx = LocalRef("s"), LocalRef("mx")

    def result(over: Over) -> tuple[Expr, Callable[[Stmt], Stmt]]:
        shift = (lambda xv: Binary("-", xv, mx)) if reduction.shifted else (lambda xv: xv)
        add = over(lambda xv, _: (Assign("s", reduction.accumulate(s, shift(xv))),))

        def accumulate(store: Stmt) -> Stmt:
            return Let("s", Const.splat(reduction.init), (*add, store))

        if not reduction.shifted:
            return reduction.finish(s, count), accumulate
        find_max = over(lambda xv, _: (Assign("mx", Binary("max", mx, xv)),))
        value = Binary("+", mx, reduction.finish(s, count))
        return value, lambda store: Let("mx", Const.splat(float("-inf")), (*find_max, accumulate(store)))

    _lower_reduction(ctx, node, x, attrs.axes, attrs.keepdims, result)


def lower_arg_extreme(ctx: LoweringContext, node: Node) -> None:
    """ArgMax/ArgMin: the running extreme and its index, replaced on a strictly better element (the
    first one wins), or on an equal one too with select_last_index (the last one wins). The int32
    index comes from a constant table 0, 1, 2, ... (loop-nest indices are affine, not values)."""
    attrs: ArgMaxAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    table = ctx.add_constant(f"index_{node.name}", np.arange(x.shape[attrs.axis], dtype=np.int32))
    better = {"ArgMax": ">", "ArgMin": "<"}[node.op] + ("=" if attrs.select_last_index else "")
    start = float("-inf") if node.op == "ArgMax" else float("inf")
    axis_var = dim_vars(len(x.shape))[attrs.axis]
    best, at = LocalRef("best"), LocalRef("at")

    def result(over: Over) -> tuple[Expr, Callable[[Stmt], Stmt]]:
        def step(xv: Load, env: dict[str, Affine]) -> tuple[Stmt, ...]:
            index = Load(table.buffer, table.at([env[axis_var]]))
            found = Assign("at", Select(better, xv, best, index, at))
            return (found, Assign("best", Select(better, xv, best, xv, best)))

        search = over(step)
        return at, lambda store: Let("best", Const.splat(start), (Let("at", Const.integer(0), (*search, store)),))

    _lower_reduction(ctx, node, x, (attrs.axis,), attrs.keepdims, result)


def _lower_reduction(
    ctx: LoweringContext, node: Node, x: TensorRef, axes: tuple[int, ...], keepdims: bool, result: Result
) -> None:
    """Per position of the kept dims: the store of the value `result` gives over the reduced dims."""
    rank = len(x.shape)
    kept = [d for d in range(rank) if d not in axes]
    # The output's dims: all of x's with keepdims (the reduced ones of size 1), else the kept ones.
    out_dims = list(range(rank)) if keepdims else kept
    out = ctx.output(node.outputs[0], tuple(out_dims.index(d) for d in x.order if d in out_dims))
    names = dim_vars(rank)
    outer = [(names[d], x.shape[d]) for d in x.order if d in kept]
    inner = [(names[d], x.shape[d]) for d in x.order if d in axes]

    def body(outer_env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def over(stmt_of) -> tuple[Stmt, ...]:
            def at_element(inner_env: dict[str, Affine]) -> tuple[Stmt, ...]:
                env = outer_env | inner_env
                return stmt_of(Load(x.buffer, x.at([env[v] for v in names])), env)

            return nest(inner, at_element, parallel=False)

        value, scope = result(over)
        at = [outer_env[names[d]] if d in kept else Affine() for d in out_dims]
        return (scope(Store(out.buffer, out.at(at), value)),)

    ctx.emit(node.name, node.op, nest(outer, body, parallel=True))
