"""Dot products of input channels in the int8 kernels (issue 16): the input zero point folded into the
bias, the reduction over input channels as loops.Dot with weights packed per lane, printed as pmaddwd
(ssse3, avx2, avx512) or vpdpbusd (avx512vnni), and every result still identical to onnxruntime's:
input-channel counts that are not multiples of 2 or 4, padded borders (where the folded zero point is
added back), uint8 and int8 activations with zero points != 0, inputs and outputs saturated at both ends;
and the vectorised QuantizeLinear and QLinearAdd."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import skip_unless_host_runs
from int8_models import _model, _weights, compare, quantized, random_feeds, residual_model
from onnx import helper

import nncg
from nncg.backends import get_backend
from nncg.frontend import import_onnx
from nncg.ir.kinds import DType
from nncg.ir.loops import Affine, Cast, Const, Dot, Load, stmt_exprs, walk_exprs, walk_stmts
from nncg.passes import PassManager, default_pipeline
from nncg.passes.dot_product import dot_products
from nncg.passes.register_block import FLIPPED_REGISTERS, chosen_blocks, flipped_activations

TARGETS = ("ssse3", "avx2", "avx512", "avx512vnni")
DOT = {"ssse3": "_mm_madd_epi16(", "avx2": "_madd_epi16(", "avx512": "_madd_epi16(", "avx512vnni": "_dpbusd_epi32("}


def padded_conv_model(c_in: int, c_out: int = 20, seed: int = 5):
    """A 3x3 Conv with padding (every border case) of c_in channels, then a Gemm of c_out * 4 * 4 inputs."""
    rng = np.random.default_rng(seed)
    init = {
        "w": _weights(rng, c_out, c_in, 3, 3),
        "b": rng.standard_normal(c_out) * 0.3,
        "wg": _weights(rng, 7, c_out * 16),
        "bg": rng.standard_normal(7) * 0.3,
    }
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1], strides=[2, 2]),
        helper.make_node("Flatten", ["c"], ["f"]),
        helper.make_node("Gemm", ["f", "wg", "bg"], ["y"], transB=1),
    ]
    return _model(nodes, [1, c_in, 7, 7], init)


def check(float_model, target: str, activations: str = "uint8", scale: float = 1.0) -> nncg.CompiledModel:
    """Compiled for `target`, identical to onnxruntime on inputs `scale` times the calibration's spread."""
    skip_unless_host_runs(target)
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    feeds = [{n: v * np.float32(scale) for n, v in f.items()} for f in random_feeds(float_model, 2, 11)]
    result = compare(model, compiled, feeds)
    assert result.max_steps == 0 and result.identical == 1.0, result
    return compiled


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("c_in", [2, 3, 4, 5, 8, 11])
def test_channel_tails_and_borders(c_in, target):
    compiled = check(padded_conv_model(c_in), target)
    conv = compiled.source.split("QLinearConv */")[1].split("/* ")[0]
    # the input zero point is folded for every channel count of a dense Conv: uint8 activations, vpdpbusd
    assert DOT[target] in conv


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_saturation_at_both_ends(activations, target):
    """Inputs 4 times beyond the calibrated range: input and output values at both ends of their type."""
    compiled = check(padded_conv_model(6), target, activations, scale=4.0)
    # uint8 activations take vpdpbusd's u8 quads, and int8 ones too, read as uint8 x + 128 (bytes x ^ 0x80)
    assert DOT[target] in compiled.source
    assert ("_xor_si" in compiled.source) == ((target, activations) == ("avx512vnni", "int8"))
    quantize = compiled.source.split(": QuantizeLinear */")[1].split("/* ")[0]  # the input's, on vectors
    assert "_div_ps(" in quantize and "_cvtps_epi32(" in quantize


@pytest.mark.parametrize("target", ["avx2", "avx512", "avx512vnni"])
@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_residual_add_runs_on_vectors(activations, target):
    """QLinearAdd in vector fused multiply-adds (onnxruntime's arithmetic) where the target has FMA,
    saturated at both ends by inputs 4 times beyond the calibration."""
    compiled = check(residual_model(), target, activations, scale=4.0)
    add = compiled.source.split("QLinearAdd */")[1].split("/* ")[0]
    assert "_fmadd_ps(" in add and "nncg_requantize(" not in add


