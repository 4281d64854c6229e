"""Backend: NEON on AArch64 CPUs with the dot-product extension (ARMv8.2-A +dotprod: Cortex-A55,
A75, A76 and later, Neoverse, Apple M1): the neon target, whose int8 convolutions and matrix products
take four input channels per sdot (vdotq_s32: int8 x int8 quads summed into each int32 lane). sdot
multiplies int8 activations only, so uint8 activations are read as x - 128 (the byte x ^ 0x80) and the
pass adds 128 * sum(w) back per output channel, a constant of generation time (passes/dot_product.py):
exact. udot (u8 x u8) does not apply to int8 weights, and usdot (u8 x s8) needs the I8MM extension
(ARMv8.6-A), which fewer CPUs have.

AArch64 only: 32 vector registers. Built without the extension (no -march=armv8.2-a+dotprod or a
-mcpu that has it), the file stops at an #error; a program built with it dies with SIGILL on a CPU
without it (run-time detection, getauxval(AT_HWCAP) & HWCAP_ASIMDDP, is the caller's choice)."""

from __future__ import annotations

from dataclasses import replace

from .neon import Q_REGISTER, Neon

DOT4 = (
    "#if !defined(__ARM_FEATURE_DOTPROD)",
    '#error "this file is for the neon-dotprod target: build it for a CPU with the dot-product extension, '
    'e.g. -march=armv8.2-a+dotprod"',
    "#endif",
)

DOTPROD_Q_REGISTER = replace(
    Q_REGISTER,
    ints={**Q_REGISTER.ints, "dot4_add": "vdotq_s32({acc}, vreinterpretq_s8_s32({xs}), vld1q_s8({address}))"},
    int_helpers={**Q_REGISTER.int_helpers, "dot4": DOT4},
)


class NeonDotprod(Neon):
    target = replace(Neon.target, name="neon-dotprod", registers=32, dot_uint8=4, dot_int8=4, dot_int8_activations=True)
    widths = {4: DOTPROD_Q_REGISTER}
    cflags = ("-march=armv8.2-a+dotprod",)
