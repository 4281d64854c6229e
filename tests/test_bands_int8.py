"""int8 models in bands (issue 18): QuantizeLinear, QLinearConv (dense, depthwise, strided), int8
MaxPool, QLinearAveragePool, table lookups and requantised adds streamed over bands of rows, the
planner counting 1-byte activations, and a depthwise QLinearConv in place; every plan bit-identical
with onnxruntime running the same quantized model."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from helpers import skip_unless_host_runs
from int8_models import _model, _weights, compare, input_shapes, quantized, random_feeds, repository_model
from onnx import helper, numpy_helper
from test_bands import band_kernels, depthwise_peak_model, lowered_graph
from test_cross_targets import require

import nncg
from nncg import lowering
from nncg.backends import get_target
from nncg.compiler import memory_figures
from nncg.ir.applicability import fused_ops_vectorise
from nncg.lowering import band_plan
from nncg.lowering.band_plan import BandPlan, plan_layers, plan_steps
from nncg.lowering.bands import BandGroup, geometry

MODELS = {  # the MLPerf-Tiny-shaped classifiers and robot, as tests/test_int8.py quantises them
    "robot": "examples/robot.onnx",
    "resnet8": "benchmarks/models/resnet8.onnx",
    "mobilenet": "benchmarks/models/mobilenet_v1_025.onnx",
    "dscnn": "benchmarks/models/dscnn.onnx",
    "autoencoder": "benchmarks/models/autoencoder.onnx",
}
# what each target's int8 dot products are spelled in its C: the banded convolutions run in vectors
DOTS = {
    "ssse3": ("_mm_madd_epi16", "_mm_maddubs_epi16"),
    "avx2": ("_mm256_madd_epi16", "_mm256_maddubs_epi16"),
    "avx512": ("_mm512_madd_epi16", "_mm512_maddubs_epi16", "_mm256_madd_epi16", "_mm256_maddubs_epi16"),
    "avx512vnni": ("_mm512_dpbusd_epi32", "_mm256_dpbusd_epi32"),
    "neon": ("nncg_vdot2q_s32",),
    "neon-dotprod": ("vdotq_s32",),
}
X86 = ("ssse3", "avx2", "avx512", "avx512vnni")
INTEGER_WINOGRAD = "QLinearConvWinograd */"  # the comment above an integer Winograd kernel
HIGH_RESOLUTION = ("robot", "resnet8", "mobilenet")  # a large first stage: balanced halves the arena
FRAGMENTED = ("mobilenet",)  # plan-memory's greedy placement leaves a gap above the layer bound at speed


def check(model: onnx.ModelProto, compiled: nncg.CompiledModel, feeds: int = 2, **run) -> None:
    result = compare(model, compiled, random_feeds(model, feeds, 7), **run)
    assert result.max_steps == 0 and result.identical == 1.0, result


def chain_model(seed: int = 11) -> onnx.ModelProto:
    """Conv 3x3 -> LeakyRelu (a table) -> depthwise 3x3 stride 2 with Relu -> MaxPool 3 stride 2
    padded -> Conv 3x3 plus the pool's output (a requantised Add) -> AveragePool 3 padded -> Conv 1x1:
    one chain of every int8 kind the bands take."""
    rng = np.random.default_rng(seed)
    init = {
        "w1": _weights(rng, 8, 3, 3, 3),
        "b1": rng.standard_normal(8) * 0.2,
        "w2": _weights(rng, 8, 1, 3, 3),
        "w3": _weights(rng, 8, 8, 3, 3),
        "b3": rng.standard_normal(8) * 0.2,
        "w4": _weights(rng, 6, 8, 1, 1),
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("LeakyRelu", ["a"], ["a_r"], alpha=0.1),
        helper.make_node("Conv", ["a_r", "w2"], ["b"], group=8, strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["b"], ["b_r"]),
        helper.make_node("MaxPool", ["b_r"], ["c"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["c", "w3", "b3"], ["d"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["d", "c"], ["e"]),
        helper.make_node("AveragePool", ["e"], ["f"], kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["f", "w4"], ["y"]),
    ]
    return _model(nodes, [1, 3, 37, 21], init)


@pytest.fixture(scope="module")
def chain() -> onnx.ModelProto:
    return quantized(chain_model())


def conv_pair_model(kind: str, channels: int = 3) -> onnx.ModelProto:
    """Conv 3x3 -> QLinearConv 3x3 (`kind`: dense, depthwise or strided dense), both in one band group;
    the input has `channels` channels, 13 columns (no multiple of a vector)."""
    rng = np.random.default_rng(3)
    second = _weights(rng, 8, 1, 3, 3) if kind == "depthwise" else _weights(rng, 8, 8, 3, 3)
    init = {"w1": _weights(rng, 8, channels, 3, 3), "b1": rng.standard_normal(8) * 0.2, "w2": second}
    attrs = {"dense": {}, "depthwise": {"group": 8}, "strided": {"strides": [2, 2]}}[kind]
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["a", "w2"], ["y"], pads=[1, 1, 1, 1], **attrs),
    ]
    return quantized(_model(nodes, [1, channels, 11, 13], init))


def band_source(compiled: nncg.CompiledModel) -> str:
    """The C of the (first) band kernel."""
    start = compiled.source.index(": Band */")
    return compiled.source[start : compiled.source.index("\n}\n", start)]


def assert_banded_dots(compiled: nncg.CompiledModel, target: str) -> None:
    """The band kernel multiplies in the target's dot products: its convolutions are vectorised."""
    source = band_source(compiled)
    assert any(dot in source for dot in DOTS[target]), f"no {DOTS[target]} in the band kernel"


