"""Lowering of QLinearAdd, as onnxruntime's x86 kernel (MLAS's AVX2 QLinearAdd) computes it, so the
results match to the bit: with r_a = a_scale / y_scale and r_b = b_scale / y_scale (float32), and
the float32 constant c = y_zp - (r_a * a_zp + r_b * b_zp), y = saturate(round_half_even(
fma(a, r_a, fma(b, r_b, c)))). C89 has no fma: each is computed in double and rounded to float,
which is the fused result whenever the double sum is exact — it is, as a and b have 8 bits and the
scales 24, unless c and the product are more than 2^21 apart in magnitude (then a double rounding
could differ from the fused one in the last bit of t, at a tie of the final rounding only)."""

from __future__ import annotations

import numpy as np

from ..ir.graph import Node, QAddAttrs
from ..ir.kinds import DType
from ..ir.loops import Affine, Binary, Cast, Const, Expr, Requantize
from .context import LoweringContext
from .elementwise import elementwise
from .quantized import widened

F32 = np.float32
FLOAT64, FLOAT32 = DType.FLOAT64, DType.FLOAT32


def fused_multiply_add(x: Expr, ratio: float, addend: Expr) -> Expr:
    """float32(x * ratio + addend), computed in double: x an int32 value, addend a float32 one."""
    product = Binary("*", Cast(FLOAT64, x), Const((ratio,), FLOAT64))
    return Cast(FLOAT32, Binary("+", product, Cast(FLOAT64, addend)))


def lower_qlinear_add(ctx: LoweringContext, node: Node) -> None:
    attrs: QAddAttrs = node.attrs
    a, b = (ctx.ref(name) for name in node.inputs)
    ratio_a, ratio_b = F32(attrs.a_scale) / F32(attrs.y_scale), F32(attrs.b_scale) / F32(attrs.y_scale)
    fixed = F32(attrs.out.zero_point) - (ratio_a * F32(attrs.a_zero_point) + ratio_b * F32(attrs.b_zero_point))
    out = attrs.out

    def value(idx: list[Affine]) -> Expr:
        partial = fused_multiply_add(widened(b, idx), float(ratio_b), Const.splat(float(fixed)))
        total = fused_multiply_add(widened(a, idx), float(ratio_a), partial)
        return Requantize(total, 0, out.low, out.high, out.dtype)

    elementwise(ctx, node, a.order, value)
