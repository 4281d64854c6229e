"""The vector math functions (nncg/backends/vector_math.py) on every vector target and width: each is
evaluated over every 4096th float32 bit pattern (all signs, denormals, NaNs, infinities) plus the
edges (overflow, underflow, branch thresholds, +-0, +-Inf), compared with float64 numpy/scipy, and
must stay within the stated ULP bound and get the specials exactly right. x86 widths run on the host
when its CPU has the instruction set; NEON runs under qemu-user (AArch64, and ARMv7, whose NEON unit
flushes denormals to zero)."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from helpers import HOST
from scipy import special

from nncg.backends import BACKENDS
from nncg.backends.c_file import PORTABILITY_MACROS
from nncg.backends.simd_needs import Needs
from nncg.backends.vector_math import ULP_BOUNDS, interleaved_name, operations_used, with_callees

FUNCTIONS = ("exp", "log", "tanh", "sigmoid", "erf", "softplus", "abs", "sqrt")
FLT_MIN = float(np.finfo(np.float32).tiny)
OPT = "-O2"


@dataclass(frozen=True)
class Build:
    """One vector width of one target: how to compile the test program and run it."""

    target: str
    lanes: int
    cc: str = "gcc"
    flags: tuple[str, ...] = ()
    emulator: tuple[str, ...] = ()
    cpu: frozenset[str] = frozenset()  # host CPU flags an x86 build needs
    flushes_denormals: bool = False

    @property
    def id(self) -> str:
        return f"{self.target}-{self.lanes}" + ("-armv7" if "qemu-arm" in self.emulator else "")


BUILDS = [
    Build("ssse3", 4, cpu=frozenset({"ssse3"})),
    Build("avx2", 8, cpu=frozenset({"avx2", "fma"})),
    Build("avx2", 4, cpu=frozenset({"avx2", "fma"})),  # the 128-bit block with FMA and blendv
    Build("avx512", 16, cpu=frozenset({"avx512f"})),
    Build("neon", 4, "aarch64-linux-gnu-gcc", ("-static",), ("qemu-aarch64",)),
    Build(
        "neon",
        4,
        "arm-linux-gnueabihf-gcc",
        ("-static", "-mfpu=neon-vfpv4", "-mfloat-abi=hard"),
        ("qemu-arm",),
        flushes_denormals=True,
    ),
    Build(
        "neon",
        4,
        "arm-linux-gnueabihf-gcc",
        ("-static", "-mfpu=neon", "-mfloat-abi=hard"),  # no VFPv4: no fused multiply-add
        ("qemu-arm",),
        flushes_denormals=True,
    ),
]


def sweep() -> np.ndarray:
    """Every 4096th bit pattern, then the edges: each threshold of the algorithms and a few ULPs
    around it, the ends of the float range, +-0, +-Inf and NaN."""
    patterns = (np.arange(1 << 20, dtype=np.uint64) * 4096 + 1234).astype(np.uint32).view(np.float32)
    edges = [
        88.72283, 88.7228394, 88.72284, 89.0, 100.0, -87.33654, -87.3366, -103.27893, -103.97208, -103.9721, -104.0,
        -150.0, 0.625, 1.0, 4.0, 3.9, 3.83, 9.0, 0.5, 2.0, 0.70710677, 1.4142135, 1e-3, 1e-8, 1e-30, FLT_MIN,
        1e-40, 1e-45, 3.4028235e38, 3.4e38, 0.34657359, 44.36, 8.66, 17.33, 32.0,
    ]  # fmt: skip
    with np.errstate(over="ignore"):  # the next float after FLT_MAX is +Inf, as meant
        near = [np.nextafter(np.float32(e), np.float32(np.inf * d)) for e in edges for d in (1, -1)]
    specials = [0.0, np.inf, np.nan, 1.0, 2.0**-149]
    around_one = np.linspace(0.99, 1.01, 20001, dtype=np.float32)  # log's cancellation
    values = np.concatenate([np.float32(edges), np.float32(near), np.float32(specials), around_one])
    return np.concatenate([patterns, values, -values]).astype(np.float32)


def reference(fn: str, x: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        x64 = x.astype(np.float64)
        return {
            "exp": np.exp,
            "log": np.log,
            "tanh": np.tanh,
            "sigmoid": special.expit,
            "erf": special.erf,
            "softplus": lambda v: np.logaddexp(0.0, v),
            "abs": np.abs,
            "sqrt": np.sqrt,
        }[fn](x64)


def ulp_errors(y: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|y - ref| in float32 ULPs at ref (2^-149 for denormals); 0 where both are the same NaN or
    infinity or where ref rounds to an infinity y is; inf where y misses a NaN or infinity."""
    with np.errstate(all="ignore"):  # NaNs cast, and overflow to infinity is what the rounding means
        y64 = y.astype(np.float64)
        expected = ref.astype(np.float32)  # the correctly rounded result
        exponent = np.maximum(np.floor(np.log2(np.abs(ref))), -126.0)
        err = np.abs(y64 - ref) / np.exp2(exponent - 23)
    special_value = np.isnan(ref) | np.isinf(expected)
    same = (np.isnan(ref) & np.isnan(y)) | (np.isinf(expected) & (y == expected))
    err = np.where(special_value, np.where(same, 0.0, np.inf), err)
    return np.where(np.isnan(err) | (np.isinf(y) & ~special_value), np.inf, err)


