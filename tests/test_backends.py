"""The backend family: a new ISA is one file of tables (a fake 8-lane one, built and run), the FMA
legalisation (Before/Expected), the helpers collected before printing, and the dependency rule."""

import re
from pathlib import Path

import numpy as np
import pytest

from nncg.backends import BACKENDS, get_backend
from nncg.backends.backend import Backend
from nncg.backends.legalize import fuse_multiply_add
from nncg.backends.neon import Neon
from nncg.backends.simd import SimdPrinter
from nncg.backends.simd_needs import Needs, collect_needs
from nncg.backends.ssse3 import Ssse3
from nncg.backends.vector_width import VectorWidth
from nncg.ir.kinds import DType
from nncg.ir.loops import (
    Affine,
    ArenaPlan,
    Binary,
    Broadcast,
    Buffer,
    Call,
    Const,
    Fma,
    Kernel,
    Load,
    LocalRef,
    Loop,
    Program,
    Select,
    Store,
)
from nncg.ir.target import Target
from nncg.ir.text import expr_to_text
from nncg.ir.verify import verify_program
from nncg.tools import run_tool
from nncg.verify import find_c_compiler

A = Affine.of
ROOT = Path(__file__).resolve().parent.parent

# ------------------------------------------------------------------------- a new ISA is one file

ARITH = {"+": "add", "-": "sub", "*": "mul", "/": "div", "max": "max", "min": "min"}
COMPARE = {">": "gt", ">=": "ge", "<": "lt", "<=": "le"}
FAKE8 = VectorWidth(
    "f32x8",
    {
        "load": "f8_load({address})",
        "store": "f8_store({address}, {value})",
        "splat": "f8_dup({value})",
        "table": "f8_constants",
        **{op: f"f8_{name}({{a}}, {{b}})" for op, name in {"+": "add", "-": "sub", "*": "mul", "max": "max"}.items()},
        "min": "f8_min({a}, {b})",
        "/": "f8_div({a}, {b})",
        "fma": "f8_fma({a}, {b}, {c})",
        **{
            cmp: f"f8_{name}({{lhs}}, {{rhs}}, {{then}}, {{otherwise}})"
            for cmp, name in {">": "gt", ">=": "ge"}.items()
        },
        **{
            cmp: f"f8_{name}({{lhs}}, {{rhs}}, {{then}}, {{otherwise}})"
            for cmp, name in {"<": "lt", "<=": "le"}.items()
        },
        "math": "f8_{fn}",
    },
    helpers={"/": ("#define f8_div(a, b) f8_mul(a, f8_recip(b))",)},
)


class Fake8(SimdPrinter):
    """What a new ISA's file holds: its target and its table, nothing else."""

    target = Target("fake8", vector_widths=(8,), registers=32, fma=True)
    widths = {8: FAKE8}
    includes = ("<math.h>", '"fake8.h"')


# The fake ISA's intrinsics, in GCC's vector extension, so the printed file builds and runs.
FAKE8_H = r"""#include <string.h>
typedef float f32x8 __attribute__((vector_size(32)));
#define LANES(expr) f32x8 r; int i; for (i = 0; i < 8; ++i) r[i] = (expr); return r
#define SELECT(name, cmp) \
    static inline f32x8 name(f32x8 l, f32x8 g, f32x8 t, f32x8 o) { LANES(l[i] cmp g[i] ? t[i] : o[i]); }
static inline f32x8 f8_load(const float *p) { f32x8 v; memcpy(&v, p, sizeof v); return v; }
static inline void f8_store(float *p, f32x8 v) { memcpy(p, &v, sizeof v); }
static inline f32x8 f8_dup(float x) { LANES(x); }
static inline f32x8 f8_add(f32x8 a, f32x8 b) { return a + b; }
static inline f32x8 f8_sub(f32x8 a, f32x8 b) { return a - b; }
static inline f32x8 f8_mul(f32x8 a, f32x8 b) { return a * b; }
static inline f32x8 f8_recip(f32x8 b) { LANES(1.0f / b[i]); }
static inline f32x8 f8_max(f32x8 a, f32x8 b) { LANES(a[i] > b[i] ? a[i] : b[i]); }
static inline f32x8 f8_min(f32x8 a, f32x8 b) { LANES(a[i] < b[i] ? a[i] : b[i]); }
static inline f32x8 f8_fma(f32x8 a, f32x8 b, f32x8 c) { LANES(fmaf(a[i], b[i], c[i])); }
SELECT(f8_gt, >) SELECT(f8_ge, >=) SELECT(f8_lt, <) SELECT(f8_le, <=)
"""

