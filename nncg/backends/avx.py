"""Backends: x86 AVX2 + FMA (8 lanes) and AVX-512F (16 lanes). What SSE lacks: a multiply feeding
an add is one fused multiply-add (one rounding, half the instructions), and a select is one blend
on the comparison's mask.

Both also print narrower blocks, so a loop too short for a full vector still runs on vectors
(12 channels on avx512: one __m256 and one __m128 block): every AVX-512F CPU has AVX2 and FMA, and
with -mavx2 -mfma the 4-lane SSE intrinsics are VEX-encoded and have fmadd and blendv too. Both
vectorise the int8 convolutions and matrix products on int32 lanes, two input channels per pmaddwd
(x86_integer.py); avx2 and avx512 take uint8 activations four channels per vpmaddubsw + vpmaddwd where
the layer's weights are proven never to saturate the int16 pair sums (x86_quads.py; avx512's 512-bit
ones in 256-bit halves, AVX-512F having no AVX-512BW), and a depthwise's taps as dots; avx512vnni adds
AVX-512 VNNI's vpdpbusd, four channels per instruction."""

from __future__ import annotations

from dataclasses import replace

from ..ir.target import Target
from .simd import SimdPrinter
from .x86 import X86_L1, X86_L2, X86_PREFETCH, x86_width
from .x86_integer import x86_integer

AVX_128 = replace(x86_width("_mm", "__m128", select="blendv", fma=True), **x86_integer(4, maddubs=True))
AVX_256 = replace(x86_width("_mm256", "__m256", select="blendv", fma=True), **x86_integer(8, maddubs=True))
AVX_512 = replace(x86_width("_mm512", "__m512", select="mask", fma=True), **x86_integer(16, maddubs=True))
VNNI_128 = replace(AVX_128, **x86_integer(4, bw=True, vnni=True))
VNNI_256 = replace(AVX_256, **x86_integer(8, bw=True, vnni=True))
VNNI_512 = replace(AVX_512, **x86_integer(16, bw=True, vnni=True))
X86 = {
    "registers": 16,
    "fma": True,
    "l1_bytes": X86_L1,
    "l2_bytes": X86_L2,
    "integer_vectors": True,
    "memory_operands": True,
    "dot_uint8": 2,
    "dot_int8": 2,
    "centred_weight_dots": True,
}


class Avx2(SimdPrinter):
    target = Target("avx2", vector_widths=(8, 4), **X86, dot_uint8_int16=4, tap_dots=True, int16_dots=True)
    widths = {8: AVX_256, 4: AVX_128}
    cflags = ("-mavx2", "-mfma")
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<immintrin.h>")
    prefetch = X86_PREFETCH
    # efficientnet_b0_96 whole, interleaved A/B: 4 -> 0.960-0.964x the time, 8 -> 0.979x, 2 -> 0.986x.
    # AVX-512 gained nothing (0.991-1.002x with 2, 4 or 8): 512-bit operations already fill the pipes.
    math_interleave = 4


class Avx512(SimdPrinter):
    target = Target(
        "avx512",
        vector_widths=(16, 8, 4),
        **{**X86, "registers": 32, "broadcast_operands": True, "dot_uint8_int16": 4, "tap_dots": True},
    )
    widths = {16: AVX_512, 8: AVX_256, 4: AVX_128}
    cflags = ("-mavx512f", "-mavx2", "-mfma")
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<immintrin.h>")
    prefetch = X86_PREFETCH


class Avx512Vnni(SimdPrinter):
    """avx512 plus AVX-512BW, VL and VNNI (Cascade Lake, Ice Lake and later; Zen 4): the int8
    convolutions and matrix products take 4 input channels per vpdpbusd (uint8 activations times int8
    weights; int8 activations read as x + 128, the bytes x ^ 0x80); float code is avx512's."""

    target = Target(
        "avx512vnni",
        vector_widths=(16, 8, 4),
        **{
            **X86,
            "registers": 32,
            "broadcast_operands": True,
            "dot_uint8": 4,
            "dot_uint8_activations": True,
            "tap_dots": True,
        },
    )
    widths = {16: VNNI_512, 8: VNNI_256, 4: VNNI_128}
    cflags = ("-mavx512f", "-mavx512bw", "-mavx512vl", "-mavx512vnni", "-mavx2", "-mfma")
    strict_cflags = ("-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<immintrin.h>")
    prefetch = X86_PREFETCH
