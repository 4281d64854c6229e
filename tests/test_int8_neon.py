"""The vectorised int8 kernels on NEON (issue 16): the integer convolutions and matrix products on
int32x4_t over output channels, one C file for ARMv7 and AArch64 (`neon`: vmlal_s16 pairs) and one for
AArch64 with the dot-product extension (`neon-dotprod`: sdot quads), bit-identical with onnxruntime
under qemu-user on aarch64 with dotprod (-cpu max) and without (-cpu cortex-a53), and on armhf (with
and without VFPv4); the requantisation helper's
rounding (vcvtnq on AArch64, the 1.5 * 2^23 addition on ARMv7) checked at its ties and clamps; the
file builds with clang's arm_neon.h too."""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cross_helpers import CLANG_NEON_FLAGS, TOOLCHAINS, clang_cross_problem, compile_with_clang, missing_tools, runner
from int8_models import (
    clip_gemm_model,
    compare,
    conv_model,
    quantized,
    random_feeds,
    repository_model,
    residual_model,
    stacked_conv_model,
)
from test_cross_targets import require, skip_unless_ci

import nncg
from nncg.backends.c_file import PORTABILITY_MACROS
from nncg.backends.neon_integer import REQUANTIZE

MODELS = {
    **{kind: lambda kind=kind: conv_model(kind) for kind in ("3x3", "stride2", "1x1")},
    **{kind: lambda kind=kind: stacked_conv_model(kind) for kind in ("depthwise", "grouped")},
    "gemm": clip_gemm_model,
    "residual": residual_model,
}
ARM = ("aarch64-neon-dotprod", "aarch64-neon", "armhf-neon", "armhf-neon-vfpv3")
MAIN = ARM[:3]  # the three code paths: sdot, vmlal_s16 on AArch64 and on ARMv7 (with VFPv4)


def check_on(toolchain: str, float_model, activations: str = "uint8", **options) -> nncg.CompiledModel:
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, target=tc.target, verify_ir=True, **options)
    run = {"cc": tc.cc, "extra_cflags": tc.flags, "runner": runner(tc)}
    result = compare(model, compiled, random_feeds(float_model, 2, 7), **run)
    assert result.max_steps == 0 and result.identical == 1.0, result
    return compiled


def vectorised(source: str) -> bool:
    """int32x4_t multiply-accumulates (vmlal_s16 pairs, sdot quads or, channel by channel, vmulq_s32)
    and vector requantisation."""
    multiply = any(f in source for f in ("nncg_vdot2q_s32(", "vdotq_s32(", "vmulq_s32("))
    return multiply and "nncg_vrequantizeq_s32(" in source


@pytest.mark.parametrize("toolchain", ARM)
@pytest.mark.parametrize("kind", sorted(MODELS))
def test_vector_kernels_match_onnxruntime_to_the_bit(kind, toolchain):
    check_on(toolchain, MODELS[kind]())


@pytest.mark.parametrize("toolchain", MAIN)
def test_int8_activations(toolchain):
    """int8 activations and zero points: the signed widening loads and narrowing stores."""
    compiled = check_on(toolchain, stacked_conv_model("depthwise"), "int8")
    assert "nncg_vstoreq_int8(" in compiled.source and "nncg_vwidenq_int8(" in compiled.source


@pytest.mark.parametrize("toolchain", MAIN)
def test_unrolled_weights_are_constant_vectors(toolchain):
    compiled = check_on(toolchain, conv_model("3x3"), unroll=2)
    assert "nncg_vsetq_s32(" in compiled.source


@pytest.mark.parametrize("toolchain", MAIN)
@pytest.mark.parametrize("name", ["dscnn", "resnet8", "mobilenet_v1_025"])
def test_repository_model(name, toolchain):
    """Whole MLPerf-Tiny-shaped networks with their final QLinearSoftmax, bit-identical; a first Conv
    reading the planar graph input stays scalar, the others are vectors."""
    assert vectorised(check_on(toolchain, repository_model(f"benchmarks/models/{name}.onnx")).source)


@pytest.mark.parametrize("target", ["neon", "neon-dotprod"])
def test_unrolled_resnet8_taps_are_dot_products(target):
    """At --unroll 2 the Convs' taps are straight-line dot products (two or four channels a call), not
    an inlined 4-byte widening load per channel and tap (7,200 of them before: gcc -O2 ran past 600 s;
    now about a minute of CPU time, measured by hand, not asserted)."""
    compiled = nncg.compile(quantized(repository_model("benchmarks/models/resnet8.onnx")), target=target, unroll=2)
    assert compiled.source.count("nncg_vwidenq_") < 100  # the first Conv's planar input
    assert compiled.source.count("vdotq_s32(" if target == "neon-dotprod" else "nncg_vdot2q_s32(") > 1000


