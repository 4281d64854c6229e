"""Loop pass `unroll{level=K}`: the paper's unroll levels (principle 1).

Level K keeps the K outermost loops of each kernel's nest and unrolls all loops inside them; level 0
unrolls everything; `none` unrolls nothing. Choice and mechanism are apart: `mark_unroll` decides
(a tuner may mark loops its own way), `expand_unrolled` materialises whatever is marked. Border
checks that unrolling made redundant are pruned."""

from __future__ import annotations

from dataclasses import replace

from ..ir.loops import Affine, If, Let, Loop, Program, Stmt
from .substitute import prune_bounds, substitute_body


def unroll(program: Program, level: int | None = 1) -> Program:
    kernels = tuple(replace(k, body=prune_bounds(expand_unrolled(mark_unroll(k.body, level)))) for k in program.kernels)
    return replace(program, kernels=kernels)


def mark_unroll(body: tuple[Stmt, ...], level: int | None, depth: int = 0) -> tuple[Stmt, ...]:
    """Marks every loop at nesting depth >= level (counted in loops, from 0) as unrolled."""
    if level is None:
        return body
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop):
            inner = mark_unroll(stmt.body, level, depth + 1)
            kind = "unrolled" if depth >= level else stmt.kind
            stmt = replace(stmt, body=inner, kind=kind)
        elif isinstance(stmt, Let | If):
            stmt = replace(stmt, body=mark_unroll(stmt.body, level, depth))
        out.append(stmt)
    return tuple(out)


def expand_unrolled(body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    """Replaces each loop marked unrolled by one copy of its body per iteration."""
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop | Let | If):
            stmt = replace(stmt, body=expand_unrolled(stmt.body))
        if isinstance(stmt, Loop) and stmt.kind == "unrolled":
            for i in range(stmt.extent):
                out.extend(substitute_body(stmt.body, {stmt.var: Affine.of(i)}))
        else:
            out.append(stmt)
    return tuple(out)