def program(build: Build, interleave: int = 1) -> str:
    """C: reads n floats from argv[1], writes each function of them (in FUNCTIONS order) to argv[2];
    with interleave > 1 through the helpers over that many vectors (n a multiple of them)."""
    printer_class = BACKENDS[build.target]
    width = printer_class.widths[build.lanes]
    used = [op for fn in with_callees(set(FUNCTIONS)) for op in operations_used(fn, width)]
    definitions = tuple(dict.fromkeys((build.lanes, op) for op in used if op in width.helpers))
    math = frozenset((build.lanes, fn) for fn in FUNCTIONS)
    interleaved = frozenset((build.lanes, fn, interleave) for fn in FUNCTIONS if interleave > 1)
    printer = printer_class(Needs(definitions, math, interleaved))
    loops = [
        f"    {_each_block(width, fn, build.lanes, interleave)}\n    fwrite(y, sizeof(float), (size_t)n, out);"
        for fn in FUNCTIONS
    ]
    return "\n".join(
        [
            "#include <stdio.h>",
            "#include <stdlib.h>",
            *(f"#include {h}" for h in printer_class.includes),
            *PORTABILITY_MACROS,
            *printer.preamble(),
            "",
            "int main(int argc, char **argv)",
            "{",
            "    FILE *in, *out;",
            "    long n, i;",
            "    float *x, *y;",
            '    if (argc != 3 || !(in = fopen(argv[1], "rb")) || !(out = fopen(argv[2], "wb"))) return 2;',
            "    fseek(in, 0, SEEK_END);",
            "    n = ftell(in) / (long)sizeof(float);",
            "    fseek(in, 0, SEEK_SET);",
            "    x = malloc((size_t)n * sizeof(float));",
            "    y = malloc((size_t)n * sizeof(float));",
            "    if (!x || !y || fread(x, sizeof(float), (size_t)n, in) != (size_t)n) return 3;",
            *loops,
            "    fclose(out);",
            "    return 0;",
            "}",
            "",
        ]
    )


def _each_block(width, fn: str, lanes: int, interleave: int) -> str:
    """The loop computing y = fn(x), one vector at a time or `interleave` vectors per helper call."""
    if interleave == 1:
        call = f"{width.spell('math', fn=fn)}({width.spell('load', address='&x[i]')})"
        return f"for (i = 0; i < n; i += {lanes}) {width.spell('store', address='&y[i]', value=call)};"
    loads = " ".join(f"v[{k}] = {width.spell('load', address=f'&x[i + {k * lanes}]')};" for k in range(interleave))
    stores = " ".join(
        f"{width.spell('store', address=f'&y[i + {k * lanes}]', value=f'v[{k}]')};" for k in range(interleave)
    )
    call = f"{interleaved_name(fn, width, interleave)}(v);"
    return f"for (i = 0; i < n; i += {lanes * interleave}) {{ {width.type} v[{interleave}]; {loads} {call} {stores} }}"


def run(build: Build, x: np.ndarray, workdir: Path, interleave: int = 1) -> dict[str, np.ndarray]:
    """Each function of x (a multiple of the width long, times `interleave`), computed by the target's
    helpers."""
    source, exe = workdir / "vmath.c", workdir / "vmath"
    source.write_text(program(build, interleave))
    printer_class = BACKENDS[build.target]
    flags = [*build.flags, *printer_class.cflags, *printer_class.strict_cflags]
    subprocess.run([build.cc, OPT, *flags, str(source), "-o", str(exe), "-lm"], check=True, capture_output=True)
    x.tofile(workdir / "x.bin")
    subprocess.run([*build.emulator, str(exe), str(workdir / "x.bin"), str(workdir / "y.bin")], check=True)
    y = np.fromfile(workdir / "y.bin", dtype=np.float32).reshape(len(FUNCTIONS), -1)
    return dict(zip(FUNCTIONS, y))


def measure(build: Build, workdir: Path) -> dict[str, tuple[float, np.ndarray, np.ndarray]]:
    """fn -> (max ULP error, the inputs, the ULP errors) over the sweep."""
    x = sweep()
    x = np.concatenate([x, np.zeros(-len(x) % 16, np.float32)])
    results = run(build, x, workdir)
    out = {}
    for fn, y in results.items():
        ref = reference(fn, x)
        err = target_errors(build, fn, x, y, ref)
        out[fn] = (float(np.max(err)), x, err)
    return out


