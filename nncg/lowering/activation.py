"""Activations applied where a value is stored: a max for ReLU, a max or conditional move for leaky,
max and min for Clip (ReLU6)."""

from __future__ import annotations

from ..ir.graph import Activation
from ..ir.loops import Binary, Const, Expr, Select


def apply_activation(value: Expr, act: Activation | None) -> Expr:
    if act is None:
        return value
    zero = Const.splat(0.0, value.lanes)
    if act.kind == "relu":
        return Binary("max", value, zero)
    if act.kind == "clip":  # an infinite bound clips nothing
        if act.low != float("-inf"):
            value = Binary("max", value, Const.splat(act.low, value.lanes))
        if act.high != float("inf"):
            value = Binary("min", value, Const.splat(act.high, value.lanes))
        return value
    scaled = Binary("*", value, Const.splat(act.alpha, value.lanes))
    # For 0 <= alpha <= 1, leaky(x) = max(x, alpha*x): one max instruction on SIMD targets; for
    # alpha > 1 it is the min. Other slopes need the conditional move.
    if 0.0 <= act.alpha <= 1.0:
        return Binary("max", value, scaled)
    if act.alpha > 1.0:
        return Binary("min", value, scaled)
    return Select(">", value, zero, value, scaled)
