"""Part of the loop pass `vectorize`, before dot_product.py: on targets whose dot products take a
depthwise convolution's taps (Target.tap_dots), the output columns whose taps all lie inside the image
are split from the border columns, so that their loop over kernel columns is a plain
multiply-accumulate the dot-product rewrite recognises:

    for ow < W: ... for kw < KW: if 0 <= ow + kw - p < Wi: acc += int32(x) * int32(w)
becomes
    ow = 0, ..., first - 1: as before, ow a constant;  ow in [first, last): for kw < KW: acc += ...;
    ow = last, ..., W - 1: as before, ow a constant

Only loops guarding such a reduction are split (nothing changes for other kernels or targets). Each
border column is its own straight-line code, so that its check depends on kw alone: dot_product.py
then knows which taps lie outside and takes the column's taps as dots too, those taps read as 0."""

from __future__ import annotations

from dataclasses import replace

from ..ir.loops import If, Let, Loop, Program, Stmt, walk_stmts
from ..ir.target import Target
from .dot_product import multiply_accumulate
from .substitute import interior, iterations


def split_tap_borders(program: Program, kernels: set[str], target: Target) -> Program:
    """The named kernels with their guarded tap reductions' interior columns split off."""
    if not target.tap_dots:
        return program
    out = tuple(replace(k, body=_split(k.body)) if k.name in kernels else k for k in program.kernels)
    return replace(program, kernels=out)


def _split(body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop) and stmt.parallel and _guards_taps(stmt):
            first, last = interior(stmt)
            if last > first:
                out += _columns(stmt, 0, first)
                out += iterations(stmt, first, last, prune=True)
                out += _columns(stmt, last, stmt.extent)
                continue
        if isinstance(stmt, Loop | Let | If):
            stmt = replace(stmt, body=_split(stmt.body))
        out.append(stmt)
    return tuple(out)


def _columns(loop: Loop, start: int, stop: int) -> tuple[Stmt, ...]:
    """Iterations [start, stop) of `loop`, each its own straight-line code (the border columns: few)."""
    return tuple(s for i in range(start, stop) for s in iterations(loop, i, i + 1))


def _guards_taps(loop: Loop) -> bool:
    """Whether a reduction loop inside `loop` is `if (check on loop's variable) acc += int32(x) *
    int32(w)`, x varying with more than the reduction (a depthwise's taps or a convolution's channels)."""
    for stmt in walk_stmts(loop.body):
        if not (isinstance(stmt, Loop) and not stmt.parallel and len(stmt.body) == 1):
            continue
        guard = stmt.body[0]
        if not isinstance(guard, If) or not any(b.expr.coeff(loop.var) for b in guard.bounds):
            continue
        if multiply_accumulate(replace(stmt, body=guard.body)) is not None:
            return True
    return False
