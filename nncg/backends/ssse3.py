"""Backend: x86 SSE/SSSE3 intrinsics, 4 float lanes. Overrides only the vector hooks of the C printer;
max/min (ReLU, leaky ReLU, max-pool) are single _mm_max_ps/_mm_min_ps instructions. SSE has no exp,
log or tanh: a vector call goes through a small helper that calls math.h once per lane.

The wider x86 targets (nncg/backends/avx.py) reuse it: the intrinsic prefix, vector type and lane count
are class attributes; they override only select and fused multiply-add."""

from __future__ import annotations

from ..ir.loops import (
    Affine,
    Binary,
    Broadcast,
    Call,
    Const,
    Expr,
    Load,
    Program,
    Select,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from .c import AnsiC, c_affine, c_float

ARITH = {"+": "add", "-": "sub", "*": "mul", "/": "div", "max": "max", "min": "min"}
COMPARE = {">": "cmpgt", ">=": "cmpge", "<": "cmplt", "<=": "cmple"}


class Ssse3(AnsiC):
    name = "ssse3"
    lanes = 4
    prefix = "_mm"  # of the intrinsics: _mm_add_ps, _mm256_add_ps, ...
    vector_type = "__m128"
    cflags = ("-mssse3",)
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<tmmintrin.h>")

    def source(self, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
        """The C file, with the lane-wise helper of every function the program calls on vectors
        defined right after the includes."""
        text = super().source(program, first_line, header_name, profile)
        fns = sorted({e.fn for e in _exprs(program) if isinstance(e, Call) and e.lanes == self.lanes})
        if not fns:
            return text
        anchor = f"#include {self.includes[-1]}\n"
        return text.replace(anchor, anchor + "".join(self._lane_wise_helper(fn) for fn in fns), 1)

    def type_of(self, lanes: int) -> str:
        return self.vector_type if lanes == self.lanes else super().type_of(lanes)

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        if value.lanes == self.lanes:
            return f"{self.prefix}_storeu_ps(&{buffer}[{c_affine(index)}], {self.expr(value)})"
        return super().store(buffer, index, value)

    def assign(self, name: str, value: Expr) -> str:
        if value.lanes == self.lanes:
            return f"{name} = {self.expr(value)}"
        return super().assign(name, value)

    def _expr_Const(self, e: Const) -> str:
        if e.lanes != self.lanes:
            return super()._expr_Const(e)
        if e.is_splat:
            return f"{self.prefix}_set1_ps({c_float(e.values[0])})"
        return f"{self.prefix}_setr_ps({', '.join(c_float(v) for v in e.values)})"

    def _expr_Load(self, e: Load) -> str:
        if e.lanes == self.lanes:
            return f"{self.prefix}_loadu_ps(&{e.buffer}[{c_affine(e.index)}])"
        return super()._expr_Load(e)

    def _expr_Broadcast(self, e: Broadcast) -> str:
        if e.lanes == self.lanes:
            return f"{self.prefix}_set1_ps({self.expr(e.value)})"
        return super()._expr_Broadcast(e)

    def _expr_Binary(self, e: Binary) -> str:
        if e.lanes == self.lanes:
            return f"{self.prefix}_{ARITH[e.op]}_ps({self.expr(e.a)}, {self.expr(e.b)})"
        return super()._expr_Binary(e)

    def _expr_Select(self, e: Select) -> str:
        if e.lanes != self.lanes:
            return super()._expr_Select(e)
        # SSSE3 has no blend: (mask & then) | (~mask & otherwise)
        mask = f"_mm_{COMPARE[e.cmp]}_ps({self.expr(e.lhs)}, {self.expr(e.rhs)})"
        then, other = self.expr(e.then), self.expr(e.otherwise)
        return f"_mm_or_ps(_mm_and_ps({mask}, {then}), _mm_andnot_ps({mask}, {other}))"

    def _expr_Call(self, e: Call) -> str:
        if e.lanes == self.lanes:
            return f"nncg_{e.fn}_ps({self.expr(e.arg)})"
        return super()._expr_Call(e)

    def _lane_wise_helper(self, fn: str) -> str:
        """nncg_FN_ps(x): FN of each lane of x through the double-precision C89 function."""
        lanes = ", ".join(f"(float){fn}(v[{i}])" for i in range(self.lanes))
        return (
            f"\n/* {fn} of each lane: no vector {fn} in the instruction set */\n"
            f"static {self.vector_type} nncg_{fn}_ps({self.vector_type} x)\n{{\n"
            f"    float v[{self.lanes}];\n    {self.prefix}_storeu_ps(v, x);\n"
            f"    return {self.prefix}_setr_ps({lanes});\n}}\n"
        )


def _exprs(program: Program):
    """Every expression of every kernel, sub-expressions included."""
    for kernel in program.kernels:
        for stmt in walk_stmts(kernel.body):
            for top in stmt_exprs(stmt):
                yield from walk_exprs(top)
