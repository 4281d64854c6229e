"""Backend, file layer: the weights blob — NAME.weights when plan-memory moved the constant arrays
out of the C file — its check in the .c (alignment and CRC-32), its macros and its contract in the header.

The contract lets the blob run as fast as embedded arrays: the pointer is NAME_WEIGHTS_ALIGN-byte
aligned (every array in the blob starts at a multiple of it, as the embedded arrays are aligned), read
only, and overlaps no input, output or arena. The .c promises the compiler the alignment
(NNCG_ASSUME_ALIGNED) and passes each array to its layer as a restrict pointer at a constant offset.
Misalignment is what cost the speed: a blob from malloc (16-byte aligned) made half the AVX2
loads and every AVX-512 load of weights split across cache lines."""

from __future__ import annotations

import zlib

import numpy as np

from ..ir.kinds import BufferRole
from ..ir.loops import Program
from .c_text import INDENT


def external_weights(program: Program) -> bool:
    """Whether plan-memory moved the constant arrays into a weights blob the caller passes."""
    return bool(program.arena and program.arena.weights_floats)


def weights_blob(program: Program) -> bytes:
    """The NAME.weights file: each constant array at its offset, little-endian float32, zero gaps."""
    blob = np.zeros(program.arena.weights_floats, dtype="<f4")
    for buf in program.role(BufferRole.CONSTANT):
        blob[buf.offset : buf.offset + buf.size] = program.constants[buf.name].ravel()
    return blob.tobytes()


def weights_align(program: Program) -> int:
    """The blob's alignment in bytes: the memory plan's, at which every array in it starts."""
    return program.arena.align_floats * 4


def assume_aligned_macro() -> list[str]:
    """NNCG_ASSUME_ALIGNED(p, n): p, with the compiler told it is n-byte aligned where it can be
    (GCC 4.7+, clang); plain p elsewhere, so C89 compilers take it too."""
    return [
        "#if defined(__clang__) || (defined(__GNUC__) && (__GNUC__ > 4 || (__GNUC__ == 4 && __GNUC_MINOR__ >= 7)))",
        "#define NNCG_ASSUME_ALIGNED(p, n) __builtin_assume_aligned((p), (n))",
        "#else",
        "#define NNCG_ASSUME_ALIGNED(p, n) (p)",
        "#endif",
    ]


def weights_pointers(program: Program) -> list[str]:
    """NAME_run's declarations of the weight arrays: the blob promised aligned once, then each array
    at its constant offset (each a multiple of the alignment)."""
    align = f"{program.name.upper()}_WEIGHTS_ALIGN"
    lines = [f"const float *const nncg_weights = (const float *)NNCG_ASSUME_ALIGNED(weights, {align});"]
    return lines + [
        f"const float *const {b.name} = nncg_weights + {b.offset};" for b in program.role(BufferRole.CONSTANT)
    ]


def weights_check(program: Program) -> list[str]:
    """NAME_weights_ok: 1 when the pointer has the promised alignment and the blob the expected
    CRC-32 (bitwise, table-free: runs once)."""
    macro = program.name.upper()
    return [
        f"int {program.name}_weights_ok(const void *weights)",
        "{",
        f"{INDENT}const unsigned char *p = (const unsigned char *)weights;",
        f"{INDENT}unsigned long crc = 0xffffffffUL, i;",
        f"{INDENT}int bit;",
        f"{INDENT}if (p == 0 || (size_t)p % {macro}_WEIGHTS_ALIGN != 0) {{",
        f"{INDENT * 2}return 0; /* the code assumes the alignment: a misaligned blob would be slow or fault */",
        f"{INDENT}}}",
        f"{INDENT}for (i = 0; i < {macro}_WEIGHTS_BYTES; ++i) {{",
        f"{INDENT * 2}crc ^= p[i];",
        f"{INDENT * 2}for (bit = 0; bit < 8; ++bit) {{",
        f"{INDENT * 3}crc = (crc >> 1) ^ (0xedb88320UL & (0UL - (crc & 1UL)));",
        f"{INDENT * 2}}}",
        f"{INDENT}}}",
        f"{INDENT}return ((crc ^ 0xffffffffUL) & 0xffffffffUL) == {macro}_WEIGHTS_CRC32;",
        "}",
        "",
    ]


def weights_header(program: Program) -> list[str]:
    """The header's description of the blob: its size, CRC-32 and check function; none when embedded."""
    if not external_weights(program):
        return []
    macro, blob = program.name.upper(), weights_blob(program)
    name = program.name
    return [
        f"/* Weights: the file {name}.weights, little-endian float32, passed as `weights`: its address in",
        "   flash, or the file loaded or mapped into memory. The generated code relies on three promises,",
        "   which make the blob as fast as weights compiled into the C file:",
        f"   - `weights` is {macro}_WEIGHTS_ALIGN-byte aligned. malloc's alignment is not enough: use",
        "     aligned_alloc or posix_memalign, over-allocate and round the address up, map the file (mmap",
        "     is page-aligned), or align it in flash with the linker;",
        "   - it is read only: the model never writes it, and nothing may write it while the model runs;",
        "   - it overlaps none of the inputs, outputs and arena.",
        f"   {name}_weights_ok(weights) returns 1 when `weights` is aligned and its {macro}_WEIGHTS_BYTES",
        "   bytes have the CRC-32 below; call it once after loading, never pass a blob that fails it. */",
        f"#define {macro}_WEIGHTS_BYTES {len(blob)}",
        f"#define {macro}_WEIGHTS_ALIGN {weights_align(program)}",
        f"#define {macro}_WEIGHTS_CRC32 0x{zlib.crc32(blob):08x}UL",
        f"int {program.name}_weights_ok(const void *weights);",
        "",
    ]