SCALES = Const(tuple(float(v) for v in range(1, 9)))


def fake8_program() -> Program:
    """y = exp(x) * <1..8> + 0.5 and z = x > 0 ? x / <1..8> : 0, eight lanes at a time."""
    x = Load("x", A("c") * 8, 8)
    y = Binary("+", Binary("*", Call("exp", x), SCALES), Const.splat(0.5, 8))
    z = Select(">", x, Const.splat(0.0, 8), Binary("/", x, SCALES), Const.splat(0.0, 8))
    body = (Loop("c", 2, (Store("y", A("c") * 8, y), Store("z", A("c") * 8, z))),)
    buffers = tuple(Buffer(name, 16, role, (16,)) for name, role in (("x", "input"), ("y", "output"), ("z", "output")))
    return Program("p", buffers, (Kernel("k", "Test", body),), arena=ArenaPlan(0, 0, 16))


def test_a_new_isa_is_one_file_of_tables():
    source = Backend(Fake8()).source(fake8_program(), "/* fake8 */", "p.h")
    kernel = source[source.index("static NNCG_NOINLINE void p_k") : source.index("void p_run")]
    assert kernel.splitlines() == [
        "static NNCG_NOINLINE void p_k(const float *NNCG_RESTRICT x, float *NNCG_RESTRICT y, float *NNCG_RESTRICT z)",
        "{",
        "    int c;",
        "    for (c = 0; c < 2; ++c) {",
        "        f8_store(&y[8 * c], f8_fma(f8_exp(f8_load(&x[8 * c])), f8_load(f8_constants[0]), f8_dup(0.5f)));",
        "        f8_store(&z[8 * c], f8_gt(f8_load(&x[8 * c]), f8_dup(0.0f), "
        "f8_div(f8_load(&x[8 * c]), f8_load(f8_constants[0])), f8_dup(0.0f)));",
        "    }",
        "}",
        "",
    ]
    includes = source[source.index('#include "fake8.h"') : source.index("#if defined(__GNUC__)")]
    assert includes == '#include "fake8.h"\n\n'  # the ISA's helpers follow the portability macros they use
    preamble = source[source.index("#define NNCG_NOINLINE\n#endif\n") : source.index("/* k: Test */")]
    assert preamble.splitlines() == [
        "#define NNCG_NOINLINE",
        "#endif",
        "",
        "#define f8_div(a, b) f8_mul(a, f8_recip(b))",
        "",
        "/* constant vectors that are not splats, loaded with f8_load */",
        "static const float f8_constants[1][8] = {",
        "    {1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f, 8.0f},",
        "};",
        "",
        "/* exp of each lane: no vector exp in the instruction set */",
        "static f32x8 f8_exp(f32x8 x)",
        "{",
        "    float v[8];",
        "    f8_store(v, x);",
        *(f"    v[{i}] = (float)exp(v[{i}]);" for i in range(8)),
        "    return f8_load(v);",
        "}",
        "",
    ]


def test_the_new_isa_builds_and_computes(tmp_path):
    program = fake8_program()
    backend = Backend(Fake8())
    (tmp_path / "fake8.h").write_text(FAKE8_H)
    (tmp_path / "p.h").write_text(backend.header(program, "/* fake8 */"))
    (tmp_path / "p.c").write_text(backend.source(program, "/* fake8 */", "p.h"))
    (tmp_path / "main.c").write_text(
        '#include <stdio.h>\n#include "p.h"\n'
        "int main(void) {\n    float x[16], y[16], z[16]; int i;\n"
        "    for (i = 0; i < 16; ++i) x[i] = (float)(i - 6) / 4.0f;\n    p(x, y, z);\n"
        '    for (i = 0; i < 16; ++i) printf("%.9g %.9g\\n", y[i], z[i]);\n    return 0;\n}\n'
    )
    flags = ["-std=gnu99", "-Wall", "-Wextra", "-Werror", "-Wno-psabi", "-O1"]
    run_tool([find_c_compiler(), *flags, "p.c", "main.c", "-lm", "-o", "main"], "building main", cwd=tmp_path)
    out = np.loadtxt(run_tool(["./main"], "running main", cwd=tmp_path).stdout.split("\n"))
    x = (np.arange(16, dtype=np.float32) - 6) / 4
    scales = np.tile(np.arange(1, 9, dtype=np.float32), 2)
    np.testing.assert_allclose(out[:, 0], np.exp(x) * scales + 0.5, rtol=1e-6)
    np.testing.assert_allclose(out[:, 1], np.where(x > 0, x / scales, 0), rtol=1e-6)


