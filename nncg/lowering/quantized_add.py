"""Lowering of QLinearAdd, as onnxruntime's x86 kernel (MLAS's AVX2 QLinearAdd) computes it, so the
results match to the bit. With r_a = a_scale / y_scale and r_b = b_scale / y_scale (float32) and the
float32 constant c = y_zp - fma(a_zp, r_a, r_b * b_zp) (the compiler contracts MLAS's
r_a * a_zp + r_b * b_zp so), y = saturate(round_half_even(fma(a, r_a, fma(b, r_b, c)))).
Broadcast, onnxruntime runs the kernel over spans of the output's innermost dims in which an operand
is either a whole span or one value: where the first operand is the one value, it passes the second
first, so a and b trade places in both formulas. C89 has no fma: each is computed in double and
rounded to float, which is the fused result whenever the double sum is exact — it is, as a and b have
8 bits and the scales 24, unless the addend and the product are more than 2^21 apart in magnitude
(then a double rounding could differ from the fused one in the last bit of t, at a tie of the final
rounding only)."""

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


def fused_multiply_add(x: Expr, ratio: float, addend: Expr) -> Expr:
    """float32(x * ratio + addend), computed in double: x an int32 value, addend a float32 one."""
    product = Binary("*", Cast(FLOAT64, x), Const((ratio,), FLOAT64))
    return Cast(FLOAT32, Binary("+", product, Cast(FLOAT64, addend)))


def _fma32(x: float, ratio: F32, addend: F32) -> F32:
    """float32(x * ratio + addend), as fused_multiply_add computes it, at compile time."""
    return F32(np.float64(x) * np.float64(ratio) + np.float64(addend))


def first_operand_is_one_value(a_shape: tuple[int, ...], out_shape: tuple[int, ...]) -> bool:
    """Whether onnxruntime's broadcast spans hold one value of the first operand: it is broadcast
    along the output's innermost dim of more than one element (dims of 1 in both do not split spans)."""
    for axis in range(1, len(out_shape) + 1):
        if out_shape[-axis] > 1:
            return axis > len(a_shape) or a_shape[-axis] == 1
    return False


def lower_qlinear_add(ctx: LoweringContext, node: Node) -> None:
    attrs: QBinaryAttrs = node.attrs
    out = attrs.out
    # (scale ratio, zero point) of the operand multiplied last, and of the one inside
    outer = (F32(attrs.a_scale) / F32(attrs.y_scale), attrs.a_zero_point)
    inner = (F32(attrs.b_scale) / F32(attrs.y_scale), attrs.b_zero_point)
    swap = first_operand_is_one_value(ctx.graph.shape(node.inputs[0]), ctx.graph.shape(node.outputs[0]))
    if swap:
        outer, inner = inner, outer
    fixed = F32(out.zero_point) - _fma32(outer[1], outer[0], inner[0] * F32(inner[1]))

    def value(loads: list[Load]) -> Expr:
        outer_load, inner_load = reversed(loads) if swap else loads
        partial = fused_multiply_add(centred(inner_load), float(inner[0]), Const.splat(float(fixed)))
        total = fused_multiply_add(centred(outer_load), float(outer[0]), partial)
        return Requantize(total, 0, out.low, out.high, out.dtype)

    broadcast(ctx, node, value)
