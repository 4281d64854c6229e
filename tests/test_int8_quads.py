"""pmaddubsw quads on ssse3, avx2 and avx512 (issue 16; avx512's 16 lanes in two 256-bit halves): uint8 activations
times int8 weights four input channels per lane, exact only where no int16 pair sum saturates. Layers whose weights
pass the generation-time proof take one pmaddubsw + pmaddwd per quad, the others pmaddwd on int16 pairs; every result
is identical to onnxruntime's. Hand-written QDQ Convs give the weights exactly: 7-bit weights (proven), full-range
weights with both extremes side by side (pmaddubsw on them saturates: shown by compiling them as quads anyway),
channel tails, zero points != 0, uint8 and int8 activations, inputs and outputs saturated at both ends."""

from __future__ import annotations

import re
from functools import partial

import numpy as np
import onnx
import onnxruntime.quantization
import pytest
from helpers import ROOT, skip_unless_host_runs
from int8_models import (
    OPSET,
    compare,
    onnxruntime_outputs,
    quantized,
    random_feeds,
    residual_model,
    stacked_conv_model,
)
from onnx import TensorProto, helper, numpy_helper

import nncg
import nncg.passes.dot_product as dot_product
from nncg.backends import get_target
from nncg.passes import default_pipeline
from nncg.passes.dot_product import pair_sums_fit_int16

TARGETS = ("ssse3", "avx2", "avx512")
MADDUBS = {"ssse3": "_mm_maddubs_epi16(", "avx2": "_maddubs_epi16(", "avx512": "_maddubs_epi16("}
TYPES = {"uint8": np.uint8, "int8": np.int8}


def int8_weights(kind: str, c_out: int, c_in: int, seed: int) -> np.ndarray:
    """[c_out, c_in, 3, 3] int8 weights: "proven" 7-bit (-64..63, what reduce_range writes: every pair
    sum fits int16), or "full" -128..127 with channels 0 and 1 at one extreme together in every tap
    (255 * 254 and 255 * -256 leave int16)."""
    rng = np.random.default_rng(seed)
    if kind == "proven":
        return rng.integers(-64, 64, (c_out, c_in, 3, 3)).astype(np.int8)
    w = rng.integers(-128, 128, (c_out, c_in, 3, 3))
    w[0::2, :2] = 127
    w[1::2, :2] = -128
    return w.astype(np.int8)


