"""Backend: legalisation before printing — rewrites of the loop-nest IR into the nodes a target
prints best, decided by its Target. Not a pass: the pipeline text (the .c's first line) is unchanged."""

from __future__ import annotations

from dataclasses import replace

from ..ir.dtypes import buffer_dtypes, expr_dtype
from ..ir.kinds import DType
from ..ir.loops import Binary, Expr, Fma, Kernel, Program, map_body, map_stmt_exprs
from ..ir.target import Target


def fuse_multiply_add(program: Program, target: Target) -> Program:
    """Every vector `a * b + c` (either operand of the add a multiply; the left one if both) becomes
    one Fma where the target has fused multiply-add (float only: an int32 product stays as it is).
    Scalar code is left to the C compiler."""
    if not target.fma:
        return program
    dtypes = buffer_dtypes(program)
    kernels = tuple(_fused(kernel, target, dtypes) for kernel in program.kernels)
    return replace(program, kernels=kernels)


def _fused(kernel: Kernel, target: Target, dtypes: dict[str, DType]) -> Kernel:
    def in_expr(e: Expr) -> Expr:
        if not (isinstance(e, Binary) and e.op == "+" and e.lanes in target.vector_widths):
            return e
        for product, addend in ((e.a, e.b), (e.b, e.a)):
            if isinstance(product, Binary) and product.op == "*" and expr_dtype(product, dtypes, {}) == DType.FLOAT32:
                return Fma(product.a, product.b, addend)
        return e

    return replace(kernel, body=map_body(kernel.body, lambda stmt: map_stmt_exprs(stmt, in_expr)))