def test_a_table_missing_an_operation_is_refused_where_it_is_declared():
    table = VectorWidth("f32x8", {op: t for op, t in FAKE8.ops.items() if op not in ("fma", "<=")})
    with pytest.raises(TypeError, match=r"Broken, 8 lanes: no template for <=; no template for fma"):
        type("Broken", (SimdPrinter,), {"target": Fake8.target, "widths": {8: table}})
    with pytest.raises(TypeError, match=r"widths \(4,\) are not the target's \(8,\)"):
        type("Broken", (SimdPrinter,), {"target": Fake8.target, "widths": {4: FAKE8}})


def test_the_registered_backends_are_the_printer_classes_of_the_package():
    assert sorted(BACKENDS) == ["ansi-c", "avx2", "avx512", "avx512vnni", "neon", "neon-dotprod", "ssse3"]
    for name, printer in BACKENDS.items():
        backend = get_backend(name)
        assert backend.target is printer.target and backend.name == name
        assert (backend.vector_widths, backend.registers) == (printer.target.vector_widths, printer.target.registers)
    assert [get_backend(n).target.fma for n in ("ansi-c", "ssse3", "avx2", "avx512", "neon")] == [0, 0, 1, 1, 1]


# ------------------------------------------------------------------------- FMA legalisation

V4 = Target("v4", vector_widths=(4,), fma=True)
a, b, c, d = (Load(name, Affine(), 4) for name in "abcd")


def one_store(value) -> Program:
    buffers = (*(Buffer(n, 4, "input") for n in "abcd"), Buffer("y", 4, "output"))
    return Program("p", buffers, (Kernel("k", "Test", (Store("y", Affine(), value),)),))


def legalised(value, target=V4):
    return fuse_multiply_add(one_store(value), target).kernels[0].body[0].value


@pytest.mark.parametrize(
    "before, expected",
    [
        (Binary("+", Binary("*", a, b), c), Fma(a, b, c)),
        (Binary("+", c, Binary("*", a, b)), Fma(a, b, c)),  # the product on the right
        (Binary("+", Binary("*", a, b), Binary("*", c, d)), Fma(a, b, Binary("*", c, d))),  # the left product
        (Binary("+", Binary("*", Binary("+", Binary("*", a, b), c), d), a), Fma(Fma(a, b, c), d, a)),  # nested
        (Binary("-", Binary("*", a, b), c), Binary("-", Binary("*", a, b), c)),  # not an add
        (Call("exp", Binary("+", Binary("*", a, b), c)), Call("exp", Fma(a, b, c))),  # under another node
    ],
)
def test_fma_legalisation(before, expected):
    assert legalised(before) == expected
    assert verify_program(fuse_multiply_add(one_store(before), V4)) == []


def test_fma_legalisation_leaves_scalars_and_targets_without_fma():
    x = Load("x", Affine())
    scalar = Binary("+", Binary("*", x, x), x)
    assert legalised(scalar) == scalar
    vector = Binary("+", Binary("*", a, b), c)
    assert legalised(vector, Target("no-fma", vector_widths=(4,), fma=False)) == vector
    assert legalised(vector, Target("other-widths", vector_widths=(8,), fma=True)) == vector


def test_fma_prints_as_multiply_and_add_where_it_is_not_fused():
    """ansi-c prints a scalar Fma as a product and a sum; ssse3, without FMA, computes a vector one in
    double (Target.fma_in_double), as QLinearAdd's scalar C does."""
    assert expr_to_text(Fma(a, b, c)) == "fma(a[0:4], b[0:4], c[0:4])"
    x = Load("x", Affine())
    assert get_backend("ansi-c").printer.expr(Fma(x, x, x)) == "((x[0] * x[0]) + x[0])"
    assert Ssse3().expr(Fma(a, b, c)) == "nncg_fma_pd(_mm_loadu_ps(&a[0]), _mm_loadu_ps(&b[0]), _mm_loadu_ps(&c[0]))"


