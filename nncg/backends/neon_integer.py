"""Backend: the int8 kernels' int32 vectors on NEON (int32x4_t), one spelling for ARMv7 and AArch64:
the reduction over input channels two at a time as widening multiply-accumulates (vmlal_s16 on the
int16 pairs of loops.Dot; neon_dotprod.py: four at a time, sdot), elsewhere 8-bit loads widened with
vmovl and 32-bit multiply and add (vmulq_s32 feeding vaddq_s32, which gcc and clang fuse into one
vmla/mla), requantisation as onnxruntime computes it (clamp in float, round half
to even, add the zero point) and saturating narrowing stores (vqmovn, vqmovun).

Four bytes are loaded and stored lane by lane (vld1_lane, vst1_lane): NEON's smallest whole load,
vld1_u8, reads eight, past the end of a buffer of four; a 32-bit lane load would need an aligned
uint32_t. Lane numbers are the same whatever the byte order, so no reinterpretation is involved."""

from __future__ import annotations

# x clamped to [low, high] as the scalar nncg_requantize does it (NaN -> low: vmaxq_f32 would keep the
# NaN), rounded half to even, plus the zero point. AArch64 has the rounding conversion (vcvtnq). ARMv7
# NEON converts only by truncation; there x + 1.5 * 2^23 is computed in float: for |x| < 2^22 the sum
# lies in [2^23, 2^24), where floats are the integers, so the one addition rounds x to an integer,
# half to even (ARMv7 NEON always rounds to nearest even; 1.5 * 2^23 is even, so the tie goes to the
# even x). In that binade the bit pattern is linear in the value, bits(1.5 * 2^23 + k) = 0x4B400000 + k,
# so subtracting 0x4B400000 - zero_point from the bits gives round(x) + zero_point exactly. The int8
# kernels store 8-bit values, so |x| <= high - low <= 255, far inside 2^22.
REQUANTIZE = (
    "/* x clamped to [low, high] (NaN: low), rounded half to even, plus zero_point: onnxruntime's float",
    "   requantisation. ARMv7 has no rounding conversion: x + 1.5 * 2^23 rounds x to an integer, half to",
    "   even, and for |x| < 2^22 its bits are 0x4B400000 + round(x) (|x| <= 255 here) */",
    "static NNCG_INLINE int32x4_t nncg_vrequantizeq_s32(float32x4_t x, float low, float high, int32_t zero_point)",
    "{",
    "    x = vbslq_f32(vcgeq_f32(x, vdupq_n_f32(low)), x, vdupq_n_f32(low));",
    "    x = vminq_f32(x, vdupq_n_f32(high));",
    "#if defined(__aarch64__)",
    "    return vaddq_s32(vcvtnq_s32_f32(x), vdupq_n_s32(zero_point));",
    "#else",
    "    x = vaddq_f32(x, vdupq_n_f32(12582912.0f));",
    "    return vsubq_s32(vreinterpretq_s32_f32(x), vdupq_n_s32(0x4B400000 - zero_point));",
    "#endif",
    "}",
)


# A constant vector lane by lane (no intrinsic takes four lanes): the compiler inlines it into one
# constant load; unlike a braced initialiser or vcreate, the same lanes whatever the byte order.
VECTOR = (
    "static NNCG_INLINE int32x4_t nncg_vsetq_s32(int32_t a, int32_t b, int32_t c, int32_t d)",
    "{",
    "    int32_t v[4];",
    "    v[0] = a;",
    "    v[1] = b;",
    "    v[2] = c;",
    "    v[3] = d;",
    "    return vld1q_s32(v);",
    "}",
)


