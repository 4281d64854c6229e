"""Analyses of the loop-nest IR that several loop passes share (and that must not live in one pass
for another to import against pipeline order): accumulators, vector instruction counts."""

from __future__ import annotations

from .loops import Let, Loop, Stmt, walk_stmts


def is_accumulator(stmt: Stmt) -> bool:
    """A local summed up by a loop below it: a reduction's accumulator."""
    return isinstance(stmt, Let) and any(isinstance(s, Loop) for s in walk_stmts(stmt.body))


def holds_accumulators(loop: Loop) -> bool:
    """Whether an accumulator lives inside the loop."""
    return any(is_accumulator(s) for s in walk_stmts(loop.body))


def vector_instructions(extent: int, widths: tuple[int, ...]) -> int:
    """Blocks of the widest width that fits, then narrower ones, then scalars (as materialize splits)."""
    count = 0
    for width in widths:
        count += extent // width
        extent %= width
    return count + extent
