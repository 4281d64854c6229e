"""Backend, file layer: the weights blob — NAME.weights when plan-memory moved the constant arrays
out of the C file — its CRC-32 check in the .c and its macros in the header."""

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


def weights_check(program: Program) -> list[str]:
    """NAME_weights_ok: 1 when the blob has the expected CRC-32 (bitwise, table-free: runs once)."""
    macro = program.name.upper()
    return [
        f"int {program.name}_weights_ok(const void *weights)",
        "{",
        f"{INDENT}const unsigned char *p = (const unsigned char *)weights;",
        f"{INDENT}unsigned long crc = 0xffffffffUL, i;",
        f"{INDENT}int bit;",
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
    return [
        f"/* Weights: the file {program.name}.weights, little-endian float32, passed as `weights` (its address",
        f"   in flash, or the file loaded or mapped into memory; {macro}_ARENA_ALIGN-byte alignment is fastest).",
        f"   {program.name}_weights_ok(weights) checks its CRC-32. */",
        f"#define {macro}_WEIGHTS_BYTES {len(blob)}",
        f"#define {macro}_WEIGHTS_CRC32 0x{zlib.crc32(blob):08x}UL",
        f"int {program.name}_weights_ok(const void *weights);",
        "",
    ]
