"""Backend, file layer: NAME.c around the printed kernels — first line, includes, portability macros,
the constant arrays (or the weights check), one static function per layer, NAME_run over the
caller's arena, NAME over a static one, and the per-layer timers of --profile."""

from __future__ import annotations

from dataclasses import replace

from ..errors import NncgError
from ..ir.arena import arena_regions, typed_arena
from ..ir.kinds import BufferRole, DType
from ..ir.loops import Kernel, Let, Loop, Program, Store, read_buffer, stmt_exprs, walk_exprs, walk_stmts
from ..ir.rename import rename_variables
from .c_header import run_signature, signature
from .c_integer import c_type
from .c_text import INDENT, c_float, c_int
from .scalar import ScalarPrinter
from .weights import assume_aligned_macro, external_weights, weights_check, weights_pointers

# Alignment of weight arrays and the static arena, restrict for the layer functions' pointers,
# NNCG_INLINE for the vector helpers (the math functions, narrowing stores): a call to one passes
# vectors in registers the ABI does not preserve, so every accumulator of the register block around it
# is spilled; gcc -O2 and -Os call the sigmoid of a SiLU epilogue (1x1 conv 16->96 at 48x48, ssse3:
# 598 us at -O2, 518 us with it inlined, as at -O3); and NNCG_NOINLINE for the layer functions (see
# _kernel_function). GNU and MSVC spellings where the compiler has them, nothing (still C89) elsewhere.
PORTABILITY_MACROS = (
    "#if defined(__GNUC__) || defined(__clang__)",
    "#define NNCG_ALIGNED __attribute__((aligned(64)))",
    "#define NNCG_RESTRICT __restrict__",
    "#define NNCG_INLINE __inline__ __attribute__((always_inline))",
    "#define NNCG_NOINLINE __attribute__((noinline))",
    "#elif defined(_MSC_VER)",
    "#define NNCG_ALIGNED __declspec(align(64))",
    "#define NNCG_RESTRICT __restrict",
    "#define NNCG_INLINE __forceinline",
    "#define NNCG_NOINLINE __declspec(noinline)",
    "#else",
    "#define NNCG_ALIGNED",
    "#define NNCG_RESTRICT",
    "#define NNCG_INLINE",
    "#define NNCG_NOINLINE",
    "#endif",
)
VALUES_PER_LINE = 8
FLOAT_BYTES = 4  # the unit of arena offsets


