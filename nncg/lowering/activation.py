"""Activations applied where a value is stored: a max for ReLU, a max or conditional move for leaky,
max and min for Clip (ReLU6) and the hard sigmoids; sigmoid, SiLU, tanh, ELU, erf, GELU, abs, sqrt,
exp, log, softplus and what is made of them through math function calls (math.h or a helper in
scalar code, polynomials and instructions on vectors); Pow by a constant exponent as products, a
square root or exp(y log x)."""

from __future__ import annotations

import math
from collections.abc import Callable

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


def _call(fn: str) -> Callable[[Expr, Activation], Expr]:
    return lambda value, _act: Call(fn, value)


def _neg(value: Expr, _act: Activation) -> Expr:
    return Binary("*", value, _splat(-1.0, value))  # exact, and -(+0) = -0


def _reciprocal(value: Expr, _act: Activation) -> Expr:
    return Binary("/", _splat(1.0, value), value)


def _pow(x: Expr, act: Activation) -> Expr:
    """x^alpha as ONNX (C's pow) has it: the common exponents as products, a square root or a
    reciprocal; others as exp(alpha log x), which is NaN for a negative x, and for an integer alpha
    from |x|, with x's sign restored for an odd one: x |x|^(alpha - 1), or 1/x |x|^(alpha + 1) below 0
    (so pow(-0, odd) keeps its sign). Unlike pow, -Inf to an exponent that is no integer is NaN, and
    sqrt(-0) = -0."""
    y = act.alpha
    special = {
        0.0: lambda: _splat(1.0, x),
        0.5: lambda: Call("sqrt", x),
        -0.5: lambda: _reciprocal(Call("sqrt", x), act),
        1.0: lambda: x,
        -1.0: lambda: _reciprocal(x, act),
        2.0: lambda: Binary("*", x, x),
        3.0: lambda: Binary("*", Binary("*", x, x), x),
    }
    if y in special:
        return special[y]()
    if not y.is_integer():
        return _exp_times_log(x, y)
    if y % 2 == 0:
        return _exp_times_log(Call("abs", x), y)
    if y > 0:
        return Binary("*", x, _exp_times_log(Call("abs", x), y - 1))
    return Binary("*", _reciprocal(x, act), _exp_times_log(Call("abs", x), y + 1))


def _exp_times_log(x: Expr, y: float) -> Expr:
    """exp(y log x)."""
    return Call("exp", Binary("*", Call("log", x), _splat(y, x)))


def _softsign(value: Expr, _act: Activation) -> Expr:
    return Binary("/", value, Binary("+", _splat(1.0, value), Call("abs", value)))


def _mish(value: Expr, _act: Activation) -> Expr:
    return Binary("*", value, Call("tanh", Call("softplus", value)))


def _selu(value: Expr, act: Activation) -> Expr:
    """gamma x above 0, gamma alpha (exp(x) - 1) elsewhere."""
    negative = Binary("*", Binary("-", Call("exp", value), _splat(1.0, value)), _splat(act.gamma * act.alpha, value))
    return Select(">", value, _splat(0.0, value), Binary("*", value, _splat(act.gamma, value)), negative)


def _celu(value: Expr, act: Activation) -> Expr:
    """max(0, x) + min(0, alpha (exp(x / alpha) - 1)), as ONNX defines it: right for any alpha's sign."""
    scaled = Call("exp", Binary("/", value, _splat(act.alpha, value)))
    negative = Binary("*", _splat(act.alpha, value), Binary("-", scaled, _splat(1.0, value)))
    return Binary("+", Binary("max", value, _splat(0.0, value)), Binary("min", _splat(0.0, value), negative))


def _thresholded_relu(value: Expr, act: Activation) -> Expr:
    return Select(">", value, _splat(act.alpha, value), value, _splat(0.0, value))


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
    "abs": _call("abs"),
    "neg": _neg,
    "sqrt": _call("sqrt"),
    "exp": _call("exp"),
    "log": _call("log"),
    "reciprocal": _reciprocal,
    "pow": _pow,
    "softplus": _call("softplus"),
    "softsign": _softsign,
    "mish": _mish,
    "selu": _selu,
    "celu": _celu,
    "thresholded_relu": _thresholded_relu,
}
