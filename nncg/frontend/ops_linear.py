"""ONNX front end (ONNX -> graph IR), step 3: convert Gemm and MatMul into Dense (alpha, beta and
transB folded into new constants w [K, N] and b [N]) and keep Add/Sub/Mul/Div as they are.
"""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.ir.graph import DenseAttrs, Node


def convert_gemm(op: OnnxOp, ctx: Context) -> Node:
    """Y = alpha * A' @ B' + beta * C becomes Dense(x=A, w=alpha * B', b=beta * C row)."""
    a = op.input(0)
    _require_runtime_x(op, ctx, a)
    b = ctx.constant_input(op, 1, "weight B")
    alpha, beta = float(op.attr("alpha", 1.0)), float(op.attr("beta", 1.0))
    trans_a = bool(op.attr("transA", 0))
    w = b.T if op.attr("transB", 0) else b
    w = np.ascontiguousarray(w * np.float32(alpha) if alpha != 1.0 else w, dtype=np.float32)
    inputs = [a, ctx.add_constant(f"{op.name}_w", w)]
    if op.input(2) and beta != 0.0:  # beta == 0 drops C entirely, as the spec's formula does
        a_shape = ctx.shape(a)
        rows = a_shape[1] if trans_a else a_shape[0]
        bias = gemm_bias(op, ctx.constant_input(op, 2, "bias C"), rows, w.shape[1], beta)
        inputs.append(ctx.add_constant(f"{op.name}_b", bias))
    return op.ir_node("Dense", inputs, DenseAttrs(trans_x=trans_a))


def gemm_bias(op: OnnxOp, c: np.ndarray, rows: int, cols: int, beta: float) -> np.ndarray:
    """beta * C as one row [N]; C may broadcast to [M, N] but every row must be the same."""
    try:
        full = np.broadcast_to(c, (rows, cols))
    except ValueError:
        raise op.error(f"has C of shape {list(c.shape)}, which does not broadcast to [{rows}, {cols}]") from None
    if not np.array_equal(full, np.broadcast_to(full[:1], full.shape)):
        raise op.error(
            f"has C of shape {list(c.shape)} with different rows; only a bias shared by all rows "
            "(scalar, [N] or [1, N]) is supported"
        )
    row = full[0] * np.float32(beta) if beta != 1.0 else full[0]
    return np.ascontiguousarray(row, dtype=np.float32)


def convert_matmul(op: OnnxOp, ctx: Context) -> Node:
    a = op.input(0)
    _require_runtime_x(op, ctx, a)
    w = ctx.constant_input(op, 1, "weight B")
    if w.ndim != 2:
        raise op.error(f"has a {w.ndim}-D weight B; only a 2-D constant B is supported")
    if len(ctx.shape(a)) < 2:
        raise op.error(f"has a 1-D input A '{a}'; only inputs of rank >= 2 are supported")
    return op.ir_node("Dense", [a, op.input(1)], DenseAttrs())


def convert_binary(op: OnnxOp, ctx: Context) -> Node:
    """Add/Sub/Mul/Div keep NumPy broadcasting; either side may be constant (not both: folded)."""
    return op.ir_node(op.type, [op.input(0), op.input(1)])


def _require_runtime_x(op: OnnxOp, ctx: Context, a: str) -> None:
    if ctx.const(a) is not None:
        raise op.error(
            f"has a constant A '{a}' but a runtime B '{op.input(1)}'; only a runtime A times a constant B is supported"
        )
