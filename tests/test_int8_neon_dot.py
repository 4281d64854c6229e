"""The int8 reduction over input channels on NEON as loops.Dot (issue 16): `neon` takes two channels
per step (vmlal_s16 on int16 pairs, ARMv7 and AArch64), `neon-dotprod` four (sdot, AArch64 with the
dot-product extension), uint8 activations offset into int8 for sdot and the offset added back per
output channel. Under qemu-user, bit-identical with onnxruntime for input-channel counts that are not
multiples of 2 or 4, padded borders, uint8 and int8 activations with zero points, inputs and outputs
saturated at both ends; the neon-dotprod file refuses to build without the extension, and a program
built with it stops (SIGILL) on a CPU without it."""

from __future__ import annotations

import signal
import subprocess

import numpy as np
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from int8_models import compare, quantized, random_feeds
from test_cross_targets import require
from test_int8_dot import padded_conv_model

import nncg
from nncg.backends import get_backend
from nncg.frontend import import_onnx
from nncg.ir.loops import Assign, Dot, Load, stmt_exprs, walk_exprs, walk_stmts
from nncg.passes import PassManager, default_pipeline
from nncg.passes.dot_product import dot_products

TOOLCHAINS_BY_PATH = ("aarch64-neon-dotprod", "aarch64-neon", "armhf-neon")
DOT = {"neon-dotprod": "vdotq_s32(", "neon": "nncg_vdot2q_s32("}


def check(toolchain: str, float_model, activations: str = "uint8", scale: float = 1.0) -> nncg.CompiledModel:
    """Compiled for the toolchain's target, identical to onnxruntime under qemu on inputs `scale` times
    the calibration's spread."""
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, target=tc.target, verify_ir=True)
    feeds = [{n: v * np.float32(scale) for n, v in f.items()} for f in random_feeds(float_model, 2, 11)]
    result = compare(model, compiled, feeds, cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))
    assert result.max_steps == 0 and result.identical == 1.0, result
    return compiled


def conv_source(compiled: nncg.CompiledModel) -> str:
    return compiled.source.split("QLinearConv */")[1].split("/* ")[0]


@pytest.mark.parametrize("toolchain", TOOLCHAINS_BY_PATH)
@pytest.mark.parametrize("c_in", [2, 3, 4, 5, 8, 11])
def test_channel_tails_and_borders(c_in, toolchain):
    """The input zero point folded for every channel count (a dense Conv): uint8 x in the pairs, and
    for sdot x read as int8 and the offset added back with the offset correction."""
    target = TOOLCHAINS[toolchain].target
    conv = conv_source(check(toolchain, padded_conv_model(c_in)))
    assert DOT[target] in conv
    assert ("vdotq_s32(" in conv) == (target == "neon-dotprod")


@pytest.mark.parametrize("toolchain", TOOLCHAINS_BY_PATH)
@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_saturation_at_both_ends(activations, toolchain):
    """Inputs 4 times beyond the calibrated range: input and output values at both ends of their type."""
    compiled = check(toolchain, padded_conv_model(6), activations, scale=4.0)
    assert DOT[TOOLCHAINS[toolchain].target] in compiled.source


def _dot_program(activations: str, c_in: int):
    target = get_backend("neon-dotprod").target
    model = quantized(padded_conv_model(c_in), activations)
    pipeline = default_pipeline(target).split(",vectorize,")[0]
    program = PassManager(pipeline, target, finish=False).run(import_onnx(model))
    conv = next(k for k in program.kernels if k.op == "QLinearConv")
    return program, dot_products(program, {conv.name}, target)


def _exprs(program):
    return [e for k in program.kernels for s in walk_stmts(k.body) for t in stmt_exprs(s) for e in walk_exprs(t)]


def test_uint8_activations_are_offset_and_corrected_per_output_channel():
    """sdot reads uint8 x as x - 128; 128 * sum_ci w[kh, kw, ci, co] is added back once per tap."""
    program, packed = _dot_program("uint8", 5)
    name = next(b.name for b in packed.buffers if b.name.endswith("_offset"))
    w = program.constants[name.removesuffix("_offset")]  # [kh, kw, c_in, c_out]
    assert np.array_equal(packed.constants[name], 128 * w.astype(np.int32).sum(axis=-2))
    dots = [e for e in _exprs(packed) if isinstance(e, Dot)]
    assert dots and all(len(d.x) == 4 for d in dots)
    corrections = [
        s
        for k in packed.kernels
        for s in walk_stmts(k.body)
        if isinstance(s, Assign) and any(isinstance(e, Load) and e.buffer == name for e in walk_exprs(s.value))
    ]
    assert len(corrections) == 1  # inside the tap loops and border checks, after the dots


def test_int8_activations_with_a_folded_zero_point_need_no_correction():
    _, packed = _dot_program("int8", 5)
    assert not any(b.name.endswith("_offset") for b in packed.buffers)
    assert any(isinstance(e, Dot) and len(e.x) == 4 for e in _exprs(packed))


def test_dotprod_file_needs_the_extension(tmp_path):
    """Built without -march=...+dotprod the file stops at an #error naming the target; built with
    it, the program dies with SIGILL on a CPU without the extension (qemu's cortex-a53) instead of
    computing anything."""
    tc = TOOLCHAINS["aarch64-neon-dotprod"]
    require(missing_tools(tc))
    compiled = nncg.compile(quantized(padded_conv_model(8)), target="neon-dotprod", name="m")
    compiled.write(tmp_path)
    build = [tc.cc, "-O2", "-std=c99", "-c", "m.c", "-o", "m.o"]
    refused = subprocess.run(build, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert refused.returncode != 0 and "neon-dotprod" in refused.stderr and "#error" in refused.stderr
    main = '#include "m.h"\nstatic float x[8 * 7 * 7], y[7];\nint main(void) { m(x, y); return 0; }\n'
    (tmp_path / "main.c").write_text(main)
    program = [tc.cc, "-O2", *compiled.cflags, *tc.flags, "main.c", "m.c", "-o", "m", "-lm"]
    subprocess.run(program, cwd=tmp_path, check=True, capture_output=True, timeout=300)
    run = subprocess.run(["qemu-aarch64", "-cpu", "cortex-a53", "./m"], cwd=tmp_path, capture_output=True, timeout=300)
    assert run.returncode == -signal.SIGILL, run
    run = subprocess.run([*runner(tc), "./m"], cwd=tmp_path, capture_output=True, timeout=300)
    assert run.returncode == 0, run


def test_plain_neon_prints_no_sdot():
    """One file for ARMv7 and AArch64: the pairs' vmlal_s16, never sdot or its #error."""
    source = nncg.compile(quantized(padded_conv_model(8)), target="neon").source
    assert "vmlal_lane_s16(" in source and "vdotq_s32" not in source and '#error "this file' not in source
