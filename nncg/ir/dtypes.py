"""Data types in both IRs. A graph value's dtype is its producer's (Graph.dtypes lists the values
that are not float32); a loop-IR expression's follows from its leaves: a Load has its buffer's, a
local its declaration's, a Const, Cast or Requantize says its own, and every other node has its
operands' (the verifier checks that they agree)."""

from __future__ import annotations

from collections.abc import Mapping

from .kinds import DType
from .loops import (
    Binary,
    Broadcast,
    Call,
    Cast,
    Const,
    Dot,
    Expr,
    Fma,
    Kernel,
    Load,
    LocalRef,
    Lookup,
    Program,
    Requantize,
    RequantizeFixed,
    Select,
    Store,
    read_buffer,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)

FLOAT32 = DType.FLOAT32


def expr_dtype(expr: Expr, buffers: Mapping[str, DType], locals_: Mapping[str, DType]) -> DType:
    """The dtype of an expression, given the dtypes of the buffers and of the locals in scope."""
    if isinstance(expr, Const | Cast | Requantize | RequantizeFixed):
        return expr.dtype
    if isinstance(expr, Load | Lookup):
        return buffers.get(read_buffer(expr), FLOAT32)
    if isinstance(expr, LocalRef):
        return locals_.get(expr.name, FLOAT32)
    if isinstance(expr, Broadcast):
        return expr_dtype(expr.value, buffers, locals_)
    if isinstance(expr, Binary):
        return expr_dtype(expr.a, buffers, locals_)
    if isinstance(expr, Select):
        return expr_dtype(expr.then, buffers, locals_)
    if isinstance(expr, Call | Fma):
        return FLOAT32
    if isinstance(expr, Dot):
        return DType.INT32
    raise TypeError(f"not a loop-IR expression: {expr!r}")


def buffer_dtypes(program: Program) -> dict[str, DType]:
    return {b.name: b.dtype for b in program.buffers}


def is_integer_program(program: Program) -> bool:
    """Whether any buffer holds integers: the C file then needs the integer typedefs."""
    return any(b.dtype != FLOAT32 for b in program.buffers)


def is_integer_kernel(kernel: Kernel, program: Program) -> bool:
    """Whether the kernel reads or writes an integer buffer: the vector passes leave it scalar."""
    integer = {b.name for b in program.buffers if b.dtype != FLOAT32}
    stmts = list(walk_stmts(kernel.body))
    touched = {s.buffer for s in stmts if isinstance(s, Store)}
    touched |= {e.buffer for s in stmts for top in stmt_exprs(s) for e in walk_exprs(top) if isinstance(e, Load)}
    return bool(touched & integer)
