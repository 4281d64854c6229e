"""Backend: ARM NEON intrinsics (<arm_neon.h>), 4 float lanes in a 128-bit q register. One file
serves 32-bit ARM (ARMv7-A with NEON) and 64-bit ARM (AArch64, where NEON is baseline): what only
one of them has is chosen by the preprocessor in small helpers printed when the program uses them.

- Fused multiply-add: vfmaq_f32 on AArch64 and on ARMv7 with VFPv4 (__ARM_FEATURE_FMA, e.g.
  -mfpu=neon-vfpv4); plain ARMv7 NEON has only vmlaq_f32, a multiply and an add with two roundings.
- Division: vdivq_f32 exists on AArch64 only; ARMv7 divides lane by lane (exact, unlike the
  reciprocal estimate and Newton steps).
- A constant vector that is not a splat is a row of one static const table, loaded with vld1q_f32:
  standard C99 on every compiler (clang's vld1q_f32 is a macro, so a braced initialiser inside its
  argument would not do), the same lanes whatever the byte order.

It reuses the SSSE3 printer's width table (type_of, assign, the lane-wise helpers' placement);
only the hooks that spell intrinsics differ."""

from __future__ import annotations

from ..ir.loops import Affine, Binary, Broadcast, Call, Const, Expr, Load, Program, Select
from .c import INDENT, c_affine, c_float
from .ssse3 import ARITH, Simd, Ssse3

NEON = Simd("v", "float32x4_t", "bsl", fma=True)  # vaddq_f32, ...; select: vbslq_f32 on a vcgtq_f32 mask
COMPARE = {">": "cgt", ">=": "cge", "<": "clt", "<=": "cle"}
VECTORS = "nncg_vectors"  # the table of constant vectors

FMA_MACRO = """
/* acc + a * b: fused (one rounding) where the ISA has it; ARMv7 NEON without VFPv4 has only vmlaq_f32,
   a multiply and an add (two roundings: not fused, well within the tolerance) */
#if defined(__aarch64__) || defined(__ARM_FEATURE_FMA)
#define nncg_vfmaq_f32(acc, a, b) vfmaq_f32(acc, a, b)
#else
#define nncg_vfmaq_f32(acc, a, b) vmlaq_f32(acc, a, b)
#endif
"""

DIV_HELPER = """
/* a / b: one instruction on AArch64; ARMv7 NEON has no vector division, so each lane is divided */
#if defined(__aarch64__)
#define nncg_vdivq_f32(a, b) vdivq_f32(a, b)
#else
static float32x4_t nncg_vdivq_f32(float32x4_t a, float32x4_t b)
{
    float x[4], y[4];
    vst1q_f32(x, a);
    vst1q_f32(y, b);
    x[0] /= y[0];
    x[1] /= y[1];
    x[2] /= y[2];
    x[3] /= y[3];
    return vld1q_f32(x);
}
#endif
"""


class Neon(Ssse3):
    name = "neon"
    simd = {4: NEON}
    vector_widths = tuple(simd)
    lanes = vector_widths[0]
    # AArch64 has 32 vector registers but ARMv7 only 16 q registers (q0-q15), and the same file
    # serves both: register blocking sized for 32 would spill on ARMv7.
    registers = 16
    # No flags on AArch64 (NEON is baseline). ARMv7 needs NEON switched on, e.g. -mfpu=neon-vfpv4
    # (hard-float toolchains have -mfloat-abi=hard already); not here, as the host harness uses cflags.
    cflags = ()
    strict_cflags = ("-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>", "<arm_neon.h>")

    def __init__(self) -> None:
        self._vectors: dict[tuple[float, ...], int] = {}  # non-splat constants -> row of the table
        self._helpers: dict[str, str] = {}  # the ISA-dependent helpers printed code uses, by name

    def source(self, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
        """The C file, with the helpers and the constant vectors the kernels use after the includes."""
        self._vectors, self._helpers = {}, {}  # a fresh table per file
        text = super().source(program, first_line, header_name, profile)
        preamble = "".join(self._helpers.values())
        if self._vectors:
            rows = [f"{INDENT}{{{', '.join(c_float(v) for v in values)}}}," for values in self._vectors]
            preamble += (
                f"\n/* constant vectors that are not splats, loaded with vld1q_f32 */\n"
                f"static const float {VECTORS}[{len(rows)}][4] = {{\n" + "\n".join(rows) + "\n};\n"
            )
        anchor = f"#include {self.includes[-1]}\n"
        return text.replace(anchor, anchor + preamble, 1)

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        if value.lanes in self.simd:
            return f"vst1q_f32(&{buffer}[{c_affine(index)}], {self.expr(value)})"
        return super().store(buffer, index, value)

    def _expr_Const(self, e: Const) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Const(e)
        if e.is_splat:
            return f"vdupq_n_f32({c_float(e.values[0])})"
        row = self._vectors.setdefault(e.values, len(self._vectors))
        return f"vld1q_f32({VECTORS}[{row}])"

    def _expr_Load(self, e: Load) -> str:
        if e.lanes in self.simd:
            return f"vld1q_f32(&{e.buffer}[{c_affine(e.index)}])"
        return super()._expr_Load(e)

    def _expr_Broadcast(self, e: Broadcast) -> str:
        if e.lanes in self.simd:
            return f"vdupq_n_f32({self.expr(e.value)})"
        return super()._expr_Broadcast(e)

    def _expr_Binary(self, e: Binary) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Binary(e)
        if e.op == "+":
            for product, addend in ((e.a, e.b), (e.b, e.a)):
                if isinstance(product, Binary) and product.op == "*":
                    self._helpers["fma"] = FMA_MACRO
                    a, b, c = (self.expr(x) for x in (product.a, product.b, addend))
                    return f"nncg_vfmaq_f32({c}, {a}, {b})"
        a, b = self.expr(e.a), self.expr(e.b)
        if e.op == "/":
            self._helpers["div"] = DIV_HELPER
            return f"nncg_vdivq_f32({a}, {b})"
        return f"v{ARITH[e.op]}q_f32({a}, {b})"

    def _expr_Select(self, e: Select) -> str:
        if e.lanes not in self.simd:
            return super()._expr_Select(e)
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        # Correct everywhere; gcc 12 for ARMv7 spells vcgtq_f32 as a generic `a > b`, which it
        # compares lane by lane in VFP without -ffast-math (NEON flushes denormals); clang does not.
        return f"vbslq_f32(v{COMPARE[e.cmp]}q_f32({lhs}, {rhs}), {then}, {other})"

    def _expr_Call(self, e: Call) -> str:
        if e.lanes in self.simd:
            return f"nncg_v{e.fn}q_f32({self.expr(e.arg)})"
        return super()._expr_Call(e)

    def _lane_wise_helper(self, fn: str, lanes: int) -> str:
        """nncg_vFNq_f32(x): FN of each lane of x through the double-precision C function."""
        simd = self.simd[lanes]
        values = "".join(f"    v[{i}] = (float){fn}(v[{i}]);\n" for i in range(lanes))
        return (
            f"\n/* {fn} of each lane: no vector {fn} in the instruction set */\n"
            f"static {simd.type} nncg_v{fn}q_f32({simd.type} x)\n{{\n"
            f"    float v[{lanes}];\n    vst1q_f32(v, x);\n{values}    return vld1q_f32(v);\n}}\n"
        )