def target_errors(build: Build, fn: str, x: np.ndarray, y: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """ULP errors of y = fn(x) against ref, as the build's FPU may compute them (also used by
    scripts/sigmoid_sweep.py)."""
    err = ulp_errors(y, ref)
    if build.flushes_denormals:
        # The NEON unit reads a denormal as a zero of its sign (its comparisons may run in VFP,
        # which does not: either reading is right), flushes a denormal result to zero, and the
        # log of a denormal it flushed in part is at most log(FLT_MIN).
        flushed = np.where(np.abs(x) < FLT_MIN, np.copysign(np.float32(0.0), x), x).astype(np.float32)
        err = np.minimum(err, ulp_errors(y, reference(fn, flushed)))
        err = np.where((np.abs(ref) < FLT_MIN) & (y == 0), 0.0, err)
        if fn == "log":
            err = np.where((0 < x) & (x < FLT_MIN) & (y <= np.log(FLT_MIN)), 0.0, err)
    return err


def missing(build: Build) -> str | None:
    if build.cpu and not build.cpu <= HOST:
        return f"the host CPU lacks {', '.join(sorted(build.cpu - HOST))}"
    tools = [build.cc, *build.emulator[:1]]
    absent = [tool for tool in tools if shutil.which(tool) is None]
    return f"{', '.join(absent)} not installed (scripts/install-test-deps.sh installs it)" if absent else None


@pytest.mark.parametrize("build", BUILDS, ids=lambda b: b.id)
def test_vector_math_is_within_its_ulp_bound_over_the_float_range(build, tmp_path):
    reason = missing(build)
    if reason:
        if os.environ.get("CI") and not build.cpu:
            pytest.fail(f"{reason}: CI must run every target", pytrace=False)
        pytest.skip(reason)
    measured = measure(build, tmp_path)
    problems = []
    for fn, (worst, x, err) in measured.items():
        if worst > ULP_BOUNDS[fn]:
            bad = np.argsort(err)[-3:]
            problems.append(f"{fn}: {worst:.3g} ULP > {ULP_BOUNDS[fn]}, at x = {x[bad].tolist()}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("build", [b for b in BUILDS if BACKENDS[b.target].math_interleave > 1], ids=lambda b: b.id)
def test_interleaved_helpers_give_the_single_helpers_bits(build, tmp_path):
    """The helpers a register block's epilogue calls over several vectors at once (backends/simd.py)
    are the same operations in another order: bit for bit the results held to the bounds above."""
    reason = missing(build)
    if reason:
        pytest.skip(reason)
    count = BACKENDS[build.target].math_interleave
    x = sweep()
    x = np.concatenate([x, np.zeros(-len(x) % (build.lanes * count), np.float32)])
    single, interleaved = run(build, x, tmp_path), run(build, x, tmp_path, count)
    for fn in FUNCTIONS:
        assert np.array_equal(single[fn].view(np.uint32), interleaved[fn].view(np.uint32)), fn


SPECIALS = [  # a list: 0.0 and -0.0 are one key of a dict
    # x, (exp, log, tanh, sigmoid, erf, softplus, abs, sqrt); None: not a special value of that function
    (0.0, (1.0, -np.inf, 0.0, 0.5, 0.0, None, 0.0, 0.0)),
    (-0.0, (1.0, -np.inf, -0.0, 0.5, -0.0, None, 0.0, -0.0)),
    (np.inf, (np.inf, np.inf, 1.0, 1.0, 1.0, np.inf, np.inf, np.inf)),
    (-np.inf, (0.0, np.nan, -1.0, 0.0, -1.0, 0.0, np.inf, np.nan)),
    (np.nan, (np.nan,) * 8),
    (-1.0, (None, np.nan, None, None, None, None, 1.0, np.nan)),
    (88.72284, (np.inf, None, 1.0, 1.0, 1.0, 88.72284, None, None)),  # the first float whose exp overflows
    (1000.0, (np.inf, None, 1.0, 1.0, 1.0, 1000.0, 1000.0, None)),
    (-1000.0, (0.0, np.nan, -1.0, 0.0, -1.0, 0.0, 1000.0, np.nan)),
    (-104.0, (0.0, np.nan, -1.0, 0.0, -1.0, 0.0, None, np.nan)),
    (20.0, (None, None, 1.0, 1.0, 1.0, None, None, None)),
    (-20.0, (None, np.nan, -1.0, None, -1.0, None, 20.0, np.nan)),
    (1.0, (None, 0.0, None, None, None, None, 1.0, 1.0)),
    (4.0, (None, None, None, None, None, None, None, 2.0)),
]


@pytest.mark.parametrize("build", BUILDS[:2] + BUILDS[3:5], ids=lambda b: b.id)
def test_special_values_are_exact(build, tmp_path):
    reason = missing(build)
    if reason:
        pytest.skip(reason)
    x = np.float32([value for value, _ in SPECIALS] + [0.0] * (-len(SPECIALS) % 16))
    results = run(build, x, tmp_path)
    for i, (value, expected) in enumerate(SPECIALS):
        for fn, want in zip(FUNCTIONS, expected):
            got = results[fn][i]
            if want is None:
                continue
            if np.isnan(want):
                assert np.isnan(got), (fn, value, got)
            else:
                assert got == want and np.signbit(got) == np.signbit(want), (fn, value, got, want)
