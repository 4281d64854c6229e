"""Integer Winograd F(2x2, 3x3) of int8 3x3 convolutions (lowering/winograd_integer.py): QLinearConv and
QDQ Convs, uint8 and int8 activations, per-channel and per-tensor weights, zero points not 0, outputs
saturating at both ends, odd image sizes (tiles cut at the bottom and right), bit-identical to
onnxruntime; on ansi-c forced (the pass leaves scalar C direct), on ssse3 and avx2 by the pass by default, in
vectors there (pmaddwd on int16 pairs). Two stacked convs: the first reads the model's input (channels
first: its input transform stays scalar), the second a channels-last tensor (vectorised)."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import onnx_model, skip_unless_host_runs
from int8_models import compare, onnxruntime_outputs, quantized, random_feeds
from onnx import TensorProto, helper

import nncg
from nncg import lowering
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.lowering.band_plan import BandPlan
from nncg.lowering.bands import BandGroup
from nncg.lowering.winograd import BAND_CHUNKS, WHOLE_CHUNKS, band_scratch_bytes, blocked_filters
from nncg.passes import default_pipeline
from nncg.passes.winograd import winograd, winograd_candidates
from nncg.verify import run_compiled

WINOGRAD_KERNEL = "QLinearConvWinograd */"  # the comment above each such kernel
FEEDS, SEED = 2, 5


def qlinear_model(activations: str, per_channel: bool, size: tuple[int, int], seed: int = 0) -> onnx.ModelProto:
    """QuantizeLinear, two padded 3x3 QLinearConvs (8 -> 12 -> 13 channels: 13 is a vector and a tail),
    DequantizeLinear. Weight zero points not 0 (per channel: on one channel; per tensor: 3), so the
    weights are int16 minus them; the output scale is small enough to saturate both ends."""
    rng = np.random.default_rng(seed)
    dtype = np.uint8 if activations == "uint8" else np.int8
    zero = {"uint8": (120, 40, 90), "int8": (-10, 20, -5)}[activations]
    init = {"xs": np.float32(0.03), "xz": dtype(zero[0])}
    nodes = [helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q0"])]
    channels = (8, 12, 13)
    for i, (c_in, c_out) in enumerate(zip(channels, channels[1:])):
        w_zero = np.zeros(c_out, np.int8)
        w_zero[1] = 4
        init |= {
            f"w{i}": rng.integers(-128, 128, (c_out, c_in, 3, 3)).astype(np.int8),
            f"ws{i}": rng.uniform(0.002, 0.01, c_out).astype(np.float32) if per_channel else np.float32(0.005),
            f"wz{i}": w_zero if per_channel else np.int8(3),
            f"ys{i}": np.float32((0.4, 0.3)[i]),
            f"yz{i}": dtype(zero[i + 1]),
            f"b{i}": rng.integers(-4000, 4000, c_out).astype(np.int32),
        }
        names = [f"q{i}", "xs" if i == 0 else "ys0", "xz" if i == 0 else "yz0"]
        names += [f"w{i}", f"ws{i}", f"wz{i}", f"ys{i}", f"yz{i}", f"b{i}"]
        nodes.append(helper.make_node("QLinearConv", names, [f"q{i + 1}"], pads=[1, 1, 1, 1]))
    nodes.append(helper.make_node("DequantizeLinear", ["q2", "ys1", "yz1"], ["y"]))
    return onnx_model(nodes, inputs={"x": (1, 8, *size)}, initializers=init, opset=13)


def float_model(size: tuple[int, int], seed: int = 1) -> onnx.ModelProto:
    """Two padded 3x3 Convs (8 -> 10 -> 9 channels) with a Relu between: quantized to QDQ, QLinearConvs."""
    rng = np.random.default_rng(seed)
    init = {
        "w1": rng.standard_normal((10, 8, 3, 3)).astype(np.float32) / 8,
        "b1": rng.standard_normal(10).astype(np.float32) * 0.3,
        "w2": rng.standard_normal((9, 10, 3, 3)).astype(np.float32) / 9,
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("Conv", ["r1", "w2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    graph = helper.make_graph(
        nodes,
        "winograd_qdq",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 8, *size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [onnx.numpy_helper.from_array(a, n) for n, a in init.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def compiled_for(
    model: onnx.ModelProto, target: str, winograd: bool | None = None, layers: list[str] | None = None, **options
):
    """The model for `target` as nncg.compile makes it, or by the default pipeline (of default_pipeline's
    `options`) with Winograd forced on or off with `winograd` (on `layers`, by default those it applies to)."""
    skip_unless_host_runs(target)
    if winograd is None and not options:
        return nncg.compile(model, target, verify_ir=True)
    pipeline = default_pipeline(nncg.get_target(target), **options)
    if winograd is not None:
        flag = "true" if winograd else "false"
        choice = ";".join(f"{name}:{flag}" for name in layers or winograd_candidates(import_onnx(model)))
        pipeline = pipeline.replace(",winograd", f",winograd{{layers={choice}}}")
    return nncg.compile(model, target, verify_ir=True, pipeline=pipeline)


def winograd_build(model: onnx.ModelProto, target: str, kernels: int = 2):
    """Integer Winograd forced (on ansi-c the pass does not choose it by itself), in `kernels` of its own."""
    compiled = compiled_for(model, target, True)
    assert compiled.source.count(WINOGRAD_KERNEL) == kernels
    return compiled


@pytest.mark.parametrize(
    "target, activations, per_channel, size",
    [
        ("ansi-c", "uint8", True, (7, 9)),
        ("ansi-c", "int8", False, (5, 4)),
        ("ssse3", "uint8", False, (7, 9)),
        ("ssse3", "int8", True, (6, 5)),
        ("avx2", "uint8", True, (9, 7)),
        ("avx2", "int8", False, (7, 9)),
    ],
)
def test_qlinear_conv_matches_onnxruntime_to_the_bit(target, activations, per_channel, size):
    model = qlinear_model(activations, per_channel, size)
    compiled = winograd_build(model, target)
    low, high = (0, 255) if activations == "uint8" else (-128, 127)
    scale, zero = np.float32(0.3), (40, 90)[1] if activations == "uint8" else (20, -5)[1]
    ends = np.float32(low - zero) * scale, np.float32(high - zero) * scale
    for feed in random_feeds(model, FEEDS, SEED):
        expected = onnxruntime_outputs(model, {"x": feed["x"] * 3})[0]
        ours = run_compiled(compiled, [feed["x"] * 3])[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)
        assert np.any(expected == ends[0]) and np.any(expected == ends[1])  # saturated at both ends


@pytest.mark.parametrize("target, activations", [("ansi-c", "uint8"), ("ssse3", "int8"), ("avx2", "uint8")])
def test_qdq_conv_matches_onnxruntime_and_the_direct_kernel(target, activations):
    """As test_int8's check (bit-identical for uint8; int8 QDQ onnxruntime runs partly in float), and
    to the bit the direct integer kernel's output."""
    model = quantized(float_model((7, 5)), activations)
    winograd, direct = winograd_build(model, target), compiled_for(model, target, False)
    assert WINOGRAD_KERNEL not in direct.source
    feeds = random_feeds(model, FEEDS, SEED)
    result = compare(model, winograd, feeds)
    assert result.max_steps <= 1, result
    assert result.identical >= (1.0 if activations == "uint8" else 0.99), result
    for feed in feeds:
        np.testing.assert_array_equal(run_compiled(winograd, [feed["x"]])[0], run_compiled(direct, [feed["x"]])[0])


