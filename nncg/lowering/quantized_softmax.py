"""Lowering of QLinearSoftmax as onnxruntime's CPU kernel computes it (frontend/ops_qsoftmax.py
gives its arithmetic and builds the table): per row, the int32 maximum m of the inputs, the float32
sum, in index order, of the table entries at 255 - m + x, then each output from its entry."""

from __future__ import annotations

from collections.abc import Callable

from ..ir.graph import Node, QSoftmaxAttrs
from ..ir.kinds import DType
from ..ir.loops import Affine, Assign, Binary, Const, Expr, Let, LocalRef, Lookup, Requantize, Stmt, Store
from .context import LoweringContext, dim_vars, nest
from .quantized import widened

INT8, INT32 = DType.INT8, DType.INT32


def lower_qlinear_softmax(ctx: LoweringContext, node: Node) -> None:
    attrs: QSoftmaxAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    table = ctx.add_constant(f"exp_{node.name}", ctx.graph.constants[node.inputs[1]])
    out = ctx.output(node.outputs[0], x.order)
    rank, axis = len(x.shape), attrs.softmax.axis
    reduced = tuple(range(axis, rank)) if attrs.softmax.coerce_2d else (axis,)
    names = dim_vars(rank)
    outer = [(names[d], x.shape[d]) for d in x.order if d not in reduced]
    inner = [(names[d], x.shape[d]) for d in reduced]  # index order: the order onnxruntime sums in

    def body(outer_env: dict[str, Affine]) -> tuple[Stmt, ...]:
        def over(stmt_of: Callable[[list[Affine]], tuple[Stmt, ...]]) -> tuple[Stmt, ...]:
            return nest(inner, lambda env: stmt_of([(outer_env | env)[v] for v in names]), parallel=False)

        def entry(idx: list[Affine]) -> Expr:
            offset = Binary("-", Const.integer(255), LocalRef("mx"))
            return Lookup(table.buffer, Binary("+", offset, widened(x, idx)))

        find_max = over(lambda idx: (Assign("mx", Binary("max", LocalRef("mx"), widened(x, idx))),))
        add = over(lambda idx: (Assign("sum", Binary("+", LocalRef("sum"), entry(idx))),))
        store = over(lambda idx: _store(attrs, entry(idx), lambda value: Store(out.buffer, out.at(idx), value)))
        lowest = Const.integer(ctx.graph.dtype(node.inputs[0]).range[0])
        return (Let("mx", lowest, (*find_max, Let("sum", Const.splat(0.0), (*add, *store)))),)

    ctx.emit(node.name, "QLinearSoftmax", nest(outer, body, parallel=True))


def _store(attrs: QSoftmaxAttrs, entry: Expr, store: Callable[[Expr], Store]) -> tuple[Stmt, ...]:
    """entry * y_multiplier / sum in float32, rounded half to even, plus the zero point, saturated."""
    quotient = Binary("/", Binary("*", entry, Const.splat(attrs.y_multiplier)), LocalRef("sum"))
    out = attrs.out
    return (store(Requantize(quotient, out.zero_point, out.low, out.high, out.dtype)),)