def test_sse_vector_math_multiplies_and_adds_instead_of_the_fma_in_double():
    """ssse3's emulated Fma (~15 instructions, for the int8 kernels' exact sums) stays out of the vector
    math functions: a sigmoid with it cost 10x its convolution in efficientnet_b0 (the ULP bounds hold
    unfused, tests/test_vector_math.py)."""
    printer = Ssse3(Needs((), frozenset({(4, "sigmoid")})))
    text = "\n".join(printer.preamble())
    assert "nncg_sigmoid_ps" in text and "nncg_fma_pd" not in text and "_mm_mul_ps(" in text


@pytest.mark.parametrize("target, lanes", [("ssse3", 4), ("avx2", 8), ("avx512", 16), ("neon", 4)])
@pytest.mark.parametrize("dtype", [DType.UINT8, DType.INT8])
def test_an_unwidened_8bit_vector_copy_is_refused_not_printed_wrong(target, lanes, dtype):
    """A vector Store(Load) of bytes (a line buffer's shift) has no byte-copy template: the int32 load
    would read 4 bytes a lane and the 8-bit store pack those as int32 values, so printing refuses."""
    buffers = (Buffer("x", 32, "input", dtype=dtype), Buffer("y", 32, "output", dtype=dtype))
    body = (Store("y", Affine(), Load("x", Affine.of(16), lanes)),)
    program = Program("p", buffers, (Kernel("k", "Test", body),), arena=ArenaPlan(0, 0, 16))
    with pytest.raises(TypeError, match=f"{lanes}-lane load of {dtype} x not widened to int32"):
        get_backend(target).source(program, "", "p.h")


# ------------------------------------------------------------------------- helpers, collected before printing


def neon_program() -> Program:
    """A division, then a product-sum, then exp; two constant vectors, one used twice."""
    first, second = Const((1.0, 2.0, 3.0, 4.0)), Const((5.0, 6.0, 7.0, 8.0))
    values = (
        Binary("/", a, first),
        Fma(a, second, Broadcast(LocalRef("s"), 4)),
        Call("exp", Binary("*", a, first)),
        Call("log", a),
    )
    return Program("p", one_store(a).buffers, (Kernel("k", "Test", tuple(Store("y", Affine(), v) for v in values)),))


def test_helpers_are_collected_in_order_of_first_use():
    needs = collect_needs(neon_program(), Neon.widths)
    assert needs.definitions == ((4, "/"), (4, "fma"))
    assert needs.rows == {4: {(1.0, 2.0, 3.0, 4.0): 0, (5.0, 6.0, 7.0, 8.0): 1}}
    assert needs.math == {(4, "exp"), (4, "log")}
    assert collect_needs(neon_program(), Ssse3.widths).rows == {}  # x86 spells constants inline


def test_neon_preamble_definitions_then_table_then_math_functions():
    printer = Neon().for_program(neon_program())
    comments = [line for line in printer.preamble() if line.startswith("/*") or line.startswith("static const")]
    assert comments == [
        "/* a / b: one instruction on AArch64; ARMv7 NEON has no vector division, so each lane is divided */",
        "/* acc + a * b: fused (one rounding) where the ISA has it; ARMv7 NEON without VFPv4 has only vmlaq_f32,",
        "/* constant vectors that are not splats, loaded with vld1q_f32 */",
        "static const float nncg_vectors[2][4] = {",
        "/* exp of each lane: x = n ln2 + r, exp(r) by a degree-6 polynomial, times 2^n; max error 1.5 ULP "
        "(nncg/backends/vector_math.py) */",
        "/* log of each lane: x = m 2^e, log(m) by a degree-11 polynomial in m - 1, plus e ln2; max error 1 ULP "
        "(nncg/backends/vector_math.py) */",
    ]
    assert Neon().preamble() == []  # a printer not bound to a program prints no helper


def test_printing_does_not_change_the_printer():
    printer = Neon().for_program(neon_program())
    before = vars(printer).copy()
    lines = printer.stmts(neon_program().kernels[0].body, 1)
    assert vars(printer) == before
    assert lines[0] == "    vst1q_f32(&y[0], nncg_vdivq_f32(vld1q_f32(&a[0]), vld1q_f32(nncg_vectors[0])));"


# ------------------------------------------------------------------------- dependencies point one way


def test_backends_import_the_ir_never_the_passes():
    for path in (ROOT / "nncg" / "backends").glob("*.py"):
        imports = re.findall(r"^from \.\.(\w+)", path.read_text(), re.M)
        assert set(imports) <= {"ir", "errors", "safe_text"}, (path.name, imports)