def test_vector_targets_run_the_gemms_as_int16_pair_dots():
    source = compiled_for(qlinear_model("uint8", True, (7, 9)), "avx2", True).source
    assert "_mm256_madd_epi16(_mm256_broadcastd_epi32(_mm_loadu_si32(" in source  # V pairs x U' pairs
    assert "nncg256_store_int16(" in source  # the input transform's int16 vectors


def test_cost_rule_takes_it_on_the_int16_dot_targets():
    """ssse3 and avx2 (Target.int16_dots) take it by default, not scalar C nor avx512."""
    graph = import_onnx(qlinear_model("uint8", True, (7, 9)))
    for target, expected in [("ansi-c", "direct"), ("ssse3", "winograd"), ("avx2", "winograd"), ("avx512", "direct")]:
        chosen = winograd(graph, nncg.get_target(target))
        assert [n.attrs.algorithm for n in chosen.nodes if n.op == "QLinearConv"] == [expected] * 2, target


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_default_build_runs_it_bit_identical(target):
    """nncg.compile's default build of an int8 model takes integer Winograd on its 3x3 QLinearConvs of 8
    and more input channels, bit-identical to onnxruntime."""
    model = qlinear_model("int8", False, (9, 7))
    compiled = compiled_for(model, target)
    assert compiled.source.count(WINOGRAD_KERNEL) == 2
    assert_matches_onnxruntime(model, compiled)


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2"])
def test_kept_in_bands_bit_identical(target, monkeypatch):
    """Both QLinearConvs and the input's QuantizeLinear in one group of bands, Winograd kept (over 2-row
    tiles, its int16 and int32 scratch a band's): bit-identical at band heights 2 and 4, under the
    sanitizers on ansi-c; on x86 the transforms in int16 vectors as run whole."""
    model = qlinear_model("uint8", True, (9, 7))
    for rows in (2, 4):
        monkeypatch.setattr(lowering, "plan_layers", winograd_bands(rows))
        compiled = winograd_build(model, target, kernels=0)
        band = compiled.source[compiled.source.index(": Band */") :]
        assert "v_QLinearConv_1" in band and ("store_int16(" in band) == (target != "ansi-c")
        assert f"/* 16x1x{BAND_CHUNKS['QLinearConv'].channels} row-major */" in compiled.source  # M: one block
        assert_matches_onnxruntime(model, compiled, sanitize=target == "ansi-c" and rows == 2)


