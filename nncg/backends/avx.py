"""Backends: x86 AVX2 + FMA (8 lanes) and AVX-512F (16 lanes). The SSSE3 printer with wider
intrinsics, plus what SSE lacks: a multiply feeding an add is one fused multiply-add (one rounding,
half the instructions), and a select is one blend on the comparison's mask."""

from __future__ import annotations

from ..ir.loops import Binary, Select
from .ssse3 import Ssse3

PREDICATES = {">": "_CMP_GT_OQ", ">=": "_CMP_GE_OQ", "<": "_CMP_LT_OQ", "<=": "_CMP_LE_OQ"}


class Avx2(Ssse3):
    name = "avx2"
    lanes = 8
    prefix = "_mm256"
    vector_type = "__m256"
    cflags = ("-mavx2", "-mfma")
    includes = ("<math.h>", "<immintrin.h>")

    def _expr_Binary(self, e: Binary) -> str:
        if e.lanes == self.lanes and e.op == "+":
            for product, addend in ((e.a, e.b), (e.b, e.a)):
                if isinstance(product, Binary) and product.op == "*":
                    a, b, c = (self.expr(x) for x in (product.a, product.b, addend))
                    return f"{self.prefix}_fmadd_ps({a}, {b}, {c})"
        return super()._expr_Binary(e)

    def _expr_Select(self, e: Select) -> str:
        if e.lanes != self.lanes:
            return super()._expr_Select(e)
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return f"_mm256_blendv_ps({other}, {then}, _mm256_cmp_ps({lhs}, {rhs}, {PREDICATES[e.cmp]}))"


class Avx512(Avx2):
    name = "avx512"
    lanes = 16
    prefix = "_mm512"
    vector_type = "__m512"
    cflags = ("-mavx512f",)

    def _expr_Select(self, e: Select) -> str:
        if e.lanes != self.lanes:
            return super()._expr_Select(e)
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return f"_mm512_mask_blend_ps(_mm512_cmp_ps_mask({lhs}, {rhs}, {PREDICATES[e.cmp]}), {other}, {then})"
