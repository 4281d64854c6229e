"""Backends: x86 AVX2 + FMA (8 lanes) and AVX-512F (16 lanes). The SSSE3 printer with wider
intrinsics, plus what SSE lacks: a multiply feeding an add is one fused multiply-add (one rounding,
half the instructions), and a select is one blend on the comparison's mask.

Both also print narrower blocks, so a loop too short for a full vector still runs on vectors
(12 channels on avx512: one __m256 and one __m128 block): every AVX-512F CPU has AVX2 and FMA, and
with -mavx2 -mfma the 4-lane SSE intrinsics are VEX-encoded and have fmadd and blendv too."""

from __future__ import annotations

from .ssse3 import Simd, Ssse3

AVX_128 = Simd("_mm", "__m128", "blendv", fma=True)
AVX_256 = Simd("_mm256", "__m256", "blendv", fma=True)
AVX_512 = Simd("_mm512", "__m512", "mask", fma=True)


class Avx2(Ssse3):
    name = "avx2"
    simd = {8: AVX_256, 4: AVX_128}
    vector_widths = tuple(simd)
    lanes = vector_widths[0]
    cflags = ("-mavx2", "-mfma")
    includes = ("<math.h>", "<immintrin.h>")


class Avx512(Avx2):
    name = "avx512"
    simd = {16: AVX_512, 8: AVX_256, 4: AVX_128}
    vector_widths = tuple(simd)
    lanes = vector_widths[0]
    cflags = ("-mavx512f", "-mavx2", "-mfma")
    registers = 32