def whole_chain(graph, rows: int) -> BandGroup:
    """Every layer but the final DequantizeLinear, in one group."""
    return BandGroup(tuple(n.name for n in graph.nodes[:-1]), rows)


def whole_chain_plan(rows: int):
    """A stand-in for lowering's planner: whole_chain in bands of `rows`, nothing in place."""
    return lambda graph, *_: BandPlan((whole_chain(graph, rows),))


def test_every_int8_kind_streams_in_one_group(chain):
    graph = lowered_graph(chain, "ansi-c")
    kinds = {"QuantizeLinear", "QLinearConv", "QLinearLookup", "MaxPool", "QLinearAdd", "QLinearAveragePool"}
    assert {n.op for n in graph.nodes} >= kinds
    assert geometry(graph, whole_chain(graph, 1)) is not None
    assert plan_layers(graph, "min").groups  # the plan takes the head, where the image is largest


def test_requantised_adds_are_priced_as_the_vectorize_pass_runs_them(chain):
    """The planner asks the vectorize pass's rule (fused_ops_vectorise): on a target whose QLinearAdds stay
    scalar (no FMA, none in double) each of its elements costs the target's lanes, whole and in bands."""
    graph, avx2 = lowered_graph(chain, "avx2"), get_target("avx2")
    scalar_adds = replace(avx2, fma=False)
    assert fused_ops_vectorise(avx2) and not fused_ops_vectorise(scalar_adds)
    vector, scalar = (band_plan.candidate_steps(graph, band_plan.StepCosts(t)) for t in (avx2, scalar_adds))
    add = next(i for i, node in enumerate(graph.nodes) if node.op == "QLinearAdd")
    extra = (avx2.lanes - 1) * math.prod(graph.shape(graph.nodes[add].outputs[0]))
    assert extra > 0 and len(vector) == len(scalar)
    for v, s in zip(vector, scalar):
        assert (v.start, v.stop, v.group, v.bytes) == (s.start, s.stop, s.group, s.bytes)
        assert s.cost == pytest.approx(v.cost + (extra if v.start <= add < v.stop else 0))


def kernel_sources(source: str) -> dict[str, str]:
    """Each kernel's C by its name (the comment above it)."""
    headers = re.finditer(r"^/\* (\S+): \w+ \*/$", source, re.MULTILINE)
    return {m.group(1): source[m.end() : source.index("\n}\n", m.end())] for m in headers}


