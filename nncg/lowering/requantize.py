"""The two forms of requantisation the integer kernels end in (lower's `requantize` parameter).

float (default): the int32 result converted to float32, times the float32 multiplier, then
Requantize: clamped to the output range, rounded half to even, plus the zero point. This is
onnxruntime's arithmetic (MLAS's MlasRequantizeOutput), so its results match to the bit.

fixed: for targets without an FPU, RequantizeFixed: the multiplier m as an int32 M in [2^30, 2^31)
and a shift s with m = M * 2^-(31 + s) (M rounded half to even from m's 24-bit significand, so
exact); the result is (x * M) / 2^31 rounded half up, then / 2^s rounded half away from zero
(gemmlowp's and TFLite's two roundings), plus the zero point, saturated. It differs from the float
form by at most one step, where the two roundings meet a tie differently."""

from __future__ import annotations

import math

import numpy as np

from ..errors import NncgError
from ..ir.graph import Requantization
from ..ir.kinds import DType
from ..ir.loops import Affine, Binary, Cast, Const, Expr, Load, Requantize, RequantizeFixed
from .context import LoweringContext

FORMS = ("float", "fixed")


def parse_requantize(text: str) -> str:
    if text not in FORMS:
        raise ValueError(f"requantize is one of {', '.join(FORMS)}")
    return text


def fixed_point(multiplier: float, layer: str) -> tuple[int, int]:
    """(M, s) with multiplier = M * 2^-(31 + s), M in [2^30, 2^31), s in [0, 31]."""
    fraction, exponent = math.frexp(float(multiplier))
    m = int(np.rint(fraction * 2**31))
    if m == 2**31:
        m, exponent = 2**30, exponent + 1
    if not 0 <= -exponent <= 31:
        raise NncgError(
            f"layer {layer} scales its result by {multiplier:g}, which the fixed-point form cannot hold "
            "(it takes scales in [2^-32, 1)): compile with --requantize float"
        )
    return m, -exponent


class Scales:
    """The multipliers of one layer (one per output channel, or one), as the form reads them:
    literals when all are equal, else constant arrays indexed by the channel."""

    def __init__(self, ctx: LoweringContext, layer: str, multipliers: np.ndarray):
        multipliers = np.asarray(multipliers, np.float32).reshape(-1)
        self.fixed = ctx.requantize == "fixed"
        self.uniform = bool(np.all(multipliers == multipliers[0]))
        values = multipliers[:1] if self.uniform else multipliers
        if self.fixed:
            pairs = np.array([fixed_point(m, layer) for m in values], dtype=np.int32).reshape(-1, 2)
            self.operands = [pairs[:, 0], pairs[:, 1]]
        else:
            self.operands = [values]
        if not self.uniform:
            names = ("qm", "qs") if self.fixed else ("m",)
            self.refs = [ctx.add_constant(f"{n}_{layer}", a) for n, a in zip(names, self.operands)]

    def _operand(self, i: int, channel: Affine) -> Expr:
        if self.uniform:
            value = self.operands[i][0]
            return Const.integer(int(value)) if self.fixed else Const.splat(float(value))
        return Load(self.refs[i].buffer, self.refs[i].at([channel]))

    def requantized(self, acc: Expr, channel: Affine, out: Requantization) -> Expr:
        """The int32 `acc` of output channel `channel` as the output type."""
        if self.fixed:
            return RequantizeFixed(
                acc, self._operand(0, channel), self._operand(1, channel), out.zero_point, out.low, out.high, out.dtype
            )
        scaled = Binary("*", Cast(DType.FLOAT32, acc), self._operand(0, channel))
        return Requantize(scaled, out.zero_point, out.low, out.high, out.dtype)