def qdq_conv(weights: np.ndarray, activations: str, x_zero: int, y_zero: int, y_scale: float = 1.0):
    """QuantizeLinear, DequantizeLinear, then a padded 3x3 Conv of int8 weights (per-channel scales)
    and int32 bias, QuantizeLinear to y_scale, DequantizeLinear: the Conv runs as QLinearConv."""
    c_out, c_in = weights.shape[:2]
    rng = np.random.default_rng(c_in)
    numpy_type = TYPES[activations]
    x_scale, w_scale = np.float32(0.05), rng.uniform(0.002, 0.004, c_out).astype(np.float32)
    init = {
        "xs": x_scale, "xz": numpy_type(x_zero), "ys": np.float32(y_scale), "yz": numpy_type(y_zero),
        "wq": weights, "wsc": w_scale, "wz": np.zeros(c_out, np.int8),
        "bq": rng.integers(-3000, 3000, c_out).astype(np.int32), "bs": (x_scale * w_scale).astype(np.float32),
        "bz": np.zeros(c_out, np.int32),
    }  # fmt: skip
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "xs", "xz"], ["xd"]),
        helper.make_node("DequantizeLinear", ["wq", "wsc", "wz"], ["w"], axis=0),
        helper.make_node("DequantizeLinear", ["bq", "bs", "bz"], ["b"], axis=0),
        helper.make_node("Conv", ["xd", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("QuantizeLinear", ["c", "ys", "yz"], ["cq"]),
        helper.make_node("DequantizeLinear", ["cq", "ys", "yz"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "quads",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, c_in, 6, 6])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [numpy_helper.from_array(np.asarray(a), n) for n, a in init.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])


def feeds(c_in: int, count: int = 3) -> list[dict[str, np.ndarray]]:
    """Inputs reaching both ends of the input type (x_scale 0.05: +-12.8 and beyond), the last all at the top."""
    rng = np.random.default_rng(7)
    out = [{"x": rng.uniform(-9, 9, (1, c_in, 6, 6)).astype(np.float32)} for _ in range(count - 1)]
    return out + [{"x": np.full((1, c_in, 6, 6), 20.0, np.float32)}]


def saturating_model(weights: np.ndarray, activations: str, x_zero: int, y_zero: int):
    """qdq_conv with an output scale that puts the Conv's extremes on the inputs twice beyond the output
    type's ends."""
    probe = qdq_conv(weights, activations, x_zero, y_zero)
    probe.graph.node.pop()
    probe.graph.node.pop()
    probe.graph.output[0].name = "c"
    values = np.concatenate([onnxruntime_outputs(probe, f)[0].ravel() for f in feeds(weights.shape[1])])
    info = np.iinfo(TYPES[activations])
    assert values.min() < 0 < values.max()
    scale = min(values.max() / (info.max - y_zero), values.min() / (info.min - y_zero)) / 2
    return qdq_conv(weights, activations, x_zero, y_zero, y_scale=float(scale))


def direct(model, target: str):
    """Compiled for target with the direct kernel these tests are about (no integer Winograd)."""
    return nncg.compile(
        model, target=target, verify_ir=True, pipeline=default_pipeline(get_target(target)).replace(",winograd", "")
    )


def check(model, target: str, c_in: int):
    """Compiled for target, identical to onnxruntime, with outputs at both ends of their type."""
    skip_unless_host_runs(target)
    compiled = direct(model, target)
    inputs = feeds(c_in)
    result = compare(model, compiled, inputs)
    assert result.max_steps == 0 and result.identical == 1.0, result
    init = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    info = np.iinfo(init["yz"].dtype)
    ends = {(v - int(init["yz"])) * init["ys"] for v in (info.min, info.max)}
    seen = np.concatenate([onnxruntime_outputs(model, f)[0].ravel() for f in inputs])
    assert all(np.isclose(seen, end).any() for end in ends), "the outputs do not reach both ends"
    return compiled


def test_the_proof():
    """255 * (sum of a pair's positive weights) <= 32767 and of its negative ones >= -32768."""
    assert pair_sums_fit_int16(np.array([[64], [64]], np.int8))  # 255 * 128 = 32640
    assert not pair_sums_fit_int16(np.array([[65], [64]], np.int8))  # 255 * 129 = 32895
    assert pair_sums_fit_int16(np.array([[-64], [-64]], np.int8))
    assert not pair_sums_fit_int16(np.array([[-65], [-64]], np.int8))
    assert pair_sums_fit_int16(np.array([[127], [-128]], np.int8))  # opposite signs never add up
    assert pair_sums_fit_int16(np.array([[127]], np.int8))  # a lone last channel pairs with 0
    assert not pair_sums_fit_int16(np.array([[[1], [2]], [[100], [100]]], np.int8))  # any lead position


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("kind", ["proven", "full"])
@pytest.mark.parametrize("c_in", [1, 2, 3, 5, 8])
def test_uint8_quads(c_in, kind, target):
    """Channel tails (the missing channels' weights 0), no input zero point: pmaddubsw on raw uint8
    where the weights are proven, pmaddwd pairs where not."""
    if kind == "full" and c_in < 2:
        pytest.skip("one channel pairs with 0: always proven")
    weights = int8_weights(kind, 6, c_in, seed=c_in)
    compiled = check(saturating_model(weights, "uint8", 0, 128), target, c_in)
    packed = weights.transpose(2, 3, 1, 0)  # [kh, kw, c_in, c_out], as the kernel reads them
    assert pair_sums_fit_int16(packed) == (kind == "proven")
    if c_in > 1:
        assert (MADDUBS[target] in compiled.source) == (kind == "proven")
    else:  # one channel: a tap-dot target pairs the kernel columns instead, proven on those
        taps = get_target(target).tap_dots and pair_sums_fit_int16(packed[:, :, 0, :])
        assert (MADDUBS[target] in compiled.source) == taps


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("kind", ["proven", "full"])
def test_uint8_zero_points(kind, target):
    """Input zero point 117 (folded into the bias), output zero point 30."""
    weights = int8_weights(kind, 6, 8, seed=3)
    compiled = check(saturating_model(weights, "uint8", 117, 30), target, 8)
    assert (MADDUBS[target] in compiled.source) == (kind == "proven")


@pytest.mark.parametrize("target", TARGETS)
def test_int8_activations_keep_pairs(target):
    """Signed activations have no unsigned operand for pmaddubsw: pmaddwd pairs, still exact."""
    weights = int8_weights("full", 6, 5, seed=4)
    compiled = check(saturating_model(weights, "int8", -9, 11), target, 5)
    assert "maddubs" not in compiled.source and "_madd_epi16(" in compiled.source


@pytest.mark.parametrize("target", TARGETS)
def test_unproven_weights_saturate_pmaddubsw(target, monkeypatch):
    """The full-range weights taken as pmaddubsw quads all the same (the proof overruled): the int16
    pair sums saturate and the outputs leave onnxruntime's, so the tests above would catch a wrong proof."""
    skip_unless_host_runs(target)
    weights = int8_weights("full", 6, 8, seed=3)
    model = saturating_model(weights, "uint8", 0, 128)
    monkeypatch.setattr(dot_product, "pair_sums_fit_int16", lambda array: True)
    compiled = direct(model, target)
    assert MADDUBS[target] in compiled.source
    assert compare(model, compiled, feeds(8)).identical < 1.0


@pytest.mark.parametrize("target", TARGETS)
def test_reduce_range_model_takes_quads_everywhere(target, monkeypatch):
    """A whole model (Convs, a residual Add, MaxPool, MatMul) quantised with onnxruntime's reduce_range:
    7-bit weights, every layer with more than one input channel proven, the Convs and the MatMul in
    pmaddubsw quads and identical to onnxruntime."""
    skip_unless_host_runs(target)
    import int8_models

    monkeypatch.setattr(
        int8_models, "quantize_static", partial(onnxruntime.quantization.quantize_static, reduce_range=True)
    )
    float_model = residual_model()
    model = quantized(float_model)
    weights = [numpy_helper.to_array(t) for t in model.graph.initializer if t.data_type == TensorProto.INT8]
    assert weights and all(np.abs(w.astype(int)).max() <= 64 for w in weights)  # any two sum to <= 128
    compiled = nncg.compile(model, target=target, verify_ir=True)
    result = compare(model, compiled, random_feeds(float_model, 3, 11))
    assert result.max_steps == 0 and result.identical == 1.0, result
    for kernel in ("QLinearConv */", "QLinearDense */"):
        bodies = [body.split("/* ")[0] for body in compiled.source.split(kernel)[1:]]
        assert bodies and all(MADDUBS[target] in body for body in bodies), kernel


# every model and every target at least once, not all twelve pairs (mobilenet on avx512 alone took 90 s)
MODEL_TARGETS = [
    ("resnet8", "ssse3"), ("resnet8", "avx512"), ("dscnn", "avx2"),
    ("mobilenet_v1_025", "avx2"), ("autoencoder", "ssse3"), ("autoencoder", "avx512"),
]  # fmt: skip


@pytest.mark.parametrize("name, target", MODEL_TARGETS)
def test_mlperf_tiny_with_reduce_range_take_quads_in_every_layer(name, target, monkeypatch):
    """The benchmark's models quantised by nncg.quantize(reduce_range=True): every reduction's weights
    pass the proof (full-range ones pass in none: README), every layer with pmaddwd pairs also has pmaddubsw
    quads but for dscnn's first layer (its input keeps a zero point: signed, pairs), and the outputs
    are identical to onnxruntime's on the same QDQ model."""
    skip_unless_host_runs(target)
    path = ROOT / "benchmarks" / "models" / f"{name}.onnx"
    float_model = onnx.load(path)
    samples = random_feeds(float_model, 16, 1234)
    (input_name,) = samples[0]
    calibration = np.stack([s[input_name] for s in samples])
    proofs = spy_on_the_proof(monkeypatch)
    model = nncg.quantize(float_model, calibration, reduce_range=True)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert proofs and all(proofs)
    pairs_only = [
        kernel
        for kernel, body in layer_bodies(compiled.source)
        if "_madd_epi16(" in body and MADDUBS[target] not in body
    ]
    assert pairs_only == (["stem_conv"] if name == "dscnn" else [])
    if target == "avx512":  # 16 lanes: two 256-bit pmaddubsw of the same broadcast activations
        assert "_mm256_maddubs_epi16(_mm512_castsi512_si256(" in compiled.source
    result = compare(model, compiled, random_feeds(float_model, 3, 11))
    assert result.max_steps == 0 and result.identical == 1.0, result


def spy_on_the_proof(monkeypatch) -> list[bool]:
    """The results of every pair_sums_fit_int16 the dot-product pass asks, in a list."""
    results: list[bool] = []

    def spy(array):
        results.append(pair_sums_fit_int16(array))
        return results[-1]

    monkeypatch.setattr(dot_product, "pair_sums_fit_int16", spy)
    return results


def layer_bodies(source: str) -> list[tuple[str, str]]:
    """(layer name, C up to the next layer's comment) of each QLinearConv and QLinearDense kernel."""
    parts = re.split(r"/\* (\w+): (QLinear\w+) \*/", source)
    return [
        (parts[i], parts[i + 2]) for i in range(1, len(parts) - 2, 3) if parts[i + 1] in ("QLinearConv", "QLinearDense")
    ]


def test_ssse3_pairs_of_a_quad_share_its_load():
    """Full-range weights on ssse3 (pmaddwd pairs) reading a channels-last input of 12 channels in two
    groups of 6: each pair is one half of 4 bytes read at a multiple of 4 (pshufd 0 or 0x55 of one
    unpack; a pair of the second group shares its bytes with the first's), identical to onnxruntime."""
    skip_unless_host_runs("ssse3")
    float_model = stacked_conv_model("grouped")
    model = quantized(float_model)
    compiled = nncg.compile(model, target="ssse3", verify_ir=True)
    quad = "_mm_shuffle_epi32(_mm_unpacklo_epi8(_mm_loadu_si32((const void *)("
    assert quad in compiled.source and "_mm_setzero_si128()), 85)" in compiled.source
    assert "_mm_loadu_si16(" not in compiled.source
    result = compare(model, compiled, random_feeds(float_model, 3, 11))
    assert result.max_steps == 0 and result.identical == 1.0, result
