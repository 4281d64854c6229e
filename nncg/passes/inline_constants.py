"""Loop pass `inline-constants`: the paper's "constants wherever possible" (principle 3).

A weight read at an index that is constant (after unrolling) is written as a literal (not the packed
weights of a dot product, which its instruction loads); a constant array that is no longer read at
all is dropped from the program."""

from __future__ import annotations

from dataclasses import replace

from ..ir.kinds import BufferRole, DType
from ..ir.loops import (
    Assign,
    Const,
    Dot,
    Expr,
    Let,
    Load,
    Program,
    Stmt,
    Store,
    children,
    map_body,
    read_buffer,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
    with_children,
)


def inline_constants(program: Program) -> Program:
    data = program.constants

    def literal(e: Expr) -> Expr:
        if isinstance(e, Load) and e.buffer in data and e.index.is_const:
            flat = data[e.buffer].reshape(-1)
            values = flat[e.index.const : e.index.const + e.lanes]
            if values.dtype.kind in "iu":  # integer weights of the int8 path
                return Const(tuple(int(v) for v in values), DType(values.dtype.name))
            return Const(tuple(float(v) for v in values))
        return e

    def inlined(e: Expr) -> Expr:
        if isinstance(e, Dot):
            return replace(e, x=tuple(inlined(x) for x in e.x))
        return literal(with_children(e, tuple(inlined(c) for c in children(e))))

    def in_stmt(stmt: Stmt) -> Stmt:
        if isinstance(stmt, Store | Assign):
            return replace(stmt, value=inlined(stmt.value))
        return replace(stmt, init=inlined(stmt.init)) if isinstance(stmt, Let) else stmt

    kernels = tuple(replace(k, body=map_body(k.body, in_stmt)) for k in program.kernels)
    read = {
        read_buffer(e) for k in kernels for s in walk_stmts(k.body) for top in stmt_exprs(s) for e in walk_exprs(top)
    }
    buffers = tuple(b for b in program.buffers if b.role != BufferRole.CONSTANT or b.name in read)
    constants = {name: arr for name, arr in data.items() if name in read}
    return replace(program, buffers=buffers, kernels=kernels, constants=constants)
