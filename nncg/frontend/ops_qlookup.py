"""ONNX front end: unary ops on int8/uint8 tensors as 256-entry tables computed at generation time,
the way onnxruntime's QLinearLeakyRelu and QLinearSigmoid (com.microsoft) build theirs
(contrib_ops/cpu/quantization/qlinear_lookup_table.cc), so the results match to the bit: each input
value x dequantised in float32 as x_scale * (x - x_zero_point), the op applied in float32, the
result quantised as QuantizeLinear does (divided by y_scale, rounded half to even, plus the zero
point, saturated). qdq.py rewrites a LeakyRelu or Sigmoid between a DequantizeLinear and a
QuantizeLinear into these ops, as onnxruntime's QDQ transformer does, and a HardSwish or Tanh into
NNCG's own QLinearHardSwish or QLinearTanh: onnxruntime runs those in float between their
DequantizeLinear and QuantizeLinear, which on one 8-bit input is such a table too (Tanh is MLAS's
rational approximation, evaluated as for Sigmoid).

Sigmoid is MLAS's logistic (core/mlas/lib/logistic.cpp): the input clamped to [-18, 18], Eigen's
rational polynomial p(x) / q(x) + 0.5, the result clamped below at 0. onnxruntime's x86-64 kernel
(LogisticKernelFma3) and its AArch64 one evaluate the polynomials with fused multiply-adds, which
is what the table does (each fma rounded once, exactly); a build of onnxruntime for x86 without
FMA3 rounds the products separately and may differ in rare entries by a step."""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_quantized import quantization, quantize
from nncg.ir.graph import Node, QLookupAttrs
from nncg.ir.kinds import DType

F32 = np.float32
LOGISTIC_RANGE, TANH_RANGE = F32(18.0), F32(9.0)
# Eigen's coefficients, as MLAS holds them (float32)
LOGISTIC_ALPHA = tuple(F32(a) for a in (4.37031012579801e-11, 1.15627324459942e-07, 6.08574864600143e-05,
                                          8.51377133304701e-03, 2.48287947061529e-01))  # fmt: skip
LOGISTIC_BETA = tuple(F32(b) for b in (6.10247389755681e-13, 5.76102136993427e-09, 6.29106785017040e-06,
                                         1.70198817374094e-03, 1.16817656904453e-01, 9.93151921023180e-01))  # fmt: skip
TANH_ALPHA = tuple(F32(a) for a in (-2.76076847742355e-16, 2.00018790482477e-13, -8.60467152213735e-11,
                                      5.12229709037114e-08, 1.48572235717979e-05, 6.37261928875436e-04,
                                      4.89352455891786e-03))  # fmt: skip
TANH_BETA = tuple(F32(b) for b in (1.19825839466702e-06, 1.18534705686654e-04, 2.26843463243900e-03,
                                     4.89352518554385e-03))  # fmt: skip


def lookup_table(
    function: Callable[[np.float32], np.float32],
    x: tuple[float, int, DType],
    y: tuple[float, int, DType],
) -> np.ndarray:
    """function's table from (scale, zero point, dtype) of input and output: entry i for input value
    x_low + i, of the output's type."""
    x_scale, x_zero, x_dtype = x
    y_scale, y_zero, y_dtype = y
    low, high = x_dtype.range
    entries = [
        quantize(float(function(F32(x_scale) * F32(value - x_zero))), y_scale, y_zero, y_dtype)
        for value in range(low, high + 1)
    ]
    return np.array(entries, dtype=y_dtype.value)


def leaky_relu(alpha: float) -> Callable[[np.float32], np.float32]:
    return lambda v: v if v >= 0 else F32(alpha) * v


def hard_swish(v: np.float32) -> np.float32:
    """ONNX's HardSwish, x * max(0, min(1, x / 6 + 0.5)), in float32 (onnxruntime's float kernel;
    its float rounding cannot move a table entry, which the tests check on every entry)."""
    return v * min(max(v * F32(1 / 6) + F32(0.5), F32(0)), F32(1))


def logistic(v: np.float32) -> np.float32:
    """MLAS's logistic of one float32, with fused multiply-adds, clamped below at 0."""
    return max(F32(0), _rational(v, LOGISTIC_RANGE, LOGISTIC_ALPHA, LOGISTIC_BETA) + F32(0.5))


def tanh(v: np.float32) -> np.float32:
    """MLAS's tanh of one float32 (core/mlas/lib/tanh.cpp), with fused multiply-adds."""
    return _rational(v, TANH_RANGE, TANH_ALPHA, TANH_BETA)


def _rational(v: np.float32, bound: np.float32, alpha: tuple, beta: tuple) -> np.float32:
    """Eigen's x * p(x^2) / q(x^2) of x = v clamped to [-bound, bound], by Horner's rule in fused
    multiply-adds (highest coefficient first), as MLAS's FMA3 kernels compute it."""
    x = min(max(v, -bound), bound)
    square = x * x
    p = _fma(square, alpha[0], alpha[1])
    for a in alpha[2:]:
        p = _fma(square, p, a)
    q = _fma(square, beta[0], beta[1])
    for b in beta[2:]:
        q = _fma(square, q, b)
    return (x * p) / q


def _fma(a: np.float32, b: np.float32, c: np.float32) -> np.float32:
    """a * b + c rounded once to float32 (to nearest, ties to even), computed exactly."""
    exact = Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c))
    near = F32(float(exact))
    candidates = (near, np.nextafter(near, F32(np.inf)), np.nextafter(near, F32(-np.inf)))
    return min(candidates, key=lambda f: (abs(Fraction(float(f)) - exact), int(f.view(np.uint32)) & 1))


def _lookup(op: OnnxOp, ctx: Context, function_name: str, function: Callable) -> Node:
    """QLinearLeakyRelu, QLinearSigmoid: X, X_scale, X_zero_point, Y_scale, Y_zero_point."""
    x = op.input(0)
    x_quantization = quantization(op, ctx, 1, "input")
    y_quantization = quantization(op, ctx, 3, "output")
    table = lookup_table(function, x_quantization, y_quantization)
    ctx.set_shape(op, op.node.output[0], ctx.shape(x))
    lut = ctx.add_constant(f"{op.node.output[0]}_lut", table)
    return op.ir_node("QLinearLookup", [x, lut], QLookupAttrs(function_name, y_quantization[2]))


def convert_qlinear_leaky_relu(op: OnnxOp, ctx: Context) -> Node:
    return _lookup(op, ctx, "LeakyRelu", leaky_relu(float(op.attr("alpha", 0.01))))


def convert_qlinear_sigmoid(op: OnnxOp, ctx: Context) -> Node:
    return _lookup(op, ctx, "Sigmoid", logistic)


def convert_qlinear_hard_swish(op: OnnxOp, ctx: Context) -> Node:
    """What qdq.py writes for a HardSwish (opset 14) between DequantizeLinear and QuantizeLinear."""
    return _lookup(op, ctx, "HardSwish", hard_swish)


def convert_qlinear_tanh(op: OnnxOp, ctx: Context) -> Node:
    """What qdq.py writes for a Tanh between DequantizeLinear and QuantizeLinear."""
    return _lookup(op, ctx, "Tanh", tanh)
