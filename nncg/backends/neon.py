"""Backend: ARM NEON intrinsics (<arm_neon.h>), 4 float lanes in a 128-bit q register. One file
serves 32-bit ARM (ARMv7-A with NEON) and 64-bit ARM (AArch64, where NEON is baseline): what only
one of them has is chosen by the preprocessor in small helpers printed when the program uses them.

- Fused multiply-add: vfmaq_f32 on AArch64 and on ARMv7 with VFPv4 (__ARM_FEATURE_FMA, e.g.
  -mfpu=neon-vfpv4); plain ARMv7 NEON has only vmlaq_f32, a multiply and an add with two roundings.
- Division and square root: vdivq_f32 and vsqrtq_f32 exist on AArch64 only; ARMv7 divides and
  takes roots lane by lane (exact, unlike the reciprocal estimates and Newton steps).
- A constant vector that is not a splat is a row of one static const table, loaded with vld1q_f32:
  standard C99 on every compiler (clang's vld1q_f32 is a macro, so a braced initialiser inside its
  argument would not do), the same lanes whatever the byte order."""

from __future__ import annotations

from ..ir.target import Target
from .neon_integer import neon_integer
from .simd import SimdPrinter
from .vector_width import VectorWidth

ARITH = {"+": "vaddq_f32", "-": "vsubq_f32", "*": "vmulq_f32", "max": "vmaxq_f32", "min": "vminq_f32"}
COMPARE = {">": "vcgtq_f32", ">=": "vcgeq_f32", "<": "vcltq_f32", "<=": "vcleq_f32"}

FMA_MACRO = (
    "/* acc + a * b: fused (one rounding) where the ISA has it; ARMv7 NEON without VFPv4 has only vmlaq_f32,",
    "   a multiply and an add (two roundings: not fused, well within the tolerance) */",
    "#if defined(__aarch64__) || defined(__ARM_FEATURE_FMA)",
    "#define nncg_vfmaq_f32(acc, a, b) vfmaq_f32(acc, a, b)",
    "#else",
    "#define nncg_vfmaq_f32(acc, a, b) vmlaq_f32(acc, a, b)",
    "#endif",
)

DIV_HELPER = (
    "/* a / b: one instruction on AArch64; ARMv7 NEON has no vector division, so each lane is divided */",
    "#if defined(__aarch64__)",
    "#define nncg_vdivq_f32(a, b) vdivq_f32(a, b)",
    "#else",
    "static NNCG_INLINE float32x4_t nncg_vdivq_f32(float32x4_t a, float32x4_t b)",
    "{",
    "    float x[4], y[4];",
    "    vst1q_f32(x, a);",
    "    vst1q_f32(y, b);",
    "    x[0] /= y[0];",
    "    x[1] /= y[1];",
    "    x[2] /= y[2];",
    "    x[3] /= y[3];",
    "    return vld1q_f32(x);",
    "}",
    "#endif",
)

SQRT_HELPER = (
    "/* sqrt of each lane: one instruction on AArch64; ARMv7 NEON has only an estimate, so each lane takes VFP's",
    "   correctly rounded vsqrt.f32 */",
    "#if defined(__aarch64__)",
    "#define nncg_sqrtq_f32(a) vsqrtq_f32(a)",
    "#else",
    "static NNCG_INLINE float32x4_t nncg_sqrtq_f32(float32x4_t a)",
    "{",
    "    float x[4];",
    "    vst1q_f32(x, a);",
    "    x[0] = sqrtf(x[0]);",
    "    x[1] = sqrtf(x[1]);",
    "    x[2] = sqrtf(x[2]);",
    "    x[3] = sqrtf(x[3]);",
    "    return vld1q_f32(x);",
    "}",
    "#endif",
)

# Correct everywhere; gcc 12 for ARMv7 spells vcgtq_f32 as a generic `a > b`, which it compares
# lane by lane in VFP without -ffast-math (NEON flushes denormals); clang does not.
Q_REGISTER = VectorWidth(
    "float32x4_t",
    {
        "load": "vld1q_f32({address})",
        "store": "vst1q_f32({address}, {value})",
        "splat": "vdupq_n_f32({value})",
        "table": "nncg_vectors",
        **{op: f"{name}({{a}}, {{b}})" for op, name in ARITH.items()},
        "/": "nncg_vdivq_f32({a}, {b})",
        "fma": "nncg_vfmaq_f32({c}, {a}, {b})",
        **{cmp: f"vbslq_f32({name}({{lhs}}, {{rhs}}), {{then}}, {{otherwise}})" for cmp, name in COMPARE.items()},
        "math": "nncg_v{fn}q_f32",
        "sqrt": "nncg_sqrtq_f32({a})",
    },
    helpers={"fma": FMA_MACRO, "/": DIV_HELPER, "sqrt": SQRT_HELPER},
    bits={
        "type": "int32x4_t",
        "splat": "vdupq_n_s32({value})",
        "from_float": "vreinterpretq_s32_f32({a})",
        "to_float": "vreinterpretq_f32_s32({a})",
        "convert": "vcvtq_f32_s32({a})",
        "+": "vaddq_s32({a}, {b})",
        "-": "vsubq_s32({a}, {b})",
        "&": "vandq_s32({a}, {b})",
        "|": "vorrq_s32({a}, {b})",
        "<<": "vshlq_n_s32({a}, {n})",
        ">>": "vshrq_n_s32({a}, {n})",
    },
    **neon_integer(),
)


class Neon(SimdPrinter):
    # AArch64 has 32 vector registers but ARMv7 only 16 q registers (q0-q15), and the same file
    # serves both: register blocking sized for 32 would spill on ARMv7.
    target = Target(
        "neon",
        vector_widths=(4,),
        registers=16,
        fma=True,
        l1_bytes=32 * 1024,
        l2_bytes=256 * 1024,
        integer_vectors=True,
        dot_uint8=2,
        dot_int8=2,
    )
    widths = {4: Q_REGISTER}
    # No flags on AArch64 (NEON is baseline). ARMv7 needs NEON switched on, e.g. -mfpu=neon-vfpv4
    # (hard-float toolchains have -mfloat-abi=hard already); not here, as the host harness uses cflags.
    cflags = ()
    strict_cflags = ("-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<arm_neon.h>")
