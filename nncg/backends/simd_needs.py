"""Backend: what a program's vector code calls besides intrinsics — helper definitions, vector math
functions, tables of constant vectors — collected by one walk over the IR before printing."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from itertools import groupby

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
    Stmt,
    Store,
    read_buffer,
    stmt_exprs,
    walk_bodies,
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
    interleaved: (lanes, fn, count) of the helpers computing fn on count vectors at once.
    rows: per width, the row of each constant vector in its table, in order of first use."""

    definitions: tuple[tuple[int, str], ...] = ()
    math: frozenset[tuple[int, str]] = frozenset()
    interleaved: frozenset[tuple[int, str, int]] = frozenset()
    rows: Mapping[int, Mapping[tuple[float, ...], int]] = field(default_factory=dict)


def collect_needs(program: Program, widths: Mapping[int, VectorWidth], interleave: int = 1) -> Needs:
    """The needs of every vector node of `program` whose width is in `widths` (others are the
    printer's to refuse); `interleave` as in interleaved_runs."""
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
    interleaved = {
        (calls[0].lanes, calls[0].fn, len(calls))
        for kernel in program.kernels
        for body in walk_bodies(kernel.body)
        for _, calls in interleaved_runs(body, widths, interleave)
        if calls
    }
    return Needs(tuple(definitions), frozenset(math), frozenset(interleaved), rows)


def interleaved_runs(
    body: tuple[Stmt, ...], widths: Mapping[int, VectorWidth], most: int
) -> Iterator[tuple[tuple[Stmt, ...], tuple[Call, ...]]]:
    """body's statements in order, in groups, each with its calls: up to `most` consecutive Stores each
    of which calls the same math function once on vectors of the same width (a register block's
    epilogue), which the printer computes with one call of an interleaved helper; every other
    statement alone, with no calls. A group computes its calls before its stores, so none may read a
    buffer that one of its stores writes."""
    calls = [math_call(stmt, widths) if most > 1 else None for stmt in body]

    def function(k: int) -> tuple[str, int] | None:
        return (calls[k].fn, calls[k].lanes) if calls[k] else None

    for key, same in groupby(range(len(body)), function):
        at = tuple(same)
        runs = [at[i : i + most] for i in range(0, len(at), most)] if key else [(k,) for k in at]
        for run in runs:
            stores, run_calls = tuple(body[k] for k in run), tuple(calls[k] for k in run)
            if len(run) == 1 or _reads_what_it_writes(stores, run_calls):
                yield from (((store,), ()) for store in stores)
            else:
                yield stores, run_calls


def math_call(stmt: Stmt, widths: Mapping[int, VectorWidth]) -> Call | None:
    """The call of a vector Store's value, when it has one call, of a function its width computes in
    vector code (vector_math.py)."""
    if not isinstance(stmt, Store) or stmt.value.lanes not in widths:
        return None
    calls = [e for e in walk_exprs(stmt.value) if isinstance(e, Call)]
    if len(calls) != 1 or calls[0].lanes not in widths or not has_vector_math(widths[calls[0].lanes]):
        return None
    return calls[0]


def _reads_what_it_writes(stores: tuple[Stmt, ...], calls: tuple[Call, ...]) -> bool:
    written = {store.buffer for store in stores}
    return any(read_buffer(e) in written for call in calls for e in walk_exprs(call.arg))


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
