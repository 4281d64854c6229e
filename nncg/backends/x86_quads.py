"""Backend: dot products of 4 input channels on ssse3, avx2 and avx512 without VNNI: pmaddubsw multiplies
the uint8 activations by the int8 weights and sums adjacent products in int16, with saturation; pmaddwd
by ones sums each lane's two int16 into int32. The dot product pass (passes/dot_product.py) emits these
quads only for layers whose weights it proves keep every int16 pair sum in range, so the saturation
never happens and the result is the exact int32 dot product. AVX-512F has no 512-bit pmaddubsw (that
is AVX-512BW): its 16 lanes are two 256-bit halves (x86_integer.halves)."""

from __future__ import annotations

# lanes -> (intrinsic prefix, the packed weights' load of `lanes` quads)
_WEIGHTS = {
    4: ("_mm", "_mm_loadu_si128((const __m128i *)({address}))"),
    8: ("_mm256", "_mm256_loadu_si256((const __m256i *)({address}))"),
}

# 4 adjacent uint8 activations in every int32 lane, SSE2 (no vpbroadcastd)
SSE2_QUAD = "_mm_shuffle_epi32(_mm_loadu_si32((const void *)({address})), 0)"


def maddubs_dot4(lanes: int) -> str:
    """The `dot4` template of a 4- or 8-lane width: pmaddwd(pmaddubsw(xs, weights), ones)."""
    p, weights = _WEIGHTS[lanes]
    return f"{p}_madd_epi16({p}_maddubs_epi16({{xs}}, {weights}), {p}_set1_epi16(1))"
