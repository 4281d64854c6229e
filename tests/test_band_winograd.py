"""Winograd F(2x2, 3x3) inside a group of bands (nncg/lowering/winograd.py lower_winograd_band,
bands.py, stream.py): every plan checked against onnxruntime on every target."""

import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, verify_on
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper
from test_bands import PEDESTRIAN, RESNET8, ROBOT, lowered_graph

import nncg
import nncg.lowering
from nncg.backends import get_target
from nncg.ir.kinds import ConvAlgorithm
from nncg.lowering import band_plan
from nncg.lowering.bands import BandGroup, geometry


def winograd_chain() -> onnx.ModelProto:
    """A direct 3x3 Conv (4 input channels), three 3x3 Convs the winograd pass takes (one adding a
    residual), a 2x2 MaxPool between: odd heights and widths, so border tiles and a last tile with one
    output row come up."""
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["a_r"]),
        helper.make_node("Conv", ["a_r", "w2", "b2"], ["b"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["b"], ["b_r"]),
        helper.make_node("Conv", ["b_r", "w3"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c", "a_r"], ["c_a"]),
        helper.make_node("MaxPool", ["c_a"], ["d"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node("Conv", ["d", "w4", "b4"], ["y"], pads=[1, 1, 1, 1]),
    ]
    init = {
        "w1": weights(8, 4, 3, 3),
        "b1": weights(8),
        "w2": weights(12, 8, 3, 3),
        "b2": weights(12),
        "w3": weights(8, 12, 3, 3),
        "w4": weights(16, 8, 3, 3),
        "b4": weights(16),
    }
    return onnx_model(nodes, inputs={"x": [1, 4, 23, 19]}, outputs={"y": [1, 16, 11, 9]}, initializers=init)


# (first node, last node, rows) per group, node indices into the lowered graph's four Convs and pool
PLANS = {
    "all-2": ((0, 4, 2),),
    "all-4": ((0, 4, 4),),
    "all-8": ((0, 4, 8),),
    "split": ((0, 2, 2), (3, 4, 4)),
    "odd-ahead": ((1, 3, 2),),
}


def compiled_with_plan(monkeypatch, model, target: str, plan) -> nncg.CompiledModel:
    graph = lowered_graph(model, target)
    names = [n.name for n in graph.nodes]
    groups = tuple(BandGroup(tuple(names[i : j + 1]), rows, winograd=True) for i, j, rows in plan)
    for group in groups:
        assert geometry(graph, group).winograd, group
    monkeypatch.setattr(nncg.lowering, "plan_layers", lambda *args, **kwargs: band_plan.BandPlan(groups))
    return nncg.compile(model, target=target, verify_ir=True)


def test_the_chain_has_winograd_layers():
    graph = lowered_graph(winograd_chain())
    kinds = [(n.op, getattr(n.attrs, "algorithm", None)) for n in graph.nodes]
    assert kinds == [
        ("Conv", ConvAlgorithm.DIRECT),
        ("Conv", ConvAlgorithm.WINOGRAD),
        ("Conv", ConvAlgorithm.WINOGRAD),
        ("MaxPool", None),
        ("Conv", ConvAlgorithm.WINOGRAD),
    ]


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2", "avx512"])
@pytest.mark.parametrize("plan", sorted(PLANS))
def test_winograd_in_bands_matches_onnxruntime(monkeypatch, target, plan):
    model = winograd_chain()
    compiled = compiled_with_plan(monkeypatch, model, target, PLANS[plan])
    assert compiled.source.count(": Band */") == len(PLANS[plan])
    assert "v_" in compiled.source  # a Winograd scratch buffer
    check_against_onnxruntime(model, compiled, sanitize=target == "ansi-c" and plan in ("all-2", "odd-ahead"))


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf-neon"])
def test_winograd_in_bands_on_neon(monkeypatch, toolchain):
    tc = TOOLCHAINS[toolchain]
    missing = missing_tools(tc)
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed")  # test_cross_targets fails CI for a missing one
    model = winograd_chain()
    for plan in ("all-2", "split"):
        report = verify_on(tc, model, compiled_with_plan(monkeypatch, model, "neon", PLANS[plan]))
        assert report.ok, report.format()


def test_winograd_stays_only_where_rows_advance_in_whole_tiles():
    graph = lowered_graph(winograd_chain())
    names = tuple(n.name for n in graph.nodes)
    one_row = geometry(graph, BandGroup(names, 1, winograd=True))
    assert one_row.winograd == ()  # one row a run (before the pool: two runs nested in a band)
    two_rows = geometry(graph, BandGroup(names, 2, winograd=True))
    assert two_rows.winograd == (names[1], names[2], names[4])
    for name in two_rows.winograd:
        rows = two_rows.rows[graph.nodes[names.index(name)].outputs[0]]
        assert rows.step % 2 == 0 and rows.ahead % 2 == 0
    assert geometry(graph, BandGroup(names, 2)).winograd == ()  # not asked: every Conv direct


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
@pytest.mark.parametrize("model", [ROBOT, PEDESTRIAN, RESNET8])
def test_balanced_halves_the_arena_of_winograd_models(model, target):
    """Issue 18's balanced target in memory (the latency is the memory suite's to measure): at least
    2x less arena than speed, by groups that keep Winograd."""
    speed = nncg.compile(model, target=target)
    compiled = nncg.compile(model, target=target, memory="balanced")
    assert 2 * compiled.arena_bytes <= speed.arena_bytes
    graph = lowered_graph(model, target)
    assert any(g.winograd for g in band_plan.plan_layers(graph, "balanced", 0, get_target(target)).groups)
    if target == "avx2":
        check_against_onnxruntime(onnx.load(model), compiled)


def test_winograd_in_bands_is_deterministic():
    first = nncg.compile(RESNET8, target="avx2", memory="balanced")
    second = nncg.compile(RESNET8, target="avx2", memory="balanced")
    assert first.source == second.source and first.header == second.header