@pytest.mark.parametrize("kind", sorted(MODELS))
def test_source_uses_integer_vectors(kind):
    """The printed C, on any host: the multiply-accumulates are on int32x4_t, and where the channels
    fill whole vectors there is no scalar accumulator (the Gemm's fifth output is a scalar tail; the
    residual model's MaxPool takes int32x4_t maxima); the integer constants are not rows of the float
    table."""
    source = nncg.compile(quantized(MODELS[kind]()), target="neon").source
    assert vectorised(source)
    assert ("nncg_int32 acc" in source) == (kind == "gemm")
    table = source[source.find("nncg_vectors[") : source.find("};", source.find("nncg_vectors["))]
    assert not re.search(r"\{-?[0-9]+\.0f, -?[0-9]+\.0f, -?[0-9]+\.0f, -?[0-9]+\.0f\}", table), table


def test_float_models_print_no_integer_helpers():
    source = nncg.compile(conv_model("3x3"), target="neon").source
    assert "int32x4_t" not in source and "nncg_int32" not in source


def test_fixed_point_form_stays_scalar():
    compiled = nncg.compile(quantized(conv_model("3x3")), target="neon", requantize="fixed")
    assert "vmulq_s32(" not in compiled.source and "nncg_requantize_fixed(" in compiled.source


# x and the expected result for zero point 3, clamped to [0, 255] (low/high - zero point: -3, 252):
# ties round to even on both sides of zero, the clamps hold at and beyond both ends, NaN gives low.
TIES = [0.5, 1.5, 2.5, -0.5, -1.5, -2.5, 0.49999997, 0.50000006, 251.5, 250.5, -2.5000002, 1e-40, -0.0]
CLAMPS = [252.0, 252.4, 252.5, 1e9, math.inf, -3.0, -3.5, -1e9, -math.inf, math.nan]


def expected(x: float, zero_point: int = 3, low: int = 0, high: int = 255) -> int:
    x = np.float32(x)
    if not x >= low - zero_point:
        x = np.float32(low - zero_point)
    return int(np.rint(min(x, np.float32(high - zero_point)))) + zero_point


def requantize_program(values: list[float]) -> str:
    rows = ", ".join(
        f"{v!r}f" if math.isfinite(v) else ("NAN" if math.isnan(v) else f"{'-' * (v < 0)}INFINITY") for v in values
    )
    return "\n".join(
        [
            "#include <math.h>",
            "#include <stdio.h>",
            "#include <arm_neon.h>",
            *PORTABILITY_MACROS,
            *REQUANTIZE,
            f"static const float xs[{len(values)}] = {{{rows}}};",
            "int main(void)",
            "{",
            "    int i, j;",
            "    int32_t out[4];",
            f"    for (i = 0; i < {len(values)}; i += 4) {{",
            "        float in[4] = {0, 0, 0, 0};",
            f"        for (j = 0; j < 4 && i + j < {len(values)}; ++j) in[j] = xs[i + j];",
            "        vst1q_s32(out, nncg_vrequantizeq_s32(vld1q_f32(in), -3.0f, 252.0f, 3));",
            f'        for (j = 0; j < 4 && i + j < {len(values)}; ++j) printf("%d\\n", (int)out[j]);',
            "    }",
            "    return 0;",
            "}",
            "",
        ]
    )


@pytest.mark.parametrize("toolchain", ARM)
def test_requantisation_rounds_half_to_even_and_clamps(toolchain, tmp_path: Path):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    values = TIES + CLAMPS
    (tmp_path / "r.c").write_text(requantize_program(values))
    build = [tc.cc, "-O2", "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", *tc.flags, "r.c", "-o", "r"]
    subprocess.run(build, cwd=tmp_path, check=True, capture_output=True, timeout=300)
    out = subprocess.run([*runner(tc), "./r"], cwd=tmp_path, check=True, capture_output=True, text=True, timeout=300)
    assert [int(line) for line in out.stdout.split()] == [expected(v) for v in values]


@pytest.mark.parametrize("target", CLANG_NEON_FLAGS)
def test_int8_source_compiles_with_clang(target, tmp_path):
    flags = CLANG_NEON_FLAGS[target]
    problem = clang_cross_problem(flags)
    if problem:
        skip_unless_ci(problem)
    for name, activations in (("depthwise", "int8"), ("3x3", "uint8")):
        compiled = nncg.compile(quantized(MODELS[name](), activations), target="neon", unroll=2)
        compile_with_clang(flags, compiled, tmp_path / name)
