"""Backend: x86 SSE/SSSE3 intrinsics, 4 float lanes. max/min (ReLU, leaky ReLU, max-pool) are single
_mm_max_ps/_mm_min_ps instructions; SSE has no blend (a select is and/andnot/or on the comparison),
no fused multiply-add, and no exp, log or tanh (a vector call calls math.h once per lane). The int8
convolutions and matrix products run on SSE2's int32 vectors: uint8 activations four input channels
per pmaddubsw + pmaddwd where the layer's weights are proven never to saturate pmaddubsw's int16 pair
sums (x86_quads.py), else two per pmaddwd on int16 pairs (x86_integer.py), the pair weights stored as
int16; a depthwise's interior columns as pmaddwd of two taps (Target.tap_dots), their bytes interleaved.
QLinearAdd's fused multiply-adds are computed in double, two lanes at a time (Target.fma_in_double)."""

from __future__ import annotations

from dataclasses import replace

from ..ir.target import Target
from .simd import SimdPrinter
from .vector_width import VectorWidth
from .x86 import X86_L1, X86_L2, X86_PREFETCH, x86_width
from .x86_integer import sse2_integer

# a * b + c rounded once: each pair of lanes in double (SSE2), where the products and sums of the
# QLinearAdd operands the vectorize pass fuses are exact (lowering/quantized_add.py), as in scalar C
FMA_IN_DOUBLE = (
    "/* a * b + c in double, rounded once to float: SSE has no fused multiply-add */",
    "static NNCG_INLINE __m128 nncg_fma_pd(__m128 a, __m128 b, __m128 c)",
    "{",
    "    __m128d low = _mm_add_pd(_mm_mul_pd(_mm_cvtps_pd(a), _mm_cvtps_pd(b)), _mm_cvtps_pd(c));",
    "    __m128d high = _mm_add_pd(_mm_mul_pd(_mm_cvtps_pd(_mm_movehl_ps(a, a)), _mm_cvtps_pd(_mm_movehl_ps(b, b))),",
    "                              _mm_cvtps_pd(_mm_movehl_ps(c, c)));",
    "    return _mm_movelh_ps(_mm_cvtpd_ps(low), _mm_cvtpd_ps(high));",
    "}",
)


def fused_in_double(width: VectorWidth) -> VectorWidth:
    return replace(
        width, ops={**width.ops, "fma_exact": "nncg_fma_pd({a}, {b}, {c})"}, helpers={"fma_exact": FMA_IN_DOUBLE}
    )


class Ssse3(SimdPrinter):
    target = Target(
        "ssse3",
        vector_widths=(4,),
        registers=16,
        fma=False,
        l1_bytes=X86_L1,
        l2_bytes=X86_L2,
        integer_vectors=True,
        memory_operands=True,
        dot_uint8=2,
        dot_int8=2,
        dot_uint8_int16=4,
        dot2_int16_weights=True,
        centred_weight_dots=True,
        dot2_quad_loads=True,
        tap_dots=True,
        fma_in_double=True,
        int16_dots=True,
    )
    widths = {4: fused_in_double(replace(x86_width("_mm", "__m128", select="bitwise", fma=False), **sse2_integer()))}
    cflags = ("-mssse3",)
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<tmmintrin.h>")
    prefetch = X86_PREFETCH
    # efficientnet_b0_96 whole, interleaved A/B: 8 -> 0.964-0.965x the time, 4 -> 0.975x.
    math_interleave = 8
