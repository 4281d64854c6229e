"""Activations applied where a value is stored: a max for ReLU, a max or conditional move for leaky,
max and min for Clip (ReLU6) and the hard sigmoids; sigmoid, SiLU, tanh, ELU, erf and GELU through math
function calls (math.h or a helper in scalar code, polynomials on vectors)."""

from __future__ import annotations

import math

from ..ir.graph import Activation
from ..ir.loops import Binary, Call, Const, Expr, Select


def apply_activation(value: Expr, act: Activation | None) -> Expr:
    if act is None:
        return value
    return ACTIVATIONS[act.kind](value, act)


def _splat(x: float, like: Expr) -> Const:
    return Const.splat(x, like.lanes)


def _relu(value: Expr, _act: Activation) -> Expr:
    return Binary("max", value, _splat(0.0, value))


def _clip(value: Expr, act: Activation) -> Expr:
    if act.low != float("-inf"):  # an infinite bound clips nothing
        value = Binary("max", value, _splat(act.low, value))
    if act.high != float("inf"):
        value = Binary("min", value, _splat(act.high, value))
    return value


def _leaky_relu(value: Expr, act: Activation) -> Expr:
    scaled = Binary("*", value, _splat(act.alpha, value))
    # For 0 <= alpha <= 1, leaky(x) = max(x, alpha*x): one max instruction on SIMD targets; for
    # alpha > 1 it is the min. Other slopes need the conditional move.
    if 0.0 <= act.alpha <= 1.0:
        return Binary("max", value, scaled)
    if act.alpha > 1.0:
        return Binary("min", value, scaled)
    return Select(">", value, _splat(0.0, value), value, scaled)


def _sigmoid(value: Expr, _act: Activation) -> Expr:
    # Scalar code prints 1 / (1 + exp(0 - x)); vectors call one function (exp, add and divide).
    return Call("sigmoid", value)


def _tanh(value: Expr, _act: Activation) -> Expr:
    return Call("tanh", value)


def _hard_sigmoid(value: Expr, act: Activation) -> Expr:
    line = Binary("+", Binary("*", value, _splat(act.alpha, value)), _splat(act.beta, value))
    return Binary("max", Binary("min", line, _splat(1.0, value)), _splat(0.0, value))


def _hard_swish(value: Expr, act: Activation) -> Expr:
    return Binary("*", value, _hard_sigmoid(value, act))


def _elu(value: Expr, act: Activation) -> Expr:
    # Both sides are computed (a conditional move); exp of a large positive x is inf, never chosen.
    negative = Binary("*", Binary("-", Call("exp", value), _splat(1.0, value)), _splat(act.alpha, value))
    return Select(">", value, _splat(0.0, value), value, negative)


def _silu(value: Expr, act: Activation) -> Expr:
    return Binary("*", value, _sigmoid(value, act))


def _erf(value: Expr, _act: Activation) -> Expr:
    return Call("erf", value)


def _gelu(value: Expr, act: Activation) -> Expr:
    return _gelu_tanh(value) if act.approximate == "tanh" else _gelu_exact(value)


def _gelu_exact(x: Expr) -> Expr:
    """0.5 x (1 + erf(x / sqrt(2)))."""
    gate = Binary("+", _splat(1.0, x), Call("erf", Binary("*", x, _splat(math.sqrt(0.5), x))))
    return Binary("*", Binary("*", x, _splat(0.5, x)), gate)


# 2u = 2 sqrt(2/pi) (x + 0.044715 x^3) = x (LINEAR + CUBIC x^2)
GELU_TANH_LINEAR = 2 * math.sqrt(2 / math.pi)
GELU_TANH_CUBIC = GELU_TANH_LINEAR * 0.044715


def _gelu_tanh(x: Expr) -> Expr:
    """0.5 x (1 + tanh(u)), u = sqrt(2/pi) (x + 0.044715 x^3), computed as the equal x sigmoid(2u):
    no cancellation in 1 + tanh(u) where x is negative and the result tiny."""
    square = Binary("*", x, x)
    twice_u = Binary("*", x, Binary("+", _splat(GELU_TANH_LINEAR, x), Binary("*", _splat(GELU_TANH_CUBIC, x), square)))
    return Binary("*", x, Call("sigmoid", twice_u))


ACTIVATIONS = {
    "relu": _relu,
    "clip": _clip,
    "leaky_relu": _leaky_relu,
    "sigmoid": _sigmoid,
    "tanh": _tanh,
    "hard_sigmoid": _hard_sigmoid,
    "hard_swish": _hard_swish,
    "elu": _elu,
    "silu": _silu,
    "erf": _erf,
    "gelu": _gelu,
}
