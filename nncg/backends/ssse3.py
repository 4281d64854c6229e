"""Backend: x86 SSE/SSSE3 intrinsics, 4 float lanes. Overrides only the vector hooks of the C printer;
max/min (ReLU, leaky ReLU, max-pool) are single _mm_max_ps/_mm_min_ps instructions."""

from __future__ import annotations

from ..ir.loops import Affine, Binary, Broadcast, Const, Expr, Load, Select
from .c import AnsiC, c_affine, c_float

ARITH = {"+": "add", "-": "sub", "*": "mul", "/": "div", "max": "max", "min": "min"}
COMPARE = {">": "cmpgt", ">=": "cmpge", "<": "cmplt", "<=": "cmple"}


class Ssse3(AnsiC):
    name = "ssse3"
    lanes = 4
    cflags = ("-mssse3",)
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<tmmintrin.h>")

    def type_of(self, lanes: int) -> str:
        return "__m128" if lanes == 4 else super().type_of(lanes)

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        if value.lanes == 4:
            return f"_mm_storeu_ps(&{buffer}[{c_affine(index)}], {self.expr(value)})"
        return super().store(buffer, index, value)

    def assign(self, name: str, value: Expr) -> str:
        if value.lanes == 4:
            return f"{name} = {self.expr(value)}"
        return super().assign(name, value)

    def _expr_Const(self, e: Const) -> str:
        if e.lanes != 4:
            return super()._expr_Const(e)
        if e.is_splat:
            return f"_mm_set1_ps({c_float(e.values[0])})"
        return f"_mm_setr_ps({', '.join(c_float(v) for v in e.values)})"

    def _expr_Load(self, e: Load) -> str:
        if e.lanes == 4:
            return f"_mm_loadu_ps(&{e.buffer}[{c_affine(e.index)}])"
        return super()._expr_Load(e)

    def _expr_Broadcast(self, e: Broadcast) -> str:
        if e.lanes == 4:
            return f"_mm_set1_ps({self.expr(e.value)})"
        return super()._expr_Broadcast(e)

    def _expr_Binary(self, e: Binary) -> str:
        if e.lanes == 4:
            return f"_mm_{ARITH[e.op]}_ps({self.expr(e.a)}, {self.expr(e.b)})"
        return super()._expr_Binary(e)

    def _expr_Select(self, e: Select) -> str:
        if e.lanes != 4:
            return super()._expr_Select(e)
        # SSSE3 has no blend: (mask & then) | (~mask & otherwise)
        mask = f"_mm_{COMPARE[e.cmp]}_ps({self.expr(e.lhs)}, {self.expr(e.rhs)})"
        then, other = self.expr(e.then), self.expr(e.otherwise)
        return f"_mm_or_ps(_mm_and_ps({mask}, {then}), _mm_andnot_ps({mask}, {other}))"
