"""ONNX front end (ONNX -> graph IR), step 3: convert Gemm and MatMul into Dense and keep
Add/Sub/Mul/Div as they are. Constant operands are folded (alpha, beta and transB into new
constants w [K, N] and b [N]); operands computed at runtime are kept and DenseAttrs says how to
read them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.ir.graph import DenseAttrs, Node, ReshapeAttrs


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


def convert_matmul(op: OnnxOp, ctx: Context) -> Node | tuple[Node, ...]:
    """A @ B with either operand computed at runtime; batch dims broadcast (NumPy rules). A 1-D A is a
    row [1, K] and a 1-D B a column [K, 1] (Reshapes, views), the dim they add removed from the
    product by a Reshape (a view)."""
    a, b = op.input(0), op.input(1)
    a_shape, b_shape = ctx.shape(a), ctx.shape(b)
    if len(a_shape) > 1 and len(b_shape) > 1:
        return op.ir_node("Dense", [a, b], DenseAttrs())
    nodes = []
    if len(a_shape) == 1:
        a, node = _as_matrix(op, ctx, a, (1, *a_shape), "row")
        nodes += node
    if len(b_shape) == 1:
        b, node = _as_matrix(op, ctx, b, (*b_shape, 1), "column")
        nodes += node
    m_k, k_n = ctx.shape(a), ctx.shape(b)
    if m_k[-1] != k_n[-2]:
        raise op.error(f"multiplies shapes {list(a_shape)} and {list(b_shape)}, whose inner dims differ")
    product_shape = (*_broadcast_batch(op, m_k[:-2], k_n[:-2]), m_k[-2], k_n[-1])
    product = ctx.intermediate(op, "product", product_shape)
    dropped = {len(product_shape) - 2} if len(a_shape) == 1 else set()
    dropped |= {len(product_shape) - 1} if len(b_shape) == 1 else set()
    out = tuple(n for d, n in enumerate(product_shape) if d not in dropped)
    ctx.set_shape(op, op.node.output[0], out)
    return (
        *nodes,
        op.ir_step("Dense", "product", [a, b], product, DenseAttrs()),
        op.ir_node("Reshape", [product], ReshapeAttrs(out)),
    )


def _as_matrix(op: OnnxOp, ctx: Context, value: str, shape: tuple[int, ...], step: str) -> tuple[str, list[Node]]:
    """A 1-D operand as a matrix of `shape`: a reshaped constant, or a Reshape node."""
    constant = ctx.const(value)
    if constant is not None:
        return ctx.add_constant(f"{op.name}_{step}", constant.reshape(shape)), []
    matrix = ctx.intermediate(op, step, shape)
    return matrix, [op.ir_step("Reshape", step, [value], matrix, ReshapeAttrs(shape))]


def _broadcast_batch(op: OnnxOp, a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...]:
    try:
        return tuple(int(d) for d in np.broadcast_shapes(a, b))
    except ValueError:
        raise op.error(f"has batch dims {list(a)} and {list(b)}, which do not broadcast together") from None


def convert_binary(op: OnnxOp, ctx: Context) -> Node:
    """Add/Sub/Mul/Div keep NumPy broadcasting; either side may be constant (not both: folded)."""
    return op.ir_node(op.type, [op.input(0), op.input(1)])
