"""Lowering of QLinearMul as onnxruntime's x86 kernel (MLAS's QLinearMul, SSE2) computes it, so the
results match to the bit: the int32 product p = (a - a_zp) (b - b_zp) (exact), then
y = saturate(round_half_even(float32(float32(p) * r) + float32(y_zp))) with the float32 ratio
r = a_scale * b_scale / y_scale (rounded as onnxruntime rounds it: the product, then the quotient).
The float32 multiply and add are each computed in double and rounded to float: exact there (p has
17 bits, r 24), so no compiler's contraction or excess precision can change them."""

from __future__ import annotations

import numpy as np

from ..ir.graph import Node, QBinaryAttrs
from ..ir.kinds import DType
from ..ir.loops import Binary, Cast, Const, Expr, Load, Requantize
from .context import LoweringContext
from .elementwise import broadcast
from .quantized import centred

F32 = np.float32
FLOAT64, FLOAT32 = DType.FLOAT64, DType.FLOAT32


def _in_float32(a: Expr, op: str, b: float) -> Expr:
    """float32(a op b) for a float32 or int32 a, computed in double."""
    return Cast(FLOAT32, Binary(op, Cast(FLOAT64, a), Const((b,), FLOAT64)))


def lower_qlinear_mul(ctx: LoweringContext, node: Node) -> None:
    attrs: QBinaryAttrs = node.attrs
    ratio = float((F32(attrs.a_scale) * F32(attrs.b_scale)) / F32(attrs.y_scale))
    out = attrs.out

    def product(loads: list[Load]) -> Expr:
        p = Binary("*", centred(loads[0], attrs.a_zero_point), centred(loads[1], attrs.b_zero_point))
        total = _in_float32(_in_float32(p, "*", ratio), "+", float(out.zero_point))
        return Requantize(total, 0, out.low, out.high, out.dtype)

    broadcast(ctx, node, product)