def test_band_scratch_holds_one_block_of_output_channels():
    """In bands, a chunk's GEMMs and output transform run a block of output channels at a time
    (12 = 8 + 4, 13 = 8 + 5: a whole block and the rest), so the planner counts an int32 M of one block
    of the chunk's tiles next to the int16 V of all input channels."""
    graph = import_onnx(qlinear_model("uint8", True, (9, 7)))
    convs = [n for n in graph.nodes if n.op == "QLinearConv"]
    chunk = BAND_CHUNKS["QLinearConv"]
    assert chunk.channels == 8 and not chunk.whole_rows
    v_bytes, m_bytes = 16 * chunk.tiles * 12 * 2, 16 * chunk.tiles * 8 * 4
    assert band_scratch_bytes(graph, convs) == v_bytes + m_bytes
    assert band_scratch_bytes(graph, convs[:1]) == 16 * chunk.tiles * 8 * 2 + m_bytes  # 8 in, 12 out


def test_blocked_filters_keep_a_block_contiguous():
    """A blocked layer's U is U[block][e][ci][channel of the block], the last block padded with zeros,
    so a block's GEMMs read whole cache lines of it; unblocked, U stays as it is."""
    u = np.arange(16 * 3 * 13, dtype=np.int16).reshape(16, 3, 13)
    blocked = blocked_filters(u, 8)
    assert blocked.shape == (2, 16, 3, 8)
    np.testing.assert_array_equal(blocked[1, :, :, :5], u[:, :, 8:])
    np.testing.assert_array_equal(blocked[0], u[:, :, :8])
    assert not blocked[1, :, :, 5:].any()
    assert blocked_filters(u, 13) is u


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2"])
def test_whole_layer_scratch_is_a_part_of_a_tile_row(target):
    """A layer run whole takes its tiles a part of a tile row at a time (winograd.WHOLE_CHUNKS), so its
    int16 V and int32 M hold that many tiles, not a row of 11 (21 columns, the last tile cut at the
    right; 5 rows, the last tile row cut at the bottom): bit-identical."""
    model = qlinear_model("uint8", True, (5, 21))
    compiled = winograd_build(model, target)
    chunk = WHOLE_CHUNKS["QLinearConv"]
    assert not chunk.whole_rows and chunk.tiles < 11
    assert f"/* 16x{chunk.tiles}x8 row-major */" in compiled.source  # V of the first conv: 8 input channels
    assert f"/* 16x{chunk.tiles}x13 row-major */" in compiled.source  # M of the second: 13 output channels
    assert_matches_onnxruntime(model, compiled)


def winograd_bands(rows: int):
    """A stand-in for lowering's planner: every layer but the DequantizeLinear in one group, Winograd kept."""
    return lambda graph, *_: BandPlan((BandGroup(tuple(n.name for n in graph.nodes[:-1]), rows, True),))


def assert_matches_onnxruntime(model: onnx.ModelProto, compiled, sanitize: bool = False) -> None:
    for feed in random_feeds(model, FEEDS, SEED):
        expected = onnxruntime_outputs(model, {"x": feed["x"] * 3})[0]
        ours = run_compiled(compiled, [feed["x"] * 3], sanitize=sanitize)[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)


def test_sums_beyond_int32_stay_direct():
    """A bias near the int32 limit: 4 b (Winograd's sums are 4 times the direct ones) would overflow,
    so the pass leaves the layer direct and refuses to force it."""
    model = qlinear_model("uint8", True, (5, 5))
    bias = next(t for t in model.graph.initializer if t.name == "b1")
    bias.CopyFrom(onnx.numpy_helper.from_array(np.full(13, 2**30, np.int32), "b1"))
    assert winograd_candidates(import_onnx(model)) == ["QLinearConv_1"]
    assert compiled_for(model, "avx2", True).source.count(WINOGRAD_KERNEL) == 1
    with pytest.raises(NncgError, match="integer transforms"):
        compiled_for(model, "avx2", True, ["QLinearConv_2"])


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_direct_kernel_of_int16_weights_on_vectors(target):
    """The direct QLinearConv whose weights are int16 (a weight zero point subtracted) widens them in
    vectors (widen_int16; before, avx2 and ssse3 failed to print it)."""
    model = qlinear_model("uint8", True, (5, 6))
    compiled = compiled_for(model, target, False)
    for feed in random_feeds(model, 1, SEED):
        expected = onnxruntime_outputs(model, feed)[0]
        np.testing.assert_array_equal(run_compiled(compiled, [feed["x"]])[0].reshape(expected.shape), expected)


def test_fixed_point_form_matches_the_direct_kernel():
    """--requantize fixed: the multiplier / 4 is the same significand with the shift 2 larger, and
    4 times the sum is requantised to what the direct kernel's sum is, to the bit."""
    model = qlinear_model("int8", True, (7, 9))
    outputs = []
    for forced in (True, False):
        compiled = compiled_for(model, "ansi-c", forced, requantize="fixed")
        assert compiled.source.count(WINOGRAD_KERNEL) == (2 if forced else 0)
        outputs.append([run_compiled(compiled, [feed["x"] * 3])[0] for feed in random_feeds(model, FEEDS, SEED)])
    for winograd_output, direct_output in zip(*outputs):
        np.testing.assert_array_equal(winograd_output, direct_output)
