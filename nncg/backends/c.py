"""Backend: prints the loop-nest IR as C. `AnsiC` is the strict C89 printer; SIMD backends subclass it
and override only the vector hooks (type, load, store, broadcast, arithmetic, select)."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from ..errors import NncgError
from ..ir.loops import (
    Affine,
    Assign,
    Binary,
    Bound,
    Broadcast,
    Call,
    Const,
    Expr,
    If,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Stmt,
    Store,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from ..ir.rename import rename_variables
from ..ir.target import Target
from ..safe_text import comment_name

INDENT = "    "

# Alignment of weight arrays and the static arena, and restrict for the layer functions' pointers:
# GNU spellings where the compiler has them, nothing (still correct C89) elsewhere.
PORTABILITY_MACROS = (
    "#if defined(__GNUC__) || defined(__clang__)",
    "#define NNCG_ALIGNED __attribute__((aligned(64)))",
    "#define NNCG_RESTRICT __restrict__",
    "#elif defined(_MSC_VER)",
    "#define NNCG_ALIGNED __declspec(align(64))",
    "#define NNCG_RESTRICT __restrict",
    "#else",
    "#define NNCG_ALIGNED",
    "#define NNCG_RESTRICT",
    "#endif",
)
VALUES_PER_LINE = 8


def c_float(value: float) -> str:
    """The shortest float32 literal that reads back to the same float32 (C89: no INFINITY macro)."""
    v = np.float32(value)
    if np.isnan(v):
        raise NncgError("the model contains a NaN constant; NNCG cannot print it as a C literal")
    if np.isinf(v):
        return "(-(float)HUGE_VAL)" if v < 0 else "((float)HUGE_VAL)"
    text = np.format_float_positional(v, unique=True, trim="0")
    if len(text) > 12:
        text = np.format_float_scientific(v, unique=True, trim="0")
    return text + "f"


def c_affine(index: Affine) -> str:
    parts = [var if c == 1 else f"{c} * {var}" for var, c in index.terms]
    if index.const or not parts:
        parts.append(str(index.const))
    return " + ".join(parts).replace("+ -", "- ")


def unparen(text: str) -> str:
    """Drops one pair of parentheses that encloses the whole expression."""
    if not (text.startswith("(") and text.endswith(")")):
        return text
    depth = 0
    for i, ch in enumerate(text):
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if depth == 0 and i < len(text) - 1:
            return text
    return text[1:-1]


def _without_clashes(kernel, program: Program):
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


def external_weights(program: Program) -> bool:
    """Whether plan-memory moved the constant arrays into a weights blob the caller passes."""
    return bool(program.arena and program.arena.weights_floats)


def weights_blob(program: Program) -> bytes:
    """The NAME.weights file: each constant array at its offset, little-endian float32, zero gaps."""
    blob = np.zeros(program.arena.weights_floats, dtype="<f4")
    for buf in program.role("constant"):
        blob[buf.offset : buf.offset + buf.size] = program.constants[buf.name].ravel()
    return blob.tobytes()


class AnsiC:
    """Strict C89 plus math.h: scalar code, conditional moves for max/min/select."""

    name = "ansi-c"
    lanes = 1  # the widest vector width
    vector_widths: tuple[int, ...] = ()  # the vector widths the printer has, widest first
    registers = 16  # vector (or float) registers, for register blocking: x86-64 has 16 xmm/ymm
    cflags: tuple[str, ...] = ()
    strict_cflags: tuple[str, ...] = ("-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror")
    includes: tuple[str, ...] = ("<math.h>",)
    scalar_type = "float"

    @property
    def target(self) -> Target:
        """The facts passes may use about this backend's hardware."""
        fma = any(getattr(simd, "fma", False) for simd in getattr(self, "simd", {}).values())
        return Target(self.name, self.vector_widths, self.registers, fma)

    # ------------------------------------------------------------------ the file

    def source(self, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
        """The .c file. `profile` adds per-layer timers (POSIX clock_gettime; for --profile only)."""
        if program.arena is None:
            raise NncgError("the program has no memory plan: run the plan-memory pass last")
        lines = [first_line]
        if profile:
            lines.append("#define _POSIX_C_SOURCE 199309L")
        lines.append(f'#include "{header_name}"')
        lines += [f"#include {inc}" for inc in (*self.includes, *(["<time.h>"] if profile else []))]
        lines += ["", *PORTABILITY_MACROS, ""]
        lines += self._constants(program)
        calls, passed = [], set()
        for kernel in program.kernels:
            params = self._kernel_params(program, kernel)
            lines += self._kernel(program.name, _without_clashes(kernel, program), params)
            calls.append(f"{program.name}_{kernel.name}({', '.join(b.name for b in params)});")
            passed |= {b.name for b in params}
        if profile:
            lines += self._profile_globals(program)
        lines += self._run_function(program, calls, passed, profile)
        lines += self._static_arena_function(program)
        return "\n".join(lines) + "\n"

    def _run_function(self, program: Program, calls: list[str], passed: set[str], profile: bool) -> list[str]:
        """NAME_run: points each internal buffer into the caller's arena, then runs the layers.
        `passed` names the buffers some layer takes; an input no layer reads is cast to void."""
        decls = [
            f"const float *const {b.name} = (const float *)weights + {b.offset};"
            for b in program.role("constant")
            if external_weights(program)
        ]
        decls += [
            f"float *const {b.name} = (float *)arena + {b.offset}; /* {'x'.join(map(str, b.shape))} {b.layout} */"
            for b in self._planned(program)
        ]
        if profile:
            decls.append("double start = nncg_now(), end;")
            calls = self._timed(program, calls)
        params = [b.name for b in (*program.role("input"), *program.role("output"))]
        unused = [f"(void){name};" for name in params if name not in passed]
        unused += [] if self._planned(program) else ["(void)arena;"]
        body = [*decls, *unused, *calls]
        return [self.run_signature(program), "{", *(INDENT + line for line in body), "}", ""]

    def _static_arena_function(self, program: Program) -> list[str]:
        """NAME: NAME_run with an arena of static storage, for callers that run one inference at a time."""
        args = [b.name for b in (*program.role("input"), *program.role("output"))]
        args += ["weights"] if external_weights(program) else []
        lines = []
        if program.arena.floats:
            lines += [f"static NNCG_ALIGNED float {program.name}_arena[{program.arena.floats}];", ""]
            args.append(f"{program.name}_arena")
        else:
            args.append("(void *)0")
        return lines + [self.signature(program), "{", f"{INDENT}{program.name}_run({', '.join(args)});", "}"]

    @staticmethod
    def _planned(program: Program) -> tuple:
        return tuple(b for b in program.role("internal") if b.offset is not None)

    @staticmethod
    def _profile_globals(program: Program) -> list[str]:
        names = ", ".join(f'"{k.name}"' for k in program.kernels)
        count = len(program.kernels)
        return [
            f"const int {program.name}_profile_count = {count};",
            f"const char *const {program.name}_profile_layers[{count}] = {{{names}}};",
            f"double {program.name}_profile_seconds[{count}];",
            "",
            "static double nncg_now(void)",
            "{",
            f"{INDENT}struct timespec t;",
            f"{INDENT}clock_gettime(CLOCK_MONOTONIC, &t);",
            f"{INDENT}return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;",
            "}",
            "",
        ]

    @staticmethod
    def _timed(program: Program, calls: list[str]) -> list[str]:
        """Each layer's call followed by adding its time to NAME_profile_seconds[i]."""
        out = []
        for i, call in enumerate(calls):
            out += [call, "end = nncg_now();", f"{program.name}_profile_seconds[{i}] += end - start;", "start = end;"]
        return out

    def header(self, program: Program, first_line: str) -> str:
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
        for buf in (*program.role("input"), *program.role("output")):
            shape = ",".join(map(str, buf.shape))
            lines.append(f"/* {buf.role} {comment_name(buf.onnx_name)}: float32[{shape}], row-major as in ONNX */")
            lines.append(f"#define {macro}_{buf.name.upper()}_SIZE {buf.size}")
        lines += [
            "",
            f"/* Activation memory: one arena of {macro}_ARENA_BYTES (the memory plan reuses space: without",
            f"   reuse the activations would take {arena.activation_floats * 4} bytes). Any float-aligned block",
            f"   works; {macro}_ARENA_ALIGN-byte alignment is fastest. */",
            f"#define {macro}_ARENA_BYTES {arena.floats * 4}",
            f"#define {macro}_ARENA_ALIGN {arena.align_floats * 4}",
            "",
            *self._weights_header(program),
            "/* Runs one inference: inputs, then outputs. Uses a static arena, so calls must not overlap. */",
            self.signature(program) + ";",
            "",
            f"/* Reentrant form: activations live in `arena` ({macro}_ARENA_BYTES bytes, owned by the caller),",
            "   so calls with distinct arenas may run at the same time. No buffer may overlap another. */",
            self.run_signature(program) + ";",
            "",
            "#ifdef __cplusplus",
            "}",
            "#endif",
            "",
            f"#endif /* {guard} */",
        ]
        return "\n".join(lines) + "\n"

    def _io_params(self, program: Program) -> list[str]:
        params = [f"const float *{b.name}" for b in program.role("input")]
        params += [f"float *{b.name}" for b in program.role("output")]
        return params + (["const void *weights"] if external_weights(program) else [])

    def signature(self, program: Program) -> str:
        return f"void {program.name}({', '.join(self._io_params(program))})"

    def run_signature(self, program: Program) -> str:
        return f"void {program.name}_run({', '.join([*self._io_params(program), 'void *arena'])})"

    def _weights_header(self, program: Program) -> list[str]:
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

    @staticmethod
    def _weights_check(program: Program) -> list[str]:
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

    def _constants(self, program: Program) -> list[str]:
        if external_weights(program):
            return self._weights_check(program)
        lines = []
        for buf in program.role("constant"):
            values = [c_float(v) for v in program.constants[buf.name].ravel()]
            lines.append(f"static NNCG_ALIGNED const float {buf.name}[{buf.size}] = {{")
            for i in range(0, len(values), VALUES_PER_LINE):
                lines.append(INDENT + ", ".join(values[i : i + VALUES_PER_LINE]) + ",")
            lines.append("};")
        return lines + ([""] if lines else [])

    @staticmethod
    def _kernel_params(program: Program, kernel) -> list:
        """The buffers a kernel touches that are not constant arrays of the file, in program order."""
        used = {s.buffer for s in walk_stmts(kernel.body) if isinstance(s, Store)}
        used |= {
            e.buffer
            for s in walk_stmts(kernel.body)
            for top in stmt_exprs(s)
            for e in walk_exprs(top)
            if isinstance(e, Load)
        }
        return [b for b in program.buffers if b.name in used and (b.role != "constant" or external_weights(program))]

    def _kernel(self, prefix: str, kernel, params) -> list[str]:
        """One static function per layer: compilers optimise several medium functions much faster
        than one huge one, and it inlines them back into the single entry point anyway. The memory
        plan never gives one layer overlapping buffers, so its pointers are restrict."""
        written = {s.buffer for s in walk_stmts(kernel.body) if isinstance(s, Store)}
        args = (
            ", ".join(f"{'' if b.name in written else 'const '}float *NNCG_RESTRICT {b.name}" for b in params) or "void"
        )
        loop_vars = sorted({s.var for s in walk_stmts(kernel.body) if isinstance(s, Loop)})
        lines = [f"/* {kernel.name}: {kernel.op} */", f"static void {prefix}_{kernel.name}({args})", "{"]
        if loop_vars:
            lines.append(f"{INDENT}int {', '.join(loop_vars)};")
        lines += self._stmts(kernel.body, 1)
        return lines + ["}", ""]

    # ------------------------------------------------------------------ statements

    def _stmts(self, body: tuple[Stmt, ...], depth: int) -> list[str]:
        out: list[str] = []
        for stmt in body:
            out += getattr(self, f"_stmt_{type(stmt).__name__}")(stmt, depth)
        return out

    def _stmt_Loop(self, loop: Loop, depth: int) -> list[str]:
        if loop.kind != "serial":
            raise NncgError(f"loop '{loop.var}' is still marked {loop.kind}: run the pass that materialises it")
        pad = INDENT * depth
        head = f"{pad}for ({loop.var} = 0; {loop.var} < {loop.extent}; ++{loop.var}) {{"
        return [head, *self._stmts(loop.body, depth + 1), pad + "}"]

    def _stmt_Let(self, let: Let, depth: int) -> list[str]:
        pad = INDENT * depth
        decl = f"{pad}{INDENT}{self.type_of(let.init.lanes)} {let.name} = {self.expr(let.init)};"
        return [pad + "{", decl, *self._stmts(let.body, depth + 1), pad + "}"]

    def _stmt_If(self, stmt: If, depth: int) -> list[str]:
        pad = INDENT * depth
        cond = " && ".join(self._bound(b) for b in stmt.bounds)
        return [f"{pad}if ({cond}) {{", *self._stmts(stmt.body, depth + 1), pad + "}"]

    def _bound(self, bound: Bound) -> str:
        e = c_affine(bound.expr)
        sides = ([f"{e} >= {bound.lo}"] if bound.lo is not None else []) + (
            [f"{e} < {bound.hi}"] if bound.hi is not None else []
        )
        return " && ".join(sides)

    def _stmt_Store(self, store: Store, depth: int) -> list[str]:
        return [INDENT * depth + self.store(store.buffer, store.index, store.value) + ";"]

    def _stmt_Assign(self, assign: Assign, depth: int) -> list[str]:
        return [INDENT * depth + self.assign(assign.name, assign.value) + ";"]

    # ------------------------------------------------------------------ scalar and vector hooks

    def type_of(self, lanes: int) -> str:
        self._scalar_only(lanes)
        return self.scalar_type

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        self._scalar_only(value.lanes)
        return f"{buffer}[{c_affine(index)}] = {unparen(self.expr(value))}"

    def assign(self, name: str, value: Expr) -> str:
        # acc = acc + e reads better as acc += e
        if isinstance(value, Binary) and value.op in "+-*/" and value.a == LocalRef(name, value.lanes):
            if value.lanes == 1:
                return f"{name} {value.op}= {unparen(self.expr(value.b))}"
        return f"{name} = {unparen(self.expr(value))}"

    def expr(self, e: Expr) -> str:
        return getattr(self, f"_expr_{type(e).__name__}")(e)

    def _expr_Const(self, e: Const) -> str:
        self._scalar_only(e.lanes)
        return c_float(e.values[0])

    def _expr_Load(self, e: Load) -> str:
        self._scalar_only(e.lanes)
        return f"{e.buffer}[{c_affine(e.index)}]"

    def _expr_LocalRef(self, e: LocalRef) -> str:
        return e.name

    def _expr_Broadcast(self, e: Broadcast) -> str:
        self._scalar_only(e.lanes)
        return self.expr(e.value)

    def _expr_Binary(self, e: Binary) -> str:
        self._scalar_only(e.lanes)
        a, b = self.expr(e.a), self.expr(e.b)
        if e.op == "max":  # the paper's conditional move
            return f"({a} > {b} ? {a} : {b})"
        if e.op == "min":
            return f"({a} < {b} ? {a} : {b})"
        return f"({a} {e.op} {b})"

    def _expr_Select(self, e) -> str:
        self._scalar_only(e.lanes)
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return f"({lhs} {e.cmp} {rhs} ? {then} : {other})"

    def _expr_Call(self, e: Call) -> str:
        self._scalar_only(e.lanes)
        return f"(float){e.fn}({self.expr(e.arg)})"  # C89 has only the double versions

    def _scalar_only(self, lanes: int) -> None:
        if lanes != 1:
            widths = "/".join(map(str, self.vector_widths)) or "1 (or not at all)"
            raise NncgError(f"target {self.name} cannot print {lanes}-lane vectors; run vectorize with lanes={widths}")
