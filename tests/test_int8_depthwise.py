"""Depthwise int8 convolutions with the taps as dot products (passes/dot_taps.py, issue 16): on
avx512vnni the interior columns' kernel rows become vpdpbusd of 4 taps per channel (2 per pmaddwd for
int8 or zero-point-shifted activations), on avx2 and ssse3 pmaddwd of 2, each lane its own channel's
activations (ssse3: two taps' bytes interleaved into int16 pairs; avx512: 512-bit pmaddwd in two
256-bit halves, AVX-512F having no AVX-512BW); on every x86 target
every result stays identical to onnxruntime's: 3x3 and 5x5, stride 1 and 2, padding, channel counts
that are not multiples of the lanes, a channel multiplier of 2, uint8 and int8 activations (zero points
!= 0), inputs and outputs saturated at both ends."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import skip_unless_host_runs
from int8_models import _model, _weights, compare, quantized, random_feeds
from onnx import helper

import nncg

TARGETS = ("ssse3", "avx2", "avx512", "avx512vnni")


def depthwise_model(
    channels: int,
    kernel: int,
    stride: int,
    multiplier: int = 1,
    relu: bool = True,
    seed: int = 8,
    pads: list[int] | None = None,
    size: tuple[int, int] = (11, 13),
):
    """A 1x1 Conv to `channels` (so the depthwise reads a channels-last input; with `relu` its
    activations' zero point is 0, else not), then a padded depthwise Conv of `kernel` x `kernel` at
    `stride` (`pads` as ONNX's, default kernel // 2 all round), `multiplier` outputs per channel, of
    an input of `size` (height, width)."""
    rng = np.random.default_rng(seed)
    init = {
        "w1": _weights(rng, channels, 3, 1, 1),
        "b1": rng.standard_normal(channels) * 0.3,
        "w": _weights(rng, channels * multiplier, 1, kernel, kernel),
        "b": rng.standard_normal(channels * multiplier) * 0.3,
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c"]),
        helper.make_node("Relu" if relu else "Identity", ["c"], ["p"]),
        helper.make_node(
            "Conv", ["p", "w", "b"], ["y"], group=channels, pads=pads or [kernel // 2] * 4, strides=[stride, stride]
        ),
    ]
    return _model(nodes, [1, 3, *size], init)


def check(float_model, target: str, activations: str, scale: float = 1.0) -> str:
    """The depthwise layer's C, after checking every output identical to onnxruntime's on inputs
    `scale` times the calibration's spread."""
    skip_unless_host_runs(target)
    model = quantized(float_model, activations)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    feeds = [{n: v * np.float32(scale) for n, v in f.items()} for f in random_feeds(float_model, 2, 13)]
    result = compare(model, compiled, feeds)
    assert result.max_steps == 0 and result.identical == 1.0, result
    return compiled.source.split("QLinearConv */")[2].split("/* ")[0]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("channels, kernel, stride", [(16, 3, 1), (24, 3, 2), (19, 5, 1), (40, 5, 2), (7, 3, 1)])
def test_geometries_and_channel_tails(channels, kernel, stride, target):
    conv = check(depthwise_model(channels, kernel, stride), target, "uint8")
    if target == "avx512vnni":  # uint8 activations without a zero point: quads of taps
        assert "_dpbusd_epi32(" in conv and "_slli_epi32(" in conv
    if target == "avx2" and channels >= 8:  # pairs of taps
        assert "_mm256_madd_epi16(_mm256_or_si256(" in conv
    if target == "ssse3" and channels >= 4:  # pairs of taps, their bytes interleaved
        assert "_mm_madd_epi16(_mm_unpacklo_epi8(_mm_unpacklo_epi8(" in conv


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_saturation_and_zero_points(activations, target):
    """Inputs 4 times beyond the calibrated range, activations with a zero point != 0 (no Relu before
    the depthwise): x - x_zero_point is signed, so avx512vnni takes pmaddwd pairs of taps, the lower
    one masked to its 16 bits."""
    conv = check(depthwise_model(20, 3, 1, relu=False), target, activations, scale=4.0)
    if target == "avx512vnni":
        assert "_mm512_madd_epi16(" in conv and "_mm512_and_si512(" in conv
    if target == "avx2":
        assert "_mm256_madd_epi16(_mm256_or_si256(_mm256_and_si256(" in conv
    if target == "ssse3":
        assert "_mm_madd_epi16(_mm_or_si128(_mm_and_si128(" in conv


# per-tap products (the border columns' before they took dots): ssse3's pmaddwd of masked lanes, pmulld
TAP_PRODUCTS = {"ssse3": "_mm_set1_epi32(0xFFFF)", "avx2": "_mm256_mullo_epi32("}


@pytest.mark.parametrize("target", ("ansi-c", "ssse3", "avx2", "avx512vnni"))
@pytest.mark.parametrize(
    "channels, kernel, stride, pads, size, relu",
    [
        (11, 3, 1, [1, 2, 2, 1], (9, 11), False),  # padding 1 and 2 on either side, a zero point != 0
        (13, 5, 2, [2, 2, 2, 2], (10, 15), True),  # 5x5 strided, padding 2: two border columns each side
        (6, 5, 1, [2, 1, 0, 2], (7, 9), False),  # 5x5, padding 1 and 2, stride 1
        (9, 5, 1, [2, 2, 2, 2], (6, 3), True),  # no interior column: every column a border one
    ],
)
def test_border_columns(channels, kernel, stride, pads, size, relu, target):
    """The border columns take their inside taps as dots too (dot_taps.py), the outside ones read as 0:
    identical to onnxruntime at both edges, odd widths, channel counts no multiple of the lanes; and
    with an interior column no tap is a product of its own."""
    activations = "uint8" if relu else "int8"
    model = depthwise_model(channels, kernel, stride, relu=relu, pads=pads, size=size)
    conv = check(model, target, activations, scale=2.0)
    if target in TAP_PRODUCTS and size[1] > kernel:
        assert TAP_PRODUCTS[target] not in conv


@pytest.mark.parametrize("target", TARGETS)
def test_channel_multiplier(target):
    """Two outputs per input channel: x is not the output channel's own, so the taps stay products."""
    check(depthwise_model(8, 3, 1, multiplier=2), target, "uint8")


@pytest.mark.parametrize("target", TARGETS)
def test_one_input_channel_taps(target):
    """A first layer of one input channel (as DS-CNN's 10x4 stem), padded and strided: its kernel
    columns' taps become dots of shared activations (x - x_zero_point: pmaddwd pairs)."""
    rng = np.random.default_rng(9)
    init = {"w": _weights(rng, 16, 1, 5, 4), "b": rng.standard_normal(16) * 0.3}
    conv = helper.make_node("Conv", ["x", "w", "b"], ["y"], pads=[2, 1, 2, 2], strides=[2, 2])
    skip_unless_host_runs(target)
    model = quantized(_model([conv], [1, 1, 15, 10], init), "uint8")
    compiled = nncg.compile(model, target=target, verify_ir=True)
    result = compare(model, compiled, random_feeds(model, 2, 14))
    assert result.max_steps == 0 and result.identical == 1.0, result
    assert "_madd_epi16(" in compiled.source.split("QLinearConv */")[1]


def test_avx512_takes_taps_in_halves():
    """avx512 (AVX-512F: no 512-bit pmaddwd) takes a depthwise's taps as dots too, each 256-bit half of
    the per-lane activations (the upper one extracted) times its half of the weights."""
    conv = check(depthwise_model(16, 3, 1), "avx512", "uint8")
    assert "_slli_epi32(" in conv and "_mm256_madd_epi16(_mm512_extracti64x4_epi64(" in conv