def source(printer: ScalarPrinter, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
    """The .c file. `profile` adds per-layer timers (POSIX clock_gettime; for --profile only)."""
    if program.arena is None:
        raise NncgError("the program has no memory plan: run the plan-memory pass last")
    printer = printer.for_program(program)
    lines = [first_line]
    if profile:
        lines.append("#define _POSIX_C_SOURCE 199309L")
    lines.append(f'#include "{header_name}"')
    lines += [f"#include {inc}" for inc in printer.includes]
    lines += ["#include <stddef.h>"] if external_weights(program) else []  # size_t, for the alignment check
    lines += ["#include <time.h>"] if profile else []
    lines += ["", *PORTABILITY_MACROS, *(assume_aligned_macro() if external_weights(program) else ())]
    lines += [*printer.preamble(), ""]
    lines += _constants(program)
    calls, passed = [], set()
    for kernel in program.kernels:
        params = _kernel_params(program, kernel)
        lines += _kernel_function(printer, program.name, _without_clashes(kernel, program), params)
        calls.append(f"{program.name}_{kernel.name}({', '.join(b.name for b in params)});")
        passed |= {b.name for b in params}
    if profile:
        lines += _profile_globals(program)
    lines += _run_function(program, calls, passed, profile)
    lines += _static_arena_function(program)
    return "\n".join(lines) + "\n"


def _constants(program: Program) -> list[str]:
    """The constant arrays, aligned; with a weights blob only its check."""
    if external_weights(program):
        return weights_check(program)
    lines = []
    for buf in program.role(BufferRole.CONSTANT):
        literal = c_float if buf.dtype == DType.FLOAT32 else c_int
        values = [literal(v) for v in program.constants[buf.name].ravel()]
        lines.append(f"static NNCG_ALIGNED const {c_type(buf.dtype)} {buf.name}[{buf.size}] = {{")
        for i in range(0, len(values), VALUES_PER_LINE):
            lines.append(INDENT + ", ".join(values[i : i + VALUES_PER_LINE]) + ",")
        lines.append("};")
    return lines + ([""] if lines else [])


def _kernel_params(program: Program, kernel: Kernel) -> list:
    """The buffers a kernel touches that are not constant arrays of the file, in program order."""
    used = {s.buffer for s in walk_stmts(kernel.body) if isinstance(s, Store)}
    used |= {read_buffer(e) for s in walk_stmts(kernel.body) for top in stmt_exprs(s) for e in walk_exprs(top)}
    return [
        b for b in program.buffers if b.name in used and (b.role != BufferRole.CONSTANT or external_weights(program))
    ]


def _without_clashes(kernel: Kernel, program: Program) -> Kernel:
    """The kernel with loop variables and locals renamed where a buffer has their name (a model
    input called `w` or `acc`), so the C function's locals do not shadow its pointers."""
    taken = {b.name for b in program.buffers}
    local = {s.var for s in walk_stmts(kernel.body) if isinstance(s, Loop)}
    local |= {s.name for s in walk_stmts(kernel.body) if isinstance(s, Let)}
    names = {}
    for name in sorted(local & taken):
        new = name + "_"
        while new in taken or new in local:
            new += "_"
        names[name] = new
    return replace(kernel, body=rename_variables(kernel.body, names)) if names else kernel


def _kernel_function(printer: ScalarPrinter, prefix: str, kernel: Kernel, params) -> list[str]:
    """One static function per layer, kept out of line: compilers optimise several medium functions
    much faster than one huge one, and better: gcc 12 -O3, inlining every layer into the entry point,
    made dscnn 1.12x slower on avx2 (60.1 us vs 53.5), keras_mobilenet_nhwc_96 1.14x, mobilenet_v2_96
    1.20x on ssse3, mnasnet0_5_96 1.06x on avx2 (none of 10 models faster by more than 2 %; a call per
    layer costs nothing). It also keeps --tune honest: it times each layer as its own function, and the
    register blocks it chose for dscnn ran 1.6x slower once inlined. The memory plan never gives one
    layer overlapping buffers, so its pointers are restrict."""
    written = {s.buffer for s in walk_stmts(kernel.body) if isinstance(s, Store)}
    args = [f"{'' if b.name in written else 'const '}{c_type(b.dtype)} *NNCG_RESTRICT {b.name}" for b in params]
    args = ", ".join(args) or "void"
    head = [f"/* {kernel.name}: {kernel.op} */", f"static NNCG_NOINLINE void {prefix}_{kernel.name}({args})", "{"]
    return head + printer.function_body(kernel.body) + ["}", ""]


def _run_function(program: Program, calls: list[str], passed: set[str], profile: bool) -> list[str]:
    """NAME_run: points each weight array into the blob (constant offsets from a pointer promised
    NAME_WEIGHTS_ALIGN-byte aligned) and each internal buffer into the caller's arena, then runs the
    layers. `passed` names the buffers some layer takes; an input no layer reads is cast to void."""
    decls = weights_pointers(program) if external_weights(program) else []
    typed = typed_arena(program)
    decls += [f"{_arena_pointer(b, typed)}; /* {'x'.join(map(str, b.shape))} {b.layout} */" for b in _planned(program)]
    if profile:
        decls.append("double start = nncg_now(), end;")
        calls = _timed(program, calls)
    params = [b.name for b in (*program.role(BufferRole.INPUT), *program.role(BufferRole.OUTPUT))]
    unused = [f"(void){name};" for name in params if name not in passed]
    unused += [] if _planned(program) else ["(void)arena;"]
    body = [*decls, *unused, *calls]
    return [run_signature(program), "{", *(INDENT + line for line in body), "}", ""]


def _arena_pointer(buf, typed: bool) -> str:
    """The declaration of a buffer's pointer into the arena. An arena of float regions only is used as
    a float array (offsets count floats); an int8 or uint8 buffer is read and written through a
    character type, which may access any object. An arena with int16 or int32 regions is addressed
    in bytes, as the struct of typed regions it is (ir/arena.py); the pointer passes through void *,
    as the offset keeps the element type's alignment."""
    ctype = c_type(buf.dtype)
    if typed:
        return f"{ctype} *const {buf.name} = ({ctype} *)(void *)((char *)arena + {buf.offset * FLOAT_BYTES})"
    if buf.dtype == DType.FLOAT32:
        return f"float *const {buf.name} = (float *)arena + {buf.offset}"
    return f"{ctype} *const {buf.name} = ({ctype} *)((float *)arena + {buf.offset})"


def _static_arena_function(program: Program) -> list[str]:
    """NAME: NAME_run with an arena of static storage, for callers that run one inference at a time."""
    args = [b.name for b in (*program.role(BufferRole.INPUT), *program.role(BufferRole.OUTPUT))]
    args += ["weights"] if external_weights(program) else []
    lines = []
    if program.arena.floats and typed_arena(program):
        lines += _static_typed_arena(program)
        args.append(f"&{program.name}_arena")
    elif program.arena.floats:
        lines += [f"static NNCG_ALIGNED float {program.name}_arena[{program.arena.floats}];", ""]
        args.append(f"{program.name}_arena")
    else:
        args.append("(void *)0")
    return lines + [signature(program), "{", f"{INDENT}{program.name}_run({', '.join(args)});", "}"]


def _static_typed_arena(program: Program) -> list[str]:
    """The static arena as a struct of one array per typed region, so each buffer is an object of its
    own type. The typedef does not compile where the struct has padding (the regions would move) or
    an element type is not the size the plan counts."""
    struct = f"struct {program.name}_arena_regions"
    members = [
        f"{INDENT}{c_type(r.dtype)} r{i}[{r.floats * FLOAT_BYTES // r.dtype.bytes}];"
        for i, r in enumerate(arena_regions(program))
    ]
    bytes_ = program.arena.floats * FLOAT_BYTES
    return [
        f"{struct} {{",
        *members,
        "};",
        f"typedef char {program.name}_arena_unpadded[sizeof({struct}) == {bytes_} ? 1 : -1];",
        f"static NNCG_ALIGNED {struct} {program.name}_arena;",
        "",
    ]


def _planned(program: Program) -> tuple:
    return tuple(b for b in program.role(BufferRole.INTERNAL) if b.offset is not None)


# The clock the profile timers read: wall time unless the build says otherwise; the benchmarks' CPU
# time (PROFILE_CPU_TIME_FLAG) leaves out the time the thread waits for a shared core.
PROFILE_CLOCK_DEFAULT = ("#ifndef NNCG_PROFILE_CLOCK", "#define NNCG_PROFILE_CLOCK CLOCK_MONOTONIC", "#endif")
PROFILE_CPU_TIME_FLAG = "-DNNCG_PROFILE_CLOCK=CLOCK_THREAD_CPUTIME_ID"


def _profile_globals(program: Program) -> list[str]:
    names = ", ".join(f'"{k.name}"' for k in program.kernels)
    count = len(program.kernels)
    return [
        f"const int {program.name}_profile_count = {count};",
        f"const char *const {program.name}_profile_layers[{count}] = {{{names}}};",
        f"double {program.name}_profile_seconds[{count}];",
        "",
        *PROFILE_CLOCK_DEFAULT,
        "static double nncg_now(void)",
        "{",
        f"{INDENT}struct timespec t;",
        f"{INDENT}clock_gettime(NNCG_PROFILE_CLOCK, &t);",
        f"{INDENT}return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;",
        "}",
        "",
    ]


def _timed(program: Program, calls: list[str]) -> list[str]:
    """Each layer's call followed by adding its time to NAME_profile_seconds[i]."""
    out = []
    for i, call in enumerate(calls):
        out += [call, "end = nncg_now();", f"{program.name}_profile_seconds[{i}] += end - start;", "start = end;"]
    return out
