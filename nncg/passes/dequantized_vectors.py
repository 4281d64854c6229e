"""Part of the loop pass `vectorize`: the dequantised stores of ConvInteger and MatMulInteger
(lowering/integer_products.py) on vectors. Scalar C spells each float32 step in double,

    float32(double(acc) * double(scale))            (or double(float32(acc)) where |acc| can pass 2^24)
    float32(double(that) + double(bias))

which a vector computes as float32 operations: float32(acc) * scale (the double product of two float32
values is exact, so it rounds once, as the float32 product does) and the sum as Fma(product, 1, bias),
one rounding as onnxruntime's float32 Add (a vector multiply feeding a vector add, the C compiler could
contract into one fused rounding; on a target without FMA vectorize makes the Fma by 1 an add)."""

from __future__ import annotations

from collections.abc import Mapping

from ..ir.dtypes import expr_dtype
from ..ir.kinds import DType
from ..ir.loops import Binary, Broadcast, Cast, Const, Expr, Fma, Let, Stmt, map_body, map_stmt_exprs, walk_stmts

FLOAT32, FLOAT64 = DType.FLOAT32, DType.FLOAT64
# the kernels whose stores may be dequantised so
DEQUANTIZING_OPS = ("ConvInteger", "MatMulInteger")


def dequantized_vectors(body: tuple[Stmt, ...], buffers: Mapping[str, DType]) -> tuple[Stmt, ...]:
    """The kernel's vector expressions float32(double(a) op double(b)) as float32 operations (above)."""
    locals_: dict[str, DType] = {}
    for stmt in walk_stmts(body):
        if isinstance(stmt, Let):
            locals_[stmt.name] = expr_dtype(stmt.init, buffers, locals_)

    def dtype(e: Expr) -> DType:
        return expr_dtype(e, buffers, locals_)

    def rewrite(e: Expr) -> Expr:
        if not (isinstance(e, Cast) and e.dtype == FLOAT32 and e.lanes > 1 and isinstance(e.value, Binary)):
            return e
        op, a, b = e.value.op, _undoubled(e.value.a), _undoubled(e.value.b)
        if a is None or b is None or dtype(b) != FLOAT32:
            return e
        if op == "*" and dtype(a).is_integer:
            return Binary("*", Cast(FLOAT32, a), b)
        if op == "*" and dtype(a) == FLOAT32:
            return Binary("*", a, b)
        if op == "+" and dtype(a) == FLOAT32:
            return Fma(a, Const.splat(1.0, e.lanes), b)
        return e

    return map_body(body, lambda s: map_stmt_exprs(s, rewrite))


def _undoubled(e: Expr) -> Expr | None:
    """x of double(x), or of its broadcast (an operand the same in every lane); None for anything else."""
    if isinstance(e, Broadcast) and isinstance(e.value, Cast) and e.value.dtype == FLOAT64:
        return Broadcast(e.value.value, e.lanes)
    return e.value if isinstance(e, Cast) and e.dtype == FLOAT64 else None
