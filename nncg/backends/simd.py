"""Backend: the SIMD printer base. Dispatches every vector node once (1-lane code goes to the scalar
printer), prints it from the target's table of widths (vector_width.py), and prints the helpers the
program needs (simd_needs.py, collected before any code) before the kernels, in a fixed order."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

from ..ir.loops import (
    Affine,
    Binary,
    Broadcast,
    Call,
    Const,
    Expr,
    Fma,
    Load,
    LocalRef,
    Loop,
    Program,
    Select,
    Stmt,
    Store,
    map_expr,
)
from .c_text import INDENT, c_affine, c_float
from .prefetch import prefetch_addresses, streamed_constants
from .scalar import ScalarPrinter
from .scalar_math import scalar_calls
from .simd_integer import IntegerVectors
from .simd_needs import Needs, collect_needs, interleaved_runs
from .vector_math import (
    has_vector_math,
    interleaved_math_helper,
    interleaved_name,
    vector_math_helper,
    with_callees,
)
from .vector_width import VectorWidth


class SimdPrinter(IntegerVectors, ScalarPrinter):
    """A SIMD target: a subclass declares `target` and fills `widths` (lanes -> VectorWidth, one per
    width of target.vector_widths); it overrides hooks only where a table cannot say it."""

    widths: Mapping[int, VectorWidth] = {}
    # The statement that prefetches the cache line at `address` ("" : the target prints none).
    prefetch = ""
    # Up to this many consecutive stores of vectors that each call one math function (a register
    # block's SiLU epilogue) call an interleaved helper once (vector_math.py), 1: each its own. A
    # sigmoid is a chain of ~20 dependent operations; written one after another, Zen 4's scheduler
    # holds few of them: SSE's throughput alone is 2.9 ns a vector, in efficientnet_b0's 16 -> 96
    # 1x1 SiLU conv 4.6 (ssse3, gcc -O3, the layer alone: 437 us, 407 with 4, 388 with 8).
    math_interleave = 1
    # The local array of an interleaved call's vectors.
    interleaved_lanes = "nncg_lanes"

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if "target" in cls.__dict__ or "widths" in cls.__dict__:
            _check_table(cls)

    def __init__(self, needs: Needs | None = None, math_calls: frozenset[str] = frozenset()) -> None:
        super().__init__(math_calls)
        self.needs = needs or Needs()
        self.streamed: dict[str, int] = {}  # constants that stream from beyond L1 (prefetch.py)
        self.extents: dict[str, int] = {}  # the loops being printed, var -> extent

    def for_program(self, program: Program) -> SimdPrinter:
        """Scalar code here is the scalar tails and the lane-wise helpers of widths without vector
        math, which call the scalar function on each lane."""
        needs = collect_needs(program, self.widths, self.math_interleave)
        lane_wise = {fn for lanes, fn in needs.math if not has_vector_math(self.widths[lanes])}
        printer = type(self)(needs, scalar_calls(program) | lane_wise).typed_for(program)
        if self.prefetch:
            printer.streamed = streamed_constants(program, self.target.l1_bytes)
        return printer.with_integer_helpers(program, printer.dtypes)

    def _stmt_Loop(self, loop: Loop, depth: int) -> list[str]:
        """A reduction loop over weights that stream from beyond L1 prefetches them (prefetch.py)."""
        self.extents[loop.var] = loop.extent
        lines = super()._stmt_Loop(loop, depth)
        pad = INDENT * (depth + 1)
        ahead = prefetch_addresses(loop, self.streamed, self.extents) if self.streamed else []
        del self.extents[loop.var]
        return [lines[0], *(pad + self.prefetch.format(address=f"&{b}[{i}]") for b, i in ahead), *lines[1:]]

    def stmts(self, body: tuple[Stmt, ...], depth: int) -> list[str]:
        out: list[str] = []
        for run, calls in interleaved_runs(body, self.widths, self.math_interleave):
            out += self._interleaved_stores(run, calls, depth) if calls else super().stmts(run, depth)
        return out

    def _interleaved_stores(self, stores: tuple[Stmt, ...], calls: tuple[Call, ...], depth: int) -> list[str]:
        """The stores' calls as one call of the interleaved helper, on an array of their arguments."""
        width, lanes = self.width(calls[0].lanes), self.interleaved_lanes
        pad, inner = INDENT * depth, INDENT * (depth + 1)
        lines = [pad + "{", f"{inner}{width.type} {lanes}[{len(stores)}];"]
        lines += [f"{inner}{lanes}[{k}] = {self.expr(call.arg)};" for k, call in enumerate(calls)]
        lines.append(f"{inner}{interleaved_name(calls[0].fn, width, len(stores))}({lanes});")
        for k, (store, call) in enumerate(zip(stores, calls, strict=True)):
            result = LocalRef(f"{lanes}[{k}]", call.lanes)
            value = map_expr(store.value, lambda e, call=call, result=result: result if e == call else e)
            lines += super().stmts((replace(store, value=value),), depth + 1)
        return [*lines, pad + "}"]

    # ------------------------------------------------------------------ dispatch, once

    def width(self, lanes: int) -> VectorWidth:
        if lanes not in self.widths:
            self.unsupported_lanes(lanes)
        return self.widths[lanes]

    def type_of(self, lanes: int) -> str:
        return super().type_of(lanes) if lanes == 1 else self.width(lanes).type

    def local_type(self, init: Expr) -> str:
        if init.lanes > 1 and self.is_integer_vector(init):
            return self.width(init.lanes).ints["type"]
        return super().local_type(init)

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        if value.lanes == 1:
            return super().store(buffer, index, value)
        width = self.width(value.lanes)
        if self.dtypes[buffer].is_integer:
            return self.integer_store(Store(buffer, index, value), width)
        return width.spell("store", address=f"&{buffer}[{c_affine(index)}]", value=self.expr(value))

    def assign(self, name: str, value: Expr) -> str:
        if value.lanes == 1:
            return super().assign(name, value)
        self.width(value.lanes)
        return f"{name} = {self.expr(value)}"

    def expr(self, e: Expr) -> str:
        if e.lanes == 1:
            return super().expr(e)
        if self.is_integer_vector(e):
            return self.integer_vector(e, self.width(e.lanes))
        return getattr(self, f"_vector_{type(e).__name__}")(e, self.width(e.lanes))

    # ------------------------------------------------------------------ vector expressions

    def _vector_Const(self, e: Const, width: VectorWidth) -> str:
        if e.is_splat:
            return width.spell("splat", value=c_float(e.values[0]))
        if "vector" in width.ops:
            return width.spell("vector", values=", ".join(c_float(v) for v in e.values))
        row = self.needs.rows[e.lanes][e.values]
        return width.spell("load", address=f"{width.spell('table')}[{row}]")

    def _vector_Load(self, e: Load, width: VectorWidth) -> str:
        return width.spell("load", address=f"&{e.buffer}[{c_affine(e.index)}]")

    def _vector_LocalRef(self, e: LocalRef, width: VectorWidth) -> str:
        return e.name

    def _vector_Broadcast(self, e: Broadcast, width: VectorWidth) -> str:
        return width.spell("splat", value=self.expr(e.value))

    def _vector_Binary(self, e: Binary, width: VectorWidth) -> str:
        return width.spell(e.op, a=self.expr(e.a), b=self.expr(e.b))

    def _vector_Fma(self, e: Fma, width: VectorWidth) -> str:
        a, b, c = self.expr(e.a), self.expr(e.b), self.expr(e.c)
        fused = next((op for op in ("fma", "fma_exact") if op in width.ops), None)
        if fused:
            return width.spell(fused, a=a, b=b, c=c)
        return width.spell("+", a=width.spell("*", a=a, b=b), b=c)

    def _vector_Select(self, e: Select, width: VectorWidth) -> str:
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return width.spell(e.cmp, lhs=lhs, rhs=rhs, then=then, otherwise=other)

    def _vector_Call(self, e: Call, width: VectorWidth) -> str:
        return f"{width.spell('math', fn=e.fn)}({self.expr(e.arg)})"

    # ------------------------------------------------------------------ helpers, before the kernels

    def preamble(self) -> list[str]:
        """The scalar math helpers (scalar.py), then the helper definitions templates call (in order
        of first use), then the tables of constant vectors (widest first), then the math functions
        (widest first; each after those it calls, then by name); a blank line before each."""
        blocks: list[tuple[str, ...]] = []
        for lanes, op in self.needs.definitions:
            definition = self.widths[lanes].helpers[op]
            if definition not in blocks:  # two widths may share a helper
                blocks.append(definition)
        for lanes, rows in sorted(self.needs.rows.items(), reverse=True):
            blocks.append(self.constant_table(lanes, tuple(rows)))
        for lanes in sorted({lanes for lanes, _ in self.needs.math}, reverse=True):
            width = self.widths[lanes]
            called = {fn for n, fn in self.needs.math if n == lanes}
            if has_vector_math(width):
                blocks += [vector_math_helper(fn, width) for fn in with_callees(called)]
                interleaved = sorted((fn, count) for n, fn, count in self.needs.interleaved if n == lanes)
                blocks += [interleaved_math_helper(fn, width, count) for fn, count in interleaved]
            else:
                blocks += [self.lane_wise_helper(fn, lanes) for fn in sorted(called)]
        lines = super().preamble() + self.integer_helpers()
        return lines + [line for block in blocks for line in ("", *block)]

    def constant_table(self, lanes: int, rows: tuple[tuple[float, ...], ...]) -> tuple[str, ...]:
        """The static table of the constant vectors of one width that are not splats, a row each:
        standard C, the same lanes whatever the byte order."""
        width = self.widths[lanes]
        loader = width.ops["load"].partition("(")[0]
        return (
            f"/* constant vectors that are not splats, loaded with {loader} */",
            f"static const float {width.spell('table')}[{len(rows)}][{lanes}] = {{",
            *(f"{INDENT}{{{', '.join(c_float(v) for v in values)}}}," for values in rows),
            "};",
        )

    def lane_wise_helper(self, fn: str, lanes: int) -> tuple[str, ...]:
        """NAME(x): math.h's double-precision fn of each lane of x, for a width without the integer
        operations of the vector math functions (vector_math.py)."""
        width = self.widths[lanes]
        head = (
            f"/* {fn} of each lane: no vector {fn} in the instruction set */",
            f"static {width.type} {width.spell('math', fn=fn)}({width.type} x)",
            "{",
            f"{INDENT}float v[{lanes}];",
            f"{INDENT}{width.spell('store', address='v', value='x')};",
        )
        calls = [ScalarPrinter.expr(self, Call(fn, Load("v", Affine((), i)))) for i in range(lanes)]
        if "vector" in width.ops:
            return (*head, f"{INDENT}return {width.spell('vector', values=', '.join(calls))};", "}")
        each = [f"{INDENT}v[{i}] = {call};" for i, call in enumerate(calls)]
        return (*head, *each, f"{INDENT}return {width.spell('load', address='v')};", "}")


def _check_table(cls: type[SimdPrinter]) -> None:
    """A SIMD target's table covers exactly its target's widths, each with every operation."""
    if tuple(cls.widths) != cls.target.vector_widths:
        raise TypeError(f"{cls.__name__}: widths {tuple(cls.widths)} are not the target's {cls.target.vector_widths}")
    for lanes, width in cls.widths.items():
        problems = width.problems(cls.target.fma)
        if problems:
            raise TypeError(f"{cls.__name__}, {lanes} lanes: {'; '.join(problems)}")
