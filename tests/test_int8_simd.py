"""The vectorised int8 kernels (issue 16): on ssse3, avx2 and avx512 the integer convolutions and matrix
products run on int32 vectors over output channels, register-blocked, and still match onnxruntime to
the bit. Tails: 12 channels are 8 + 4 lanes on avx2, 8 + an overlapping 8 on avx512; the Gemm's 5
outputs end in a vector overlapping the one before. A depthwise or grouped Conv reads a channels-last
input here (after a 1x1 Conv), as in a network: on the planar graph input it stays scalar."""

from __future__ import annotations

import pytest
from helpers import skip_unless_host_runs
from int8_models import clip_gemm_model, compare, conv_model, quantized, random_feeds, stacked_conv_model

import nncg

MODELS = {
    **{kind: lambda kind=kind: conv_model(kind) for kind in ("3x3", "stride2", "1x1")},
    **{kind: lambda kind=kind: stacked_conv_model(kind) for kind in ("depthwise", "grouped")},
    "gemm": clip_gemm_model,
}


def check(float_model, target: str, **options) -> nncg.CompiledModel:
    skip_unless_host_runs(target)
    model = quantized(float_model)
    compiled = nncg.compile(model, target=target, verify_ir=True, **options)
    result = compare(model, compiled, random_feeds(float_model, 2, 7))
    assert result.max_steps == 0 and result.identical == 1.0, result
    return compiled


# the dot product of input channels each target prints (ssse3's channel-by-channel product is a pmaddwd too)
MULTIPLY = {
    "ssse3": "_mm_madd_epi16(",
    "avx2": "_madd_epi16(",
    "avx512": "_madd_epi16(",
    "avx512vnni": "_dpbusd_epi32(",
}


@pytest.mark.parametrize("target", sorted(MULTIPLY))
@pytest.mark.parametrize("kind", sorted(MODELS))
def test_vector_kernels_match_onnxruntime_to_the_bit(kind, target):
    compiled = check(MODELS[kind](), target)
    # the graph input's zero point is folded (3 channels, one group): uint8 quads on avx512vnni too
    assert MULTIPLY[target] in compiled.source and "_cvtps_epi32(" in compiled.source


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_int8_activations(target):
    """int8 activations and zero points: x - x_zero_point still within int16 (ssse3's pmaddwd)."""
    skip_unless_host_runs(target)
    float_model = stacked_conv_model("depthwise")
    model = quantized(float_model, "int8")
    result = compare(model, nncg.compile(model, target=target), random_feeds(float_model, 2, 7))
    assert result.max_steps <= 1 and result.identical >= 0.99, result


def test_tails_are_vectors():
    """12 depthwise channels on avx2: an 8-lane and a 4-lane block of dots, no scalar tail."""
    compiled = check(stacked_conv_model("depthwise"), "avx2")
    assert "_mm_madd_epi16(" in compiled.source and "_mm256_madd_epi16(" in compiled.source
    assert "nncg_int32 acc" not in compiled.source


def test_fixed_point_form_stays_scalar():
    skip_unless_host_runs("avx2")
    compiled = nncg.compile(quantized(conv_model("3x3")), target="avx2", requantize="fixed")
    assert "_mullo_epi32(" not in compiled.source and "nncg_requantize_fixed(" in compiled.source


def test_sanitizers_find_nothing():
    skip_unless_host_runs("avx2")
    model = quantized(conv_model("depthwise"))
    result = compare(
        model, nncg.compile(model, target="avx2"), random_feeds(conv_model("depthwise"), 1, 7), sanitize=True
    )
    assert result.identical == 1.0, result
