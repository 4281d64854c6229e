"""Backend: what a program's vector code calls besides intrinsics — helper definitions, vector math
functions, tables of constant vectors — collected by one walk over the IR before printing."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

from ..ir.loops import (
    Binary,
    Broadcast,
    Call,
    Const,
    Expr,
    Fma,
    Load,
    Program,
    Select,
    Store,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from .vector_math import has_vector_math, operations_used, with_callees
from .vector_width import VectorWidth


@dataclass(frozen=True)
class Needs:
    """definitions: (lanes, operation) whose template calls a helper the width defines, in order of
    first use (kernels in order, statements in order, an expression before its operands).
    math: (lanes, fn) of the math functions called on vectors (not those they call).
    rows: per width, the row of each constant vector in its table, in order of first use."""

    definitions: tuple[tuple[int, str], ...] = ()
    math: frozenset[tuple[int, str]] = frozenset()
    rows: Mapping[int, Mapping[tuple[float, ...], int]] = field(default_factory=dict)


def collect_needs(program: Program, widths: Mapping[int, VectorWidth]) -> Needs:
    """The needs of every vector node of `program` whose width is in `widths` (others are the
    printer's to refuse)."""
    definitions: dict[tuple[int, str], None] = {}  # an ordered set
    math: set[tuple[int, str]] = set()
    rows: dict[int, dict[tuple[float, ...], int]] = {}
    for lanes, node in _vector_nodes(program, widths):
        width = widths[lanes]
        definitions |= {(lanes, op): None for op in operations(node, width) if op in width.helpers}
        if isinstance(node, Call):
            if (lanes, node.fn) not in math and has_vector_math(width):  # the helper's own operations
                used = [op for fn in with_callees({node.fn}) for op in operations_used(fn, width)]
                definitions |= {(lanes, op): None for op in used if op in width.helpers}
            math.add((lanes, node.fn))
        elif isinstance(node, Const) and _in_table(node, width):
            table = rows.setdefault(lanes, {})
            table.setdefault(node.values, len(table))  # == on floats: 0.0 and -0.0 share a row
    return Needs(tuple(definitions), frozenset(math), rows)


def operations(node: Expr | Store, width: VectorWidth) -> tuple[str, ...]:
    """The operations of `width`'s template table that print `node` (a Store: its store)."""
    if isinstance(node, Store):
        return ("store",)
    if isinstance(node, Load):
        return ("load",)
    if isinstance(node, Const):
        return ("splat",) if node.is_splat else ("load",) if _in_table(node, width) else ("vector",)
    if isinstance(node, Broadcast):
        return ("splat",)
    if isinstance(node, Binary):
        return (node.op,)
    if isinstance(node, Fma):
        fused = tuple(op for op in ("fma", "fma_exact") if op in width.ops)
        return fused[:1] or ("*", "+")
    if isinstance(node, Select):
        return (node.cmp,)
    return ()  # a local; a call goes to a math helper


def _in_table(const: Const, width: VectorWidth) -> bool:
    """Whether a constant vector is a row of the width's table: it is a float vector, not a splat, and
    the width has no template that spells a vector lane by lane (integer vectors have `ints` `vector`)."""
    return not const.is_splat and "vector" not in width.ops and not const.dtype.is_integer


def _vector_nodes(program: Program, widths: Mapping[int, VectorWidth]) -> Iterator[tuple[int, Expr | Store]]:
    """(lanes, node) of every vector store and expression, in the order the printer meets them."""
    for kernel in program.kernels:
        for stmt in walk_stmts(kernel.body):
            if isinstance(stmt, Store) and stmt.value.lanes in widths:
                yield stmt.value.lanes, stmt
            for top in stmt_exprs(stmt):
                for e in walk_exprs(top):
                    if e.lanes in widths:
                        yield e.lanes, e
