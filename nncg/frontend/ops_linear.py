"""ONNX front end (ONNX -> graph IR), step 3: convert Gemm and MatMul into Dense and keep
Add/Sub/Mul/Div as they are. Constant operands are folded (alpha, beta and transB into new
constants w [K, N] and b [N]); operands computed at runtime are kept and DenseAttrs says how to
read them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.ir.graph import DenseAttrs, Node
from nncg.safe_text import shown


def convert_gemm(op: OnnxOp, ctx: Context) -> Node:
    """Y = alpha * A' @ B' + beta * C becomes Dense(x=A, w=B', b=C), alpha and beta folded into
    whichever of B and C is constant."""
    a = op.input(0)
    alpha, beta = float(op.attr("alpha", 1.0)), float(op.attr("beta", 1.0))
    trans_a, trans_b = bool(op.attr("transA", 0)), bool(op.attr("transB", 0))
    b_shape = ctx.shape(op.input(1))
    rows, cols = ctx.shape(a)[1 if trans_a else 0], b_shape[0 if trans_b else 1]
    attrs = DenseAttrs(trans_x=trans_a)
    b = ctx.const(op.input(1))
    if b is None:
        inputs = [a, op.input(1)]
        attrs = replace(attrs, trans_w=trans_b, alpha=alpha)
    else:
        w = b.T if trans_b else b
        w = np.ascontiguousarray(w * np.float32(alpha) if alpha != 1.0 else w, dtype=np.float32)
        inputs = [a, ctx.add_constant(f"{op.name}_w", w)]
    if op.input(2) and beta != 0.0:  # beta == 0 drops C entirely, as the spec's formula does
        c = ctx.const(op.input(2))
        if c is None:
            _check_broadcasts(op, ctx.shape(op.input(2)), rows, cols)
            inputs.append(op.input(2))
            attrs = replace(attrs, beta=beta)
        else:
            inputs.append(ctx.add_constant(f"{op.name}_b", gemm_bias(op, c, rows, cols, beta)))
    return op.ir_node("Dense", inputs, attrs)


def gemm_bias(op: OnnxOp, c: np.ndarray, rows: int, cols: int, beta: float) -> np.ndarray:
    """beta * C as one row [N]; C may broadcast to [M, N] but every row must be the same."""
    _check_broadcasts(op, c.shape, rows, cols)
    full = np.broadcast_to(c, (rows, cols))
    if not np.array_equal(full, np.broadcast_to(full[:1], full.shape)):
        raise op.error(
            f"has C of shape {list(c.shape)} with different rows; only a bias shared by all rows "
            "(scalar, [N] or [1, N]) is supported"
        )
    row = full[0] * np.float32(beta) if beta != 1.0 else full[0]
    return np.ascontiguousarray(row, dtype=np.float32)


def _check_broadcasts(op: OnnxOp, shape: tuple[int, ...], rows: int, cols: int) -> None:
    try:
        ok = np.broadcast_shapes(tuple(shape), (rows, cols)) == (rows, cols)
    except ValueError:
        ok = False
    if not ok:
        raise op.error(f"has C of shape {list(shape)}, which does not broadcast to [{rows}, {cols}]")


def convert_matmul(op: OnnxOp, ctx: Context) -> Node:
    """A @ B with either operand computed at runtime; batch dims broadcast (NumPy rules)."""
    for index, role in enumerate("AB"):
        if len(ctx.shape(op.input(index))) < 2:
            raise op.error(f"has a 1-D input {role} {shown(op.input(index))}; only inputs of rank >= 2 are supported")
    return op.ir_node("Dense", [op.input(0), op.input(1)], DenseAttrs())


def convert_binary(op: OnnxOp, ctx: Context) -> Node:
    """Add/Sub/Mul/Div keep NumPy broadcasting; either side may be constant (not both: folded)."""
    return op.ir_node(op.type, [op.input(0), op.input(1)])