def test_fixed_requantisation_is_priced_as_the_vectorize_pass_runs_it(chain, monkeypatch):
    """Under requantize=fixed an int8 kernel that requantises in the fixed-point form stays scalar (the
    vectorize pass's rule, integer_kernel_vectorises): the planner prices a layer run whole, and a band
    kernel, scalar (the target's lanes an element) exactly where the pass leaves its kernel scalar."""
    target = get_target("avx2")
    graph, costs = lowered_graph(chain, "avx2"), band_plan.StepCosts(target, "fixed")

    def vectorised(requantize: str) -> set[str]:
        kernels = kernel_sources(nncg.compile(chain, target="avx2", requantize=requantize).source)
        return {name for name, c in kernels.items() if re.search(r"_mm(256)?_", c)}

    fixed, floats = vectorised("fixed"), vectorised("float")  # lookups and tiny layers: scalar either way
    priced = {n.name for n in graph.nodes if n.name in floats and costs.of(graph, [n]).element(n) == 1}
    assert fixed == priced and floats - fixed
    monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(2))
    assert re.search(r"_mm(256)?_", band_source(nncg.compile(chain, target="avx2", requantize="fixed"))) is None
    band = graph.nodes[:-1]
    assert all(costs.of(graph, band).element(n) == target.lanes for n in band)
    assert band_plan.StepCosts(target).of(graph, band).element(band[0]) == 1  # the float form vectorises


@pytest.mark.parametrize("rows", [1, 2, 3, 8])
def test_every_band_height_is_bit_identical(chain, rows, monkeypatch):
    """The whole chain in one group at each height (the plan would stop at the pool, where the
    tensors become small)."""
    monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(rows))
    compiled = nncg.compile(chain, target="ansi-c", memory="min", verify_ir=True)
    assert band_kernels(compiled) == 1
    check(chain, compiled, sanitize=rows == 3)


@pytest.mark.parametrize("kind", ["dense", "depthwise", "strided"])
@pytest.mark.parametrize("target", X86)
def test_banded_conv_runs_in_dot_products(kind, target, monkeypatch):
    """A QLinearConv 3x3 reading a line buffer, vectorised in the target's dot products at band
    heights 1, 2, 3 and 8 (an 8-bit line buffer's shift stays scalar: the vectors widen 8-bit loads)."""
    skip_unless_host_runs(target)
    model = conv_pair_model(kind)
    for rows in (1, 2, 3, 8):
        monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(rows))
        compiled = nncg.compile(model, target=target, memory="min", verify_ir=True)
        assert band_kernels(compiled) == 1
        assert_banded_dots(compiled, target)
        check(model, compiled, sanitize=rows == 2 and kind == "depthwise")


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_banded_depthwise_border_columns_run_in_vectors(target, monkeypatch):
    """A depthwise in bands takes vectors over channels in its border columns (split from the interior's
    tap dots) as it does run whole: no scalar int32 accumulator is left in the band kernel."""
    skip_unless_host_runs(target)
    model = conv_pair_model("depthwise")
    monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(2))
    compiled = nncg.compile(model, target=target, memory="min", verify_ir=True)
    assert "nncg_int32 acc" not in band_source(compiled)
    check(model, compiled)


@pytest.mark.parametrize("rows", [1, 2, 3, 8])
@pytest.mark.parametrize("target", X86)
def test_chain_on_the_x86_targets(chain, target, rows, monkeypatch):
    """Every int8 kind in one group, its convolutions and requantised add in vectors, the others scalar."""
    skip_unless_host_runs(target)
    monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(rows))
    compiled = nncg.compile(chain, target=target, memory="min", verify_ir=True)
    assert band_kernels(compiled) == 1
    assert_banded_dots(compiled, target)
    check(chain, compiled, sanitize=rows == 3 and target == "avx2")