def test_zero_point_is_folded_into_the_bias():
    """No per-tap subtraction of the input zero point (a dense Conv of 2 or more input channels): the
    border taps add back a constant instead."""
    for c_in in (2, 5):
        source = nncg.compile(quantized(padded_conv_model(c_in)), target="ansi-c").source
        assert "zw_" in source and ") - " not in source.split("QLinearConv */")[1].split("/* ")[0]


def test_ansi_c_is_strict_c89_and_exact():
    """ansi-c prints no dot products (the target has none) and is still identical to onnxruntime."""
    float_model = padded_conv_model(5)
    model = quantized(float_model)
    compiled = nncg.compile(model, target="ansi-c", verify_ir=True)
    result = compare(model, compiled, random_feeds(float_model, 2, 11))
    assert result.identical == 1.0, result


def _dot_program(target: str):
    model = quantized(padded_conv_model(5))
    pipeline = default_pipeline(get_backend(target).target).split(",vectorize,")[0]
    return PassManager(pipeline, get_backend(target).target, finish=False).run(import_onnx(model))


def test_weights_are_packed_in_the_order_the_kernel_reads_them():
    """K weights of one output channel side by side, output channels one after another, the missing
    channels of the tail 0; the unpacked array is dropped."""
    target = get_backend("avx512vnni").target
    program = _dot_program("avx512vnni")
    conv = next(k for k in program.kernels if k.op == "QLinearConv")
    packed = dot_products(program, {conv.name}, target)
    name = next(b.name for b in packed.buffers if b.name.endswith("_dot4"))
    original = name.removesuffix("_dot4")
    w = program.constants[original]  # [kh, kw, c_in, c_out]
    p = packed.constants[name]  # [kh, kw, c_in / 4 rounded up, c_out, 4]
    assert p.shape == (3, 3, 2, 20, 4) and original not in packed.constants
    assert np.array_equal(p[..., 0, :, :], np.moveaxis(w[..., 0:4, :], -2, -1))
    assert np.array_equal(p[..., 1, :, 0], w[..., 4, :]) and not p[..., 1, :, 1:].any()
    dots = [e for e in _exprs(packed) if isinstance(e, Dot)]
    assert dots and all(len(d.x) == 4 for d in dots)
    assert any(d.x[1:] == (Const.integer(0),) * 3 for d in dots)  # the tail channel


def test_lane_by_lane_fallback_without_a_dot_template():
    """A width without a dot template (as a target without a dot instruction) prints each lane as
    scalar products, and the scalar printer prints a dot as plain products."""
    printer = get_backend("avx2").printer
    width = printer.widths[8]
    plain = replace(width, ints={k: v for k, v in width.ints.items() if not k.startswith("dot")})
    printer.dtypes = {"x": DType.UINT8, "w": DType.INT8}
    x = tuple(Cast(DType.INT32, Load("x", Affine((), i))) for i in range(2))
    dot = Dot(x, Load("w", Affine(), 16))
    lanes = printer._dot(dot, plain)
    assert lanes.startswith("_mm256_setr_epi32(") and lanes.count("w[") == 16
    assert printer.expr(Dot(x, Load("w", Affine((), 6), 2))) == (
        "(((nncg_int32)x[0]) * ((nncg_int32)w[6]) + ((nncg_int32)x[1]) * ((nncg_int32)w[7]))"
    )


def _exprs(program):
    return [e for k in program.kernels for s in walk_stmts(k.body) for t in stmt_exprs(s) for e in walk_exprs(t)]


def test_flipped_activations_get_a_smaller_register_block():
    """int8 activations read as uint8 on avx512vnni keep each pixel's xor-ed bytes and the 0x80 mask in
    registers: their blocks are sized for FLIPPED_REGISTERS (gcc spills accumulators beyond), uint8's
    for all 32."""
    target = get_backend("avx512vnni").target
    pipeline = default_pipeline(target).split(",register-block,")[0]
    blocks = {}
    for activations in ("uint8", "int8"):
        model = quantized(padded_conv_model(8, c_out=64), activations)
        program = PassManager(pipeline, target, finish=False).run(import_onnx(model))
        conv = next(k for k in program.kernels if k.op == "QLinearConv")
        assert flipped_activations(conv, target) == (activations == "int8")
        blocks[activations] = chosen_blocks(program, target)[conv.name]
    pixels, channels = blocks["int8"]
    assert channels == blocks["uint8"][1] == 4 and pixels * (channels + 1) + 1 <= FLIPPED_REGISTERS
    assert blocks["uint8"][0] * (channels + 1) + 1 > FLIPPED_REGISTERS