def _widen(dtype: str) -> tuple[str, ...]:
    """The four bytes at p, each widened to an int32 lane."""
    s, vt = ("s", "int8x8_t") if dtype == "int8" else ("u", "uint8x8_t")
    widen = f"vmovl_{s}16(vget_low_{s}16(vmovl_{s}8(b)))"
    value = widen if s == "s" else f"vreinterpretq_s32_u32({widen})"
    return (
        f"/* the four {dtype} values at p, widened to int32 lanes */",
        f"static NNCG_INLINE int32x4_t nncg_vwidenq_{dtype}(const nncg_{dtype} *p)",
        "{",
        f"    {vt} b = vdup_n_{s}8(0);",
        *(f"    b = vld1_lane_{s}8(p + {i}, b, {i});" for i in range(4)),
        f"    return {value};",
        "}",
    )


def _store(dtype: str) -> tuple[str, ...]:
    """The narrowing store of four int32 lanes already in the type's range (the saturation changes nothing)."""
    s, vt, narrow = ("s", "int8x8_t", "vqmovn_s16") if dtype == "int8" else ("u", "uint8x8_t", "vqmovun_s16")
    return (
        f"static NNCG_INLINE void nncg_vstoreq_{dtype}(nncg_{dtype} *p, int32x4_t v)",
        "{",
        "    int16x4_t h = vqmovn_s32(v);",
        f"    {vt} b = {narrow}(vcombine_s16(h, h));",
        *(f"    vst1_lane_{s}8(p + {i}, b, {i});" for i in range(4)),
        "}",
    )


# Two input channels per step, for ARMv7 and AArch64 without the dot-product extension: the packed
# pairs (lane l's two weights side by side, loops.Dot) widened to int16 and split by channel (vuzp),
# each multiplied by its int16 activation and accumulated into int32 by vmlal: exact (x - x_zero_point
# in [-255, 255] and an int8 weight are int16 values, their products and sums int32).
DOT2 = (
    "/* acc + the dot products of int16 pairs: lane l adds x0 * w[2l] + x1 * w[2l + 1], x0 and x1 the",
    "   low and high int16 halves of xs' lanes (split in a register: the same whatever the byte order) */",
    "static int32x4_t nncg_vdot2q_s32(int32x4_t acc, int32x4_t xs, const nncg_int8 *w)",
    "{",
    "    int16x8_t pairs = vmovl_s8(vld1_s8(w));",
    "    int16x4x2_t channels = vuzp_s16(vget_low_s16(pairs), vget_high_s16(pairs));",
    "    int16x4_t x = vreinterpret_s16_s32(vget_low_s32(xs));",
    "    acc = vmlal_lane_s16(acc, channels.val[0], x, 0);",
    "    return vmlal_lane_s16(acc, channels.val[1], x, 1);",
    "}",
)


def neon_integer() -> dict:
    """VectorWidth fields `ints` and `int_helpers` of NEON's q registers."""
    ints = {
        "type": "int32x4_t",
        "load": "vld1q_s32((const int32_t *)({address}))",
        "widen_uint8": "nncg_vwidenq_uint8({address})",
        "widen_int8": "nncg_vwidenq_int8({address})",
        "splat": "vdupq_n_s32({value})",
        "vector": "nncg_vsetq_s32({values})",
        "+": "vaddq_s32({a}, {b})",
        "-": "vsubq_s32({a}, {b})",
        "*": "vmulq_s32({a}, {b})",
        "max": "vmaxq_s32({a}, {b})",
        "convert": "vcvtq_f32_s32({a})",
        "requantize": "nncg_vrequantizeq_s32({value}, {low}, {high}, {zero_point})",
        "store_uint8": "nncg_vstoreq_uint8({address}, {value})",
        "store_int8": "nncg_vstoreq_int8({address}, {value})",
        "store_int32": "vst1q_s32((int32_t *)({address}), {value})",
        "widen_int16": "vmovl_s16(vld1_s16((const int16_t *)({address})))",
        "dot2_add": "nncg_vdot2q_s32({acc}, {xs}, {address})",
    }
    helpers = {
        "requantize": REQUANTIZE,
        "vector": VECTOR,
        **{f"widen_{t}": _widen(t) for t in ("uint8", "int8")},
        **{t: _store(t) for t in ("uint8", "int8")},
        "dot2": DOT2,
    }
    return {"ints": ints, "int_helpers": helpers}
