"""Backend, file layer: NAME.h — the parameter sizes, the arena, the weights blob and the two entry
points' signatures (which the .c repeats)."""

from __future__ import annotations

from collections.abc import Mapping

from ..ir.arena import typed_arena
from ..ir.kinds import BufferRole, DType
from ..ir.loops import Buffer, Program, Store, walk_stmts
from ..safe_text import comment_name
from .c_integer import SMALL_C_TYPES, c_type, header_typedefs
from .c_text import c_float, c_int
from .weights import external_weights, weights_header

LAYOUT_NOTES = {
    "nchw": "row-major NCHW (channels first)",
    "nhwc": "row-major NHWC (channels last, as in Keras)",
}


def header(
    program: Program,
    first_line: str,
    input_layout: str | None = None,
    io_quantization: Mapping[str, tuple[float, int]] | None = None,
) -> str:
    """NAME.h; `input_layout` (nchw, nhwc) names the layout of the 4-D inputs (default: as in ONNX);
    `io_quantization` (ONNX name -> scale, zero point) gives the integer inputs' and outputs' macros."""
    guard = f"{program.name.upper()}_H"
    macro = program.name.upper()
    arena = program.arena
    lines = [
        first_line,
        f"#ifndef {guard}",
        f"#define {guard}",
        "",
        "#ifdef __cplusplus",
        'extern "C" {',
        "#endif",
        "",
    ]
    lines += header_typedefs(program)
    for buf in (*program.role(BufferRole.INPUT), *program.role(BufferRole.OUTPUT)):
        shape = ",".join(map(str, buf.shape))
        layout = "row-major as in ONNX"
        if input_layout and buf.role == BufferRole.INPUT and len(buf.shape) == 4:
            layout = LAYOUT_NOTES[input_layout]
        lines.append(
            f"/* {buf.role} {comment_name(buf.onnx_name)}: {buf.dtype}[{shape}], {layout}{_dtype_note(program, buf)} */"
        )
        lines.append(f"#define {macro}_{buf.name.upper()}_SIZE {buf.size}")
        if buf.dtype.is_integer and buf.onnx_name in (io_quantization or {}):
            lines += _quantization_macros(f"{macro}_{buf.name.upper()}", *io_quantization[buf.onnx_name])
    lines += [
        "",
        f"/* Activation memory: one arena of {macro}_ARENA_BYTES (the memory plan reuses space: without",
        *_arena_kind(program, f"reuse the activations would take {arena.activation_floats * 4} bytes).", macro),
        f"#define {macro}_ARENA_BYTES {arena.floats * 4}",
        f"#define {macro}_ARENA_ALIGN {arena.align_floats * 4}",
        "",
        *weights_header(program),
        "/* Runs one inference: inputs, then outputs. Uses a static arena, so calls must not overlap. */",
        signature(program) + ";",
        "",
        f"/* Reentrant form: activations live in `arena` ({macro}_ARENA_BYTES bytes, owned by the caller),",
        "   so calls with distinct arenas may run at the same time. No buffer may overlap another. */",
        run_signature(program) + ";",
        "",
        "#ifdef __cplusplus",
        "}",
        "#endif",
        "",
        f"#endif /* {guard} */",
    ]
    return "\n".join(lines) + "\n"


def signature(program: Program) -> str:
    """NAME: inputs, then outputs (then the weights blob when there is one)."""
    return f"void {program.name}({', '.join(_io_params(program))})"


def _arena_kind(program, reuse: str, macro: str) -> list[str]:
    """The rest of the arena's comment: what memory the caller may pass."""
    if typed_arena(program):  # int16 or int32 regions besides float ones: no declared array has all those types
        return [
            f"   {reuse} It holds float and integer buffers, so pass",
            f"   allocated memory (malloc), not an array of one type; {macro}_ARENA_ALIGN-byte alignment",
            "   is fastest. */",
        ]
    return [f"   {reuse} Any float-aligned block", f"   works; {macro}_ARENA_ALIGN-byte alignment is fastest. */"]


def run_signature(program: Program) -> str:
    """NAME_run: NAME's parameters and the caller's arena."""
    return f"void {program.name}_run({', '.join([*_io_params(program), 'void *arena'])})"


def _dtype_note(program: Program, buf: Buffer) -> str:
    """What an integer input or output holds, in which C type."""
    if buf.dtype in (DType.INT8, DType.UINT8):
        return f"; quantized values in {c_type(buf.dtype)} ({SMALL_C_TYPES[buf.dtype]})"
    if buf.dtype != DType.INT32:
        return ""
    if _writer(program, buf) in ("ArgMax", "ArgMin"):
        return "; indices (ArgMax/ArgMin), int32 where ONNX says int64: C89 has no guaranteed 64-bit type"
    return "; int32 sums (ConvInteger/MatMulInteger), in nncg_int32 (int, or long where int is narrower)"


def _quantization_macros(prefix: str, scale: float, zero_point: int) -> list[str]:
    """An integer input's or output's scale and zero point. The suffixes _SIZE, _SCALE and _ZERO_POINT
    do not end one another, and buffer names differ ignoring case: no two macros coincide."""
    return [
        f"/* real = (q - {prefix}_ZERO_POINT) * {prefix}_SCALE; q = real / {prefix}_SCALE",
        f"   rounded half to even, plus {prefix}_ZERO_POINT, saturated to the type's range */",
        f"#define {prefix}_SCALE {c_float(scale)}",
        f"#define {prefix}_ZERO_POINT {c_int(zero_point)}",
    ]


def _writer(program: Program, buf: Buffer) -> str:
    """The op of the kernel that stores to `buf` ("" if none does)."""
    kernels = (
        k for k in program.kernels if any(isinstance(s, Store) and s.buffer == buf.name for s in walk_stmts(k.body))
    )
    return next((k.op for k in kernels), "")


def _io_params(program: Program) -> list[str]:
    params = [f"const {c_type(b.dtype)} *{b.name}" for b in program.role(BufferRole.INPUT)]
    params += [f"{c_type(b.dtype)} *{b.name}" for b in program.role(BufferRole.OUTPUT)]
    return params + (["const void *weights"] if external_weights(program) else [])
