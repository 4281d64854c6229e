"""Backend: the C of the int8 path — the integer types (strict C89 has no <stdint.h>: they are
derived from <limits.h>) and the requantisation helpers, printed only for programs that use them.

The fixed-point form needs the high half of a 32x32-bit product, which C89 cannot hold in one
integer (long is only guaranteed 32 bits): the magnitudes are split into 16-bit halves and the
partial products, each below 2^32, are summed with their carries in unsigned long."""

from __future__ import annotations

from ..ir.kinds import BufferRole, DType
from ..ir.loops import Program, Requantize, RequantizeFixed, stmt_exprs, walk_exprs, walk_stmts

C_TYPES = {
    DType.FLOAT32: "float",
    DType.FLOAT64: "double",
    DType.INT8: "nncg_int8",
    DType.UINT8: "nncg_uint8",
    DType.INT16: "nncg_int16",
    DType.INT32: "nncg_int32",
}

# What the small types are, for the header's notes.
SMALL_C_TYPES = {DType.INT8: "signed char", DType.UINT8: "unsigned char"}

# signed char and short hold int8 and int16 on every two's complement machine; int holds int32
# where INT_MAX says so, else long (at least 32 bits in C89).
INT32_TYPEDEF = (
    "#if INT_MAX >= 2147483647",
    "typedef int nncg_int32;",
    "#else",
    "typedef long nncg_int32;",
    "#endif",
)
SMALL_TYPEDEFS = (
    "#if SCHAR_MIN > -128",
    '#error "the int8 code needs a signed char that holds -128"',
    "#endif",
    "typedef signed char nncg_int8;",
    "typedef unsigned char nncg_uint8;",
    "typedef short nncg_int16;",
)
TYPEDEFS = ("#include <limits.h>", *SMALL_TYPEDEFS, *INT32_TYPEDEF)
# The header's types, for a function with integer inputs or outputs: nncg_int32 always, the small
# types where an input or output is int8 or uint8. Guarded, so that headers of several models can
# be included together, and then not repeated by the .c file.
HEADER_INT32_TYPEDEFS = ("#ifndef NNCG_INT32_DEFINED", "#define NNCG_INT32_DEFINED", *INT32_TYPEDEF, "#endif")
HEADER_SMALL_TYPEDEFS = ("#ifndef NNCG_INT8_DEFINED", "#define NNCG_INT8_DEFINED", *SMALL_TYPEDEFS, "#endif")

REQUANTIZE = (
    "/* x clamped to [low - zero_point, high - zero_point] (NaN: low), rounded half to even, plus",
    "   zero_point: the float form of requantisation, as onnxruntime's CPU kernels compute it. The",
    "   clamp keeps |x| small, so the conversion truncates exactly and x - i is exact. */",
    "static nncg_int32 nncg_requantize(float x, nncg_int32 zero_point, nncg_int32 low, nncg_int32 high)",
    "{",
    "    nncg_int32 i;",
    "    float d;",
    "    if (!(x >= (float)(low - zero_point))) x = (float)(low - zero_point);",
    "    if (x > (float)(high - zero_point)) x = (float)(high - zero_point);",
    "    i = (nncg_int32)x;",
    "    d = x - (float)i;",
    "    if (d > 0.5f || (d == 0.5f && i % 2 != 0)) ++i;",
    "    else if (d < -0.5f || (d == -0.5f && i % 2 != 0)) --i;",
    "    return i + zero_point;",
    "}",
)

REQUANTIZE_FIXED = (
    "/* x * multiplier / 2^(31 + shift) rounded half away from zero, in one rounding (CMSIS-NN's",
    "   single-rounding requantisation), plus zero_point, saturated to [low, high]. multiplier is in",
    "   [2^30, 2^31), shift in [0, 31]. The product of the magnitudes, below 2^62, is summed from",
    "   16-bit halves (each partial product below 2^32): q is its bits from 31 up, s1 holds bits 16",
    "   to 31 (and carries); rounding at bit 30 + shift adds 2^(shift - 1) to q, or bit 30 when",
    "   shift is 0. */",
    "static nncg_int32 nncg_requantize_fixed(nncg_int32 x, nncg_int32 multiplier, nncg_int32 shift,",
    "                                        nncg_int32 zero_point, nncg_int32 low, nncg_int32 high)",
    "{",
    "    unsigned long a = x < 0 ? 0UL - (unsigned long)x : (unsigned long)x;",
    "    unsigned long b = (unsigned long)multiplier;",
    "    unsigned long a1 = a >> 16, a0 = a & 0xFFFFUL, b1 = b >> 16, b0 = b & 0xFFFFUL;",
    "    unsigned long lo = a0 * b0, mid = a1 * b0 + a0 * b1;",
    "    unsigned long s1 = (lo >> 16) + (mid & 0xFFFFUL);",
    "    unsigned long q = 2UL * (a1 * b1 + (mid >> 16) + (s1 >> 16)) + ((s1 >> 15) & 1UL);",
    "    nncg_int32 y;",
    "    if (shift > 0) q = (q + (1UL << (shift - 1))) >> shift;",
    "    else q += (s1 >> 14) & 1UL;",
    "    y = x < 0 ? -(nncg_int32)q : (nncg_int32)q;",
    "    return y < low - zero_point ? low : (y > high - zero_point ? high : y + zero_point);",
    "}",
)


def c_type(dtype: DType) -> str:
    return C_TYPES[DType(dtype)]


def _io_dtypes(program: Program) -> set[DType]:
    return {b.dtype for b in program.buffers if b.role in (BufferRole.INPUT, BufferRole.OUTPUT)}


def has_integer_io(program: Program) -> bool:
    """Whether an input or output of the function is not float32: its header defines nncg_int32."""
    return bool(_io_dtypes(program) - {DType.FLOAT32})


def has_small_io(program: Program) -> bool:
    """Whether an input or output is int8 or uint8: its header defines the small types too."""
    return bool(_io_dtypes(program) & {DType.INT8, DType.UINT8})


def header_typedefs(program: Program) -> list[str]:
    """The integer types the header's prototypes name; nothing for a float32 interface."""
    if not has_integer_io(program):
        return []
    small = HEADER_SMALL_TYPEDEFS if has_small_io(program) else ()
    return ["#include <limits.h>", *small, *HEADER_INT32_TYPEDEFS, ""]


def integer_preamble(program: Program) -> list[str]:
    """The typedefs (but the header's) and the helpers the program calls; nothing for a float program."""
    if all(b.dtype == DType.FLOAT32 for b in program.buffers):
        return []
    kinds = {
        type(e)
        for k in program.kernels
        for s in walk_stmts(k.body)
        for top in stmt_exprs(s)
        for e in walk_exprs(top)
        if isinstance(e, Requantize | RequantizeFixed) and e.lanes == 1  # vectors requantise inline
    }
    typedefs = TYPEDEFS
    if has_integer_io(program):  # the header has <limits.h>, nncg_int32 and maybe the small types
        small = any(b.dtype in (DType.INT8, DType.UINT8, DType.INT16) for b in program.buffers)
        typedefs = SMALL_TYPEDEFS if small and not has_small_io(program) else ()
    lines = ["", *typedefs] if typedefs else []
    for kind, helper in ((Requantize, REQUANTIZE), (RequantizeFixed, REQUANTIZE_FIXED)):
        lines += ["", *helper] if kind in kinds else []
    return lines
