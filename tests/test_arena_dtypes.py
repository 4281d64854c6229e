"""int16 and int32 buffers in the arena: float32, int16 and int32 buffers never share memory (C's
aliasing rule), int8 ones share any; the static arena is a struct of typed regions, the caller's
arena is addressed in bytes; both are clean under C89 -pedantic, ASan and UBSan."""

from pathlib import Path

import numpy as np
import pytest
from helpers import skip_unless_host_runs

from nncg.compiler import emit
from nncg.ir.arena import arena_regions, sharing_problems, typed_arena
from nncg.ir.kinds import DType
from nncg.ir.loops import Affine, Binary, Buffer, Cast, Const, Kernel, Load, Loop, Program, Requantize, Store
from nncg.ir.verify import verify_ir
from nncg.passes.plan_memory import plan_memory
from nncg.tools import run_tool
from nncg.verify import find_c_compiler, run_compiled

N = 64
SANITIZERS = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all")


def reversed_kernel(name, dst, value_of_load, src):
    """dst[i] = value(src[N-1-i]): not elementwise, so plan-memory never runs it in place."""
    load = Load(src, Affine.of("i") * -1 + (N - 1))
    return Kernel(name, "Test", (Loop("i", N, (Store(dst, Affine.of("i"), value_of_load(load)),)),))


def typed_chain() -> Program:
    """x int8 -> a int32 -> b int16 -> f float -> c int8 -> y int32, each step reversing the order.
    Lifetimes a, b, f, c follow one another, so without the aliasing rule a, f and c would share."""
    int32 = lambda v: Cast(DType.INT32, v)  # noqa: E731
    kernels = (
        reversed_kernel("k0", "a", lambda v: Binary("*", int32(v), Const.integer(200)), "x"),
        reversed_kernel("k1", "b", lambda v: Cast(DType.INT16, v), "a"),
        reversed_kernel("k2", "f", lambda v: Binary("*", Cast(DType.FLOAT32, v), Const.splat(0.5)), "b"),
        reversed_kernel(
            "k3", "c", lambda v: Requantize(Binary("*", v, Const.splat(0.01)), 1, -128, 127, DType.INT8), "f"
        ),
        reversed_kernel("k4", "y", int32, "c"),
    )
    buffers = [Buffer("x", N, "input", (N,), dtype=DType.INT8), Buffer("y", N, "output", (N,), dtype=DType.INT32)]
    buffers += [Buffer(n, N, "internal", (N,), dtype=d) for n, d in zip("abfc", ("int32", "int16", "float32", "int8"))]
    return Program("typed", tuple(buffers), kernels)


def expected(x: np.ndarray) -> np.ndarray:
    """y[i] = c[N-1-i] = x[N-1-i] + 1 saturated (f = 100 x, in reverse, times 0.01 plus zero point 1)."""
    return np.minimum(x[::-1].astype(np.int32) + 1, 127)


def test_float_int16_and_int32_buffers_never_share_but_int8_shares_any():
    planned = plan_memory(typed_chain())
    assert verify_ir(planned) == []
    place = {b.name: (b.offset, b.offset + b.floats) for b in planned.role("internal")}

    def overlap(p, q):
        return place[p][0] < place[q][1] and place[q][0] < place[p][1]

    assert not overlap("a", "b") and not overlap("b", "f") and not overlap("a", "f")
    assert any(overlap("c", typed) for typed in "abf")  # c lives after a and b: it takes their memory
    assert planned.arena.floats == 64 + 32 + 64  # a, b, f side by side; c inside them
    regions = arena_regions(planned)
    assert sorted(r.dtype for r in regions) == ["float32", "int16", "int32"]
    assert [r.start for r in regions] == sorted(r.start for r in regions)
    assert sum(r.floats for r in regions) == planned.arena.floats


def test_verify_finds_typed_buffers_sharing_memory():
    planned = plan_memory(typed_chain())
    a = next(b for b in planned.buffers if b.name == "a")
    moved = tuple(b.__class__(**{**b.__dict__, "offset": a.offset}) if b.name == "f" else b for b in planned.buffers)
    broken = planned.__class__(**{**planned.__dict__, "buffers": moved})
    assert sharing_problems(broken) == ["int32 buffer a and float32 buffer f share arena memory"]


def test_a_float_and_int8_arena_stays_a_float_array():
    """Without int16 or int32 buffers the arena is printed as before: one float array."""
    program = typed_chain()
    kernels = program.kernels[2:]  # f, c, y from an int8 input through float: no int16 or int32 buffer
    buffers = [b for b in program.buffers if b.name not in "ab"] + [Buffer("b", N, "input", (N,), dtype=DType.INT16)]
    planned = plan_memory(Program("plain", tuple(b for b in buffers if b.name != "x"), kernels))
    assert not typed_arena(planned)
    source = emit(planned, "ansi-c").source
    assert "static NNCG_ALIGNED float plain_arena[" in source and "struct" not in source


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2"])
def test_typed_arena_runs_clean_under_sanitizers(target):
    """NAME (the static struct arena) under ASan and UBSan with the target's strict flags (ansi-c: C89
    -pedantic -Werror), at -O2 with strict aliasing too."""
    skip_unless_host_runs(target)
    compiled = emit(plan_memory(typed_chain()), target)
    assert "struct typed_arena_regions {" in compiled.source
    assert "typed_run(x, y, &typed_arena);" in compiled.source
    assert "allocated memory (malloc)" in compiled.header
    x = np.arange(-128, 128, 4, dtype=np.int8)
    x[-1] = 127
    for opt in ("-O1", "-O2"):
        (y,) = run_compiled(compiled, [x], opt=opt, sanitize=True, extra_cflags=["-fstrict-aliasing"])
        np.testing.assert_array_equal(y, expected(x))


REENTRANT_MAIN = """#include <stdio.h>
#include <stdlib.h>
#include "typed.h"

int main(void)
{
    nncg_int8 x[TYPED_X_SIZE];
    nncg_int32 y[TYPED_Y_SIZE];
    void *arena = malloc(TYPED_ARENA_BYTES);
    int i;
    for (i = 0; i < TYPED_X_SIZE; ++i)
        x[i] = (nncg_int8)(i * 4 - 128);
    typed_run(x, y, arena);
    typed_run(x, y, arena);  /* again: memory left from the first run holds every type */
    for (i = 0; i < TYPED_Y_SIZE; ++i)
        printf("%d\\n", (int)y[i]);
    free(arena);
    return 0;
}
"""


def test_callers_malloc_arena_runs_clean_under_sanitizers(tmp_path: Path):
    compiled = emit(plan_memory(typed_chain()), "ansi-c")
    compiled.write(tmp_path)
    (tmp_path / "main.c").write_text(REENTRANT_MAIN)
    flags = ["-O2", "-fstrict-aliasing", "-g", *SANITIZERS, *compiled.cflags, *compiled.strict_cflags]
    run_tool([find_c_compiler(), *flags, "main.c", "typed.c", "-o", "main", "-lm"], "building main", cwd=tmp_path)
    run = run_tool([tmp_path / "main"], "running main")
    x = (np.arange(N) * 4 - 128).astype(np.int8)
    np.testing.assert_array_equal(np.array(run.stdout.split(), dtype=np.int32), expected(x))
