"""Backend: x86 SSE/SSSE3 intrinsics, 4 float lanes. Overrides only the vector hooks of the C printer;
max/min (ReLU, leaky ReLU, max-pool) are single _mm_max_ps/_mm_min_ps instructions. SSE has no exp,
log or tanh: a vector call goes through a small helper that calls math.h once per lane.

The printer is table-driven so that the wider x86 targets (nncg/backends/avx.py) reuse it: `simd`
maps each vector width the target prints to its intrinsic prefix, vector type, select style and
whether it has fused multiply-add; every hook looks up the width of the expression it prints, so one
program may mix widths (16-, 8- and 4-lane blocks of the same loop on avx512)."""

from __future__ import annotations

from dataclasses import dataclass

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
PREDICATES = {">": "_CMP_GT_OQ", ">=": "_CMP_GE_OQ", "<": "_CMP_LT_OQ", "<=": "_CMP_LE_OQ"}


@dataclass(frozen=True)
class Simd:
    """How one vector width is printed."""

    prefix: str  # of the intrinsics: _mm_add_ps, _mm256_add_ps, ...
    type: str  # __m128, __m256, __m512
    select: (
        str  # "bitwise": and/andnot/or on a comparison (SSE); "blendv": blendv_ps (AVX); "mask": a __mmask (AVX-512)
    )
    fma: bool  # a multiply feeding an add is one fmadd_ps (one rounding, half the instructions)

    @property
    def helpers(self) -> str:
        """The lane-wise helpers' prefix, after the intrinsics': nncg_exp_ps, nncg256_exp_ps, ..."""
        return "nncg" + self.prefix.removeprefix("_mm")


SSE = Simd("_mm", "__m128", "bitwise", fma=False)


class Ssse3(AnsiC):
    name = "ssse3"
    simd = {4: SSE}  # lanes -> how to print them, widest first
    vector_widths = tuple(simd)
    lanes = vector_widths[0]
    cflags = ("-mssse3",)
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<tmmintrin.h>")

    def source(self, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
        """The C file, with the lane-wise helper of every function the program calls on vectors
        defined right after the includes."""
        text = super().source(program, first_line, header_name, profile)
        calls = {(-e.lanes, e.fn) for e in _exprs(program) if isinstance(e, Call) and e.lanes in self.simd}
        if not calls:
            return text
        anchor = f"#include {self.includes[-1]}\n"
        helpers = "".join(self._lane_wise_helper(fn, -neg) for neg, fn in sorted(calls))
        return text.replace(anchor, anchor + helpers, 1)

    def type_of(self, lanes: int) -> str:
        return self.simd[lanes].type if lanes in self.simd else super().type_of(lanes)

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        if value.lanes in self.simd:
            return f"{self.simd[value.lanes].prefix}_storeu_ps(&{buffer}[{c_affine(index)}], {self.expr(value)})"
        return super().store(buffer, index, value)

    def assign(self, name: str, value: Expr) -> str:
        if value.lanes in self.simd:
            return f"{name} = {self.expr(value)}"
        return super().assign(name, value)

    def _expr_Const(self, e: Const) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Const(e)
        p = self.simd[e.lanes].prefix
        if e.is_splat:
            return f"{p}_set1_ps({c_float(e.values[0])})"
        return f"{p}_setr_ps({', '.join(c_float(v) for v in e.values)})"

    def _expr_Load(self, e: Load) -> str:
        if e.lanes in self.simd:
            return f"{self.simd[e.lanes].prefix}_loadu_ps(&{e.buffer}[{c_affine(e.index)}])"
        return super()._expr_Load(e)

    def _expr_Broadcast(self, e: Broadcast) -> str:
        if e.lanes in self.simd:
            return f"{self.simd[e.lanes].prefix}_set1_ps({self.expr(e.value)})"
        return super()._expr_Broadcast(e)

    def _expr_Binary(self, e: Binary) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Binary(e)
        simd = self.simd[e.lanes]
        if simd.fma and e.op == "+":
            for product, addend in ((e.a, e.b), (e.b, e.a)):
                if isinstance(product, Binary) and product.op == "*":
                    a, b, c = (self.expr(x) for x in (product.a, product.b, addend))
                    return f"{simd.prefix}_fmadd_ps({a}, {b}, {c})"
        return f"{simd.prefix}_{ARITH[e.op]}_ps({self.expr(e.a)}, {self.expr(e.b)})"

    def _expr_Select(self, e: Select) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Select(e)
        simd = self.simd[e.lanes]
        p = simd.prefix
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        if simd.select == "mask":
            return f"{p}_mask_blend_ps({p}_cmp_ps_mask({lhs}, {rhs}, {PREDICATES[e.cmp]}), {other}, {then})"
        if simd.select == "blendv":
            return f"{p}_blendv_ps({other}, {then}, {p}_cmp_ps({lhs}, {rhs}, {PREDICATES[e.cmp]}))"
        # no blend: (mask & then) | (~mask & otherwise)
        mask = f"{p}_{COMPARE[e.cmp]}_ps({lhs}, {rhs})"
        return f"{p}_or_ps({p}_and_ps({mask}, {then}), {p}_andnot_ps({mask}, {other}))"

    def _expr_Call(self, e: Call) -> str:
        if e.lanes in self.simd:
            return f"{self.simd[e.lanes].helpers}_{e.fn}_ps({self.expr(e.arg)})"
        return super()._expr_Call(e)

    def _lane_wise_helper(self, fn: str, lanes: int) -> str:
        """nncg_FN_ps(x) (nncg256_FN_ps, ... for wider vectors): FN of each lane of x through the
        double-precision C89 function."""
        simd = self.simd[lanes]
        values = ", ".join(f"(float){fn}(v[{i}])" for i in range(lanes))
        return (
            f"\n/* {fn} of each lane: no vector {fn} in the instruction set */\n"
            f"static {simd.type} {simd.helpers}_{fn}_ps({simd.type} x)\n{{\n"
            f"    float v[{lanes}];\n    {simd.prefix}_storeu_ps(v, x);\n"
            f"    return {simd.prefix}_setr_ps({values});\n}}\n"
        )


def _exprs(program: Program):
    """Every expression of every kernel, sub-expressions included."""
    for kernel in program.kernels:
        for stmt in walk_stmts(kernel.body):
            for top in stmt_exprs(stmt):
                yield from walk_exprs(top)