@pytest.mark.parametrize("target", X86)
def test_chain_planned_on_the_x86_targets(chain, target):
    skip_unless_host_runs(target)
    compiled = nncg.compile(chain, target=target, memory="min", verify_ir=True)
    assert band_kernels(compiled) >= 1
    assert_banded_dots(compiled, target)
    check(chain, compiled)


@pytest.mark.parametrize("toolchain", ["aarch64-neon-dotprod", "aarch64-neon", "armhf-neon"])
def test_chain_on_neon(chain, toolchain):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    compiled = nncg.compile(chain, target=tc.target, memory="min", verify_ir=True)
    assert band_kernels(compiled) >= 1
    assert_banded_dots(compiled, tc.target)
    check(chain, compiled, cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


@pytest.mark.parametrize("rows", [1, 2, 3, 8])
@pytest.mark.parametrize("toolchain", ["aarch64-neon-dotprod", "aarch64-neon"])
def test_every_band_height_on_neon(chain, toolchain, rows, monkeypatch):
    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(rows))
    compiled = nncg.compile(chain, target=tc.target, memory="min", verify_ir=True)
    assert_banded_dots(compiled, tc.target)
    check(chain, compiled, cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


@pytest.fixture(scope="module", params=sorted(MODELS))
def model(request) -> tuple[str, onnx.ModelProto]:
    return request.param, quantized(repository_model(MODELS[request.param]))


def test_models_at_each_setting(model):
    """Speed's arena is the layer bound the planner counts (1 byte an activation); min takes at most a
    third of it where there are bands to run, balanced at least halves speed's arena on the models
    with a high-resolution first stage; all bit-identical."""
    name, qdq = model
    arenas = {}
    for memory in ("speed", "balanced", "min"):
        compiled = nncg.compile(qdq, target="ansi-c", memory=memory)
        figures = memory_figures(compiled)
        arenas[memory] = compiled.arena_bytes
        if memory == "speed" and name not in FRAGMENTED:
            assert compiled.arena_bytes == figures.layer_bound_bytes
        check(qdq, compiled, feeds=1, sanitize=memory == "min" and name == "resnet8")
    bound = figures.layer_bound_bytes
    assert arenas["min"] <= arenas["balanced"] <= arenas["speed"]
    if name in HIGH_RESOLUTION:
        assert arenas["min"] <= bound / 2.5
        assert arenas["balanced"] <= arenas["speed"] / 2


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_balanced_bands_int8_convs_in_vectors(target):
    """In bands an int8 Conv runs in the target's dot products as whole: balanced bands resnet8's first
    stages on x86 too, bit-identical and vectorised. Speed runs the 3x3 layers of 16 and more input
    channels as integer Winograd, its arena the planner's count with their int16 and int32 scratch;
    balanced keeps them so in its bands, its arena the planner's count too. Every value the band kernel
    requantises, its residual adds' too, is in vectors (no scalar nncg_requantize: scalar adds in double
    arithmetic, every channel unrolled, had doubled the kernel's code past the instruction cache)."""
    skip_unless_host_runs(target)
    qdq = quantized(repository_model(MODELS["resnet8"]))
    graph, planned = lowered_graph(qdq, target), get_target(target)
    assert plan_layers(graph, "balanced", target=planned).groups
    speed = nncg.compile(qdq, target=target, memory="speed")
    balanced = nncg.compile(qdq, target=target, memory="balanced")
    assert speed.source.count(INTEGER_WINOGRAD) == 4 and "Winograd kept" in memory_figures(balanced).plan
    for compiled, memory in ((speed, "speed"), (balanced, "balanced")):  # in plan-memory's 64-byte alignment
        assert compiled.arena_bytes == -(-max(step.bytes for step in plan_steps(graph, memory, 0, planned)) // 64) * 64
    assert speed.arena_bytes > memory_figures(speed).layer_bound_bytes  # the scratch on top of the activations
    assert balanced.arena_bytes < speed.arena_bytes
    assert_banded_dots(balanced, target)
    assert "nncg_requantize(" not in band_source(balanced)
    check(qdq, balanced, feeds=1)


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_balanced_halves_resnet8_int8_arena(target):
    """Issue 18's balanced target on resnet8 int8: at least 2x less arena than speed (whose integer
    Winograd scratch counts), Winograd kept in bands on avx2: its M holds one block of output channels
    (winograd.BAND_CHUNKS)."""
    qdq = quantized(repository_model(MODELS["resnet8"]))
    speed = nncg.compile(qdq, target=target, memory="speed")
    balanced = nncg.compile(qdq, target=target, memory="balanced")
    assert balanced.arena_bytes <= speed.arena_bytes / 2


def quantize_edge_feeds(model: onnx.ModelProto, seed: int = 5) -> list[dict[str, np.ndarray]]:
    """An input that tests the input QuantizeLinear's rounding and saturation: a third of the elements
    exactly half-way between two steps (x / scale a tie in float32, as the C divides), the rest standard
    normal times 4, past the calibrated range at both ends."""
    quantize = next(n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == "x")
    constants = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    scale, zero_point = np.float32(constants[quantize.input[1]]), int(constants[quantize.input[2]])
    rng = np.random.default_rng(seed)
    shape = input_shapes(model)["x"]
    x = (rng.standard_normal(shape) * 4).astype(np.float32)
    steps = rng.integers(-zero_point - 3, 255 - zero_point + 3, shape) + 0.5
    ties = (steps * scale).astype(np.float32)
    exact = (ties / scale == steps) & (rng.random(shape) < 1 / 3)
    assert exact.sum() > x.size / 6  # most of the third are exact ties
    return [{"x": np.where(exact, ties, x)}]


VECTOR_QUOTIENTS = {"ssse3": "_mm_div_ps(", "avx2": "_mm256_div_ps("}  # how QuantizeLinear's vectors divide


@pytest.mark.parametrize("channels", [3, 4])
@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
def test_banded_input_quantize_is_bit_identical(channels, target, monkeypatch):
    """The model input's QuantizeLinear in bands: each row quantised into a planar scratch row (in vectors of 8,
    then 4, then a scalar on avx2: 13 columns), interleaved into the channels-last line buffer; ties round
    to even and values past the range saturate as onnxruntime's, at band heights 1 and 3."""
    skip_unless_host_runs(target)
    model = conv_pair_model("dense", channels)
    for rows in (1, 3):
        monkeypatch.setattr(lowering, "plan_layers", whole_chain_plan(rows))
        compiled = nncg.compile(model, target=target, memory="min", verify_ir=True)
        assert band_kernels(compiled) == 1
        if target in VECTOR_QUOTIENTS:
            assert band_source(compiled).count(VECTOR_QUOTIENTS[target]) >= channels
        result = compare(model, compiled, quantize_edge_feeds(model), sanitize=rows == 3 and target == "ansi-c")
        assert result.max_steps == 0 and result.identical == 1.0, result


@pytest.mark.parametrize("name", ["mobilenet", "robot"])
@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_balanced_bands_the_input_quantize_in_vectors(name, target):
    """A QuantizeLinear in bands quantises in vectors as it does whole (a row at a time, then interleaves
    the row into its line buffer): balanced takes the model input's QuantizeLinear into its first group on
    x86 as on ansi-c, at least halving speed's arena, bit-identical."""
    skip_unless_host_runs(target)
    qdq = quantized(repository_model(MODELS[name]))
    graph = lowered_graph(qdq, target)
    ops = {n.name: n.op for n in graph.nodes}
    groups = plan_layers(graph, "balanced", target=get_target(target)).groups
    assert groups and ops[groups[0].nodes[0]] == "QuantizeLinear"
    speed = nncg.compile(qdq, target=target, memory="speed")
    balanced = nncg.compile(qdq, target=target, memory="balanced")
    assert balanced.arena_bytes <= speed.arena_bytes / 2
    assert_banded_dots(balanced, target)
    assert VECTOR_QUOTIENTS[target] in band_source(balanced)
    check(qdq, balanced, feeds=1)


def test_ram_budget_is_met_or_refused_with_the_int8_minimum():
    qdq = quantized(repository_model(MODELS["resnet8"]))
    smallest = nncg.compile(qdq, target="ansi-c", memory="min").arena_bytes
    assert nncg.compile(qdq, target="ansi-c", ram_budget=smallest).arena_bytes <= smallest
    with pytest.raises(nncg.NncgError, match=f"smallest activation arena is {smallest} bytes"):
        nncg.compile(qdq, target="ansi-c", ram_budget=smallest - 1)


# ---------------------------------------------------------------------------- in-place depthwise

IN_PLACE_BUDGET = 40_000  # bytes: below speed's 65,536, above the in-place plans (38,912 B; 39,936 at 5x5)


@pytest.fixture(scope="module", params=[(3, (1, 1, 1, 1)), (5, (2, 1, 2, 3))], ids=["3x3", "5x5-asymmetric"])
def depthwise_peak(request) -> onnx.ModelProto:
    """tests/test_bands.py's model whose depthwise layer is the largest, quantised (1x1 QLinearConv
    8 -> 32 channels, the depthwise QLinearConv, 1x1 QLinearConv 32 -> 4)."""
    kernel, pads = request.param
    return quantized(depthwise_peak_model(kernel, list(pads)))


def depthwise_layer(graph) -> str:
    return next(n.name for n in graph.nodes if n.op == "QLinearConv" and n.attrs.group > 1)


def in_place_plan(model: onnx.ModelProto):
    """ansi-c's plan under the budget: the QuantizeLinear and first layer in bands, the depthwise in place;
    every target's in-place code is tested with this plan."""
    graph = lowered_graph(model, "ansi-c")
    plan = plan_layers(graph, "speed", IN_PLACE_BUDGET, get_target("ansi-c"))
    assert plan.in_place == {depthwise_layer(graph)}
    return plan


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512vnni"])
def test_int8_depthwise_runs_in_place_where_the_budget_needs_it(depthwise_peak, target, monkeypatch):
    """Under the budget the depthwise QLinearConv writes its output over its input (stored pad + 1
    rows down; the QuantizeLinear and first layer run in bands, their 8 KB input not live beside the
    32 KB tensor): bit-identical with onnxruntime, under the sanitizers on ansi-c."""
    skip_unless_host_runs(target)
    assert nncg.compile(depthwise_peak, target=target).arena_bytes == 65_536
    plan = in_place_plan(depthwise_peak)
    monkeypatch.setattr(lowering, "plan_layers", lambda *_: plan)
    compiled = nncg.compile(depthwise_peak, target=target, ram_budget=IN_PLACE_BUDGET, verify_ir=True)
    assert compiled.arena_bytes <= IN_PLACE_BUDGET
    check(depthwise_peak, compiled, sanitize=target == "ansi-c")


def test_int8_depthwise_runs_in_place_on_neon(depthwise_peak, monkeypatch):
    tc = TOOLCHAINS["aarch64-neon-dotprod"]
    require(missing_tools(tc))
    plan = in_place_plan(depthwise_peak)
    monkeypatch.setattr(lowering, "plan_layers", lambda *_: plan)
    compiled = nncg.compile(depthwise_peak, target=tc.target, ram_budget=IN_PLACE_BUDGET, verify_ir=True)
    assert compiled.arena_bytes <= IN_PLACE_BUDGET
    check(depthwise_peak, compiled, cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


def test_int8_depthwise_stays_apart_where_it_does_not_pay(depthwise_peak):
    graph = lowered_graph(depthwise_peak, "ssse3")
    assert not plan_layers(graph, "speed", 70_000, get_target("ssse3")).in_place  # speed fits
    assert not plan_layers(graph, "min", 0, get_target("ssse3")).in_place  # bands take less
