"""Band execution (nncg/lowering/bands.py, stream.py, band_plan.py): chains of layers over bands of rows
with line buffers, the memory settings and the RAM budget, checked against onnxruntime."""

from pathlib import Path

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, verify_on
from helpers import check_against_onnxruntime, nncg_onnx, onnx_model, weights
from onnx import helper

import nncg
from nncg.backends import BACKENDS, get_target
from nncg.frontend import import_onnx
from nncg.lowering import band_plan
from nncg.lowering.band_costs import COSTS
from nncg.lowering.band_plan import layer_bound_bytes, plan_layers
from nncg.lowering.bands import BandGroup, geometry
from nncg.passes import PassManager, default_pipeline
from nncg.verify_layers import verify_per_layer

ROOT = Path(__file__).parent.parent
ROBOT = ROOT / "examples" / "robot.onnx"
PEDESTRIAN = ROOT / "examples" / "pedestrian.onnx"
BALL = ROOT / "examples" / "ball.onnx"
RESNET8 = ROOT / "benchmarks" / "models" / "resnet8.onnx"
MOBILENET = ROOT / "benchmarks" / "models" / "mobilenet_v1_025.onnx"
X86 = ("ssse3", "avx2", "avx512")


def lowered_graph(model, target: str = "ssse3"):
    """The graph as lower receives it in the default pipeline."""
    tgt = get_target(target)
    return PassManager(default_pipeline(tgt).split(",lower")[0], tgt).run(import_onnx(model))


def band_kernels(compiled) -> int:
    return compiled.source.count(": Band */")


# ---------------------------------------------------------------------------- a chain of every kind


def chain_model() -> onnx.ModelProto:
    """Conv 3x3 -> depthwise 3x3 stride 2 -> dilated Conv -> MaxPool 3 stride 2 padded -> grouped Conv
    with a fused residual (Add) -> AveragePool counting the padding: one chain of every window kind."""
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["a"], ["a_r"]),
        helper.make_node("Conv", ["a_r", "w2"], ["b"], group=8, strides=[2, 2], pads=[1, 0, 1, 1]),
        helper.make_node("Conv", ["b", "w3"], ["c"], dilations=[2, 2], pads=[2, 2, 2, 2]),
        helper.make_node("MaxPool", ["c"], ["d"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["d", "w4"], ["e"], group=2, pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["e", "d"], ["f"]),
        helper.make_node("AveragePool", ["f"], ["y"], kernel_shape=[2, 2], pads=[1, 1, 0, 0], count_include_pad=1),
    ]
    init = {
        "w1": weights(8, 3, 3, 3),
        "b1": weights(8),
        "w2": weights(8, 1, 3, 3),
        "w3": weights(12, 8, 3, 3),
        "w4": weights(12, 6, 3, 3),
    }
    return onnx_model(nodes, inputs={"x": [1, 3, 29, 22]}, outputs={"y": [1, 12, 8, 6]}, initializers=init)


@pytest.mark.parametrize("target", ["ansi-c", *X86])
@pytest.mark.parametrize("memory", ["balanced", "min"])
def test_chain_of_every_window_kind_runs_in_bands(target, memory):
    model = chain_model()
    compiled = nncg.compile(model, target=target, memory=memory, verify_ir=True)
    assert band_kernels(compiled) >= 1
    check_against_onnxruntime(model, compiled)


@pytest.mark.parametrize("rows", [1, 2, 3, 8])
def test_every_band_height_gives_the_same_outputs(rows, monkeypatch):
    model = chain_model()
    graph = lowered_graph(model, "ansi-c")
    assert geometry(graph, BandGroup(tuple(n.name for n in graph.nodes), rows)) is not None
    monkeypatch.setattr(band_plan, "BAND_ROWS", (rows,))
    assert {group.rows for group in plan_layers(graph, "min").groups} == {rows}
    compiled = nncg.compile(model, target="ansi-c", memory="min")
    check_against_onnxruntime(model, compiled, sanitize=rows == 3)


def random_chain(seed: int) -> onnx.ModelProto | None:
    """2 to 5 layers drawn from Conv (kernel 1-4, stride 1-2, dilation 1-2, asymmetric padding),
    depthwise Conv, a 3x3 Conv with a residual Add, Relu, MaxPool (dilated) and AveragePool (padding
    counted or not); None when the image shrinks below two rows."""
    rng = np.random.default_rng(seed)
    shape = [1, int(rng.integers(1, 6)), int(rng.integers(12, 40)), int(rng.integers(5, 20))]
    image = list(shape)
    nodes, init, x = [], {}, "x"
    for i in range(int(rng.integers(2, 6))):
        kind = str(rng.choice(["conv", "conv", "depthwise", "max", "average", "residual"]))
        k, s = int(rng.integers(1, 5)), int(rng.integers(1, 3))
        d = int(rng.integers(1, 3)) if k > 1 else 1
        pads = [int(rng.integers(0, k)) for _ in range(4)]
        y, channels = f"t{i}", shape[1]
        if kind == "residual":
            k, s, d, pads = 3, 1, 1, [1, 1, 1, 1]
        if kind in ("conv", "depthwise", "residual"):
            channels = int(rng.integers(1, 9)) if kind == "conv" else shape[1]
            group = shape[1] if kind == "depthwise" else 1
            init[f"w{i}"] = weights(channels, shape[1] // group, k, k)
            conv = dict(group=group, strides=[s, s], dilations=[d, d], pads=pads)
            nodes.append(helper.make_node("Conv", [x, f"w{i}"], [y], **conv))
            if kind == "residual":
                nodes.append(helper.make_node("Add", [y, x], [y + "_add"]))
                y += "_add"
            if rng.random() < 0.5:
                nodes.append(helper.make_node("Relu", [y], [y + "_relu"]))
                y += "_relu"
        else:
            pads = [min(p, k - 1) for p in pads]
            pool = dict(kernel_shape=[k, k], strides=[s, s], pads=pads)
            if kind == "average":
                pool["count_include_pad"] = int(rng.integers(0, 2))
            else:
                pool["dilations"] = [d, d]
            nodes.append(helper.make_node("MaxPool" if kind == "max" else "AveragePool", [x], [y], **pool))
        span = (k - 1) * d + 1
        shape = [1, channels, *((shape[2 + a] + pads[a] + pads[2 + a] - span) // s + 1 for a in (0, 1))]
        if shape[2] < 2 or shape[3] < 1:
            return None
        x = y
    return onnx_model(nodes, inputs={"x": image}, outputs=[x], initializers=init)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 5, 7, 8, 9, 10, 12])
def test_random_chains_run_in_bands_and_match_onnxruntime(seed):
    model = random_chain(seed)
    compiled = nncg.compile(model, target="ansi-c", memory="min", verify_ir=True)
    assert band_kernels(compiled) >= 1
    check_against_onnxruntime(model, compiled, sanitize=seed < 2)


def test_geometry_refuses_a_tensor_read_outside_the_group():
    graph = lowered_graph(ROBOT)
    names = [n.name for n in graph.nodes]
    assert geometry(graph, BandGroup(tuple(names[:2]), 1)) is not None
    assert geometry(graph, BandGroup((names[0], names[2]), 1)) is None  # not consecutive
    assert geometry(graph, BandGroup(tuple(names[:2]), 0)) is None


def test_layers_before_a_stride_run_nested_with_short_line_buffers():
    """mobilenet's stem..block4_dw: steps 4, 2, 1 become three levels, each run making one row, so a
    3x3 window's input keeps 3 lines and a 1x1's keeps 1, whatever the level."""
    graph = lowered_graph(MOBILENET)
    names = [n.name for n in graph.nodes]
    geo = geometry(graph, BandGroup(tuple(names[: names.index("block4_dw_conv") + 1]), 1))
    assert geo.reps == (1, 2, 2)
    assert {v: (r.level, r.step, r.lines) for v, r in geo.rows.items()} == {
        "block4.dw.relu6": (0, 1, 0),
        "block3.pw.relu6": (1, 1, 3),
        "block3.dw.relu6": (1, 1, 1),
        "block2.pw.relu6": (1, 1, 3),
        "block2.dw.relu6": (1, 1, 1),
        "block1.pw.relu6": (2, 1, 3),
        "block1.dw.relu6": (2, 1, 1),
        "stem.relu6": (2, 1, 3),
    }


# ---------------------------------------------------------------------------- the models


MODEL_TARGETS = {  # (model, largest arena at --memory min the issue asks for)
    "robot": (ROBOT, 48_000),
    "pedestrian": (PEDESTRIAN, 16_384),
    "resnet8": (RESNET8, 65_536),
    "mobilenet": (MOBILENET, 73_728),
}


@pytest.mark.parametrize("target", ["ansi-c", "avx2"])
@pytest.mark.parametrize("model", sorted(MODEL_TARGETS))
def test_models_at_min_match_onnxruntime_below_the_layer_bound(model, target):
    path, goal = MODEL_TARGETS[model]
    compiled = nncg.compile(path, target=target, memory="min")
    bound = layer_bound_bytes(lowered_graph(path, target))
    assert compiled.arena_bytes < bound / 2
    assert compiled.arena_bytes <= goal
    check_against_onnxruntime(onnx.load(path), compiled, sanitize=target == "ansi-c" and model == "robot")


@pytest.mark.parametrize("target", X86)
def test_robot_balanced_and_min_on_every_x86_target(target):
    for memory in ("balanced", "min"):
        compiled = nncg.compile(ROBOT, target=target, memory=memory)
        check_against_onnxruntime(onnx.load(ROBOT), compiled)


def test_resnet8_min_under_the_sanitizers():
    compiled = nncg.compile(RESNET8, target="ssse3", memory="min")
    check_against_onnxruntime(onnx.load(RESNET8), compiled, sanitize=True)


# ---------------------------------------------------------------------------- in-place depthwise


def depthwise_peak_model(kernel: int, pads: list[int]) -> onnx.ModelProto:
    """1x1 Conv 8 -> 32 channels, a depthwise Conv, 1x1 Conv 32 -> 4: the depthwise layer's input
    and output side by side are the largest layer (the model's input and output are not the arena's)."""
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["a"]),
        helper.make_node("Relu", ["a"], ["a_r"]),
        helper.make_node("Conv", ["a_r", "w2", "b2"], ["b"], group=32, pads=pads),
        helper.make_node("Relu", ["b"], ["b_r"]),
        helper.make_node("Conv", ["b_r", "w3"], ["y"]),
    ]
    init = {
        "w1": weights(32, 8, 1, 1),
        "b1": weights(32),
        "w2": weights(32, 1, kernel, kernel),
        "b2": weights(32),
        "w3": weights(4, 32, 1, 1),
    }
    return onnx_model(nodes, inputs={"x": [1, 8, 32, 32]}, outputs={"y": [1, 4, 32, 32]}, initializers=init)


IN_PLACE_BUDGET = 160_000  # bytes: below speed's 262,144, above the in-place plan's 155,648


@pytest.mark.parametrize("target", ["ansi-c", *X86])
@pytest.mark.parametrize(("kernel", "pads"), [(3, [1, 1, 1, 1]), (5, [2, 1, 2, 3])])
def test_depthwise_runs_in_place_where_the_budget_needs_it(target, kernel, pads):
    """The fastest plan under the budget writes the depthwise output over its input (stored pad + 1
    rows down): every layer still computed whole, 262,144 -> 155,648 B, the same outputs."""
    model = depthwise_peak_model(kernel, pads)
    speed = nncg.compile(model, target=target)
    compiled = nncg.compile(model, target=target, ram_budget=IN_PLACE_BUDGET)
    graph = lowered_graph(model, target)
    assert band_plan.plan_layers(graph, "speed", IN_PLACE_BUDGET, get_target(target)).in_place == {graph.nodes[1].name}
    assert band_kernels(compiled) == 0
    assert (speed.arena_bytes, compiled.arena_bytes) == (262_144, 155_648 + 1024 * 4 * (pads[0] - 1))
    check_against_onnxruntime(model, compiled, sanitize=target == "ansi-c")


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf-neon"])
def test_depthwise_runs_in_place_on_neon(toolchain):
    tc = TOOLCHAINS[toolchain]
    missing = missing_tools(tc)
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed")  # test_cross_targets fails CI for a missing one
    model = depthwise_peak_model(3, [1, 1, 1, 1])
    compiled = nncg.compile(model, target="neon", ram_budget=IN_PLACE_BUDGET)
    assert compiled.arena_bytes == 155_648
    report = verify_on(tc, model, compiled)
    assert report.ok, report.format()


def test_in_place_depthwise_reads_back_per_layer_and_is_left_out_where_it_does_not_pay():
    model = depthwise_peak_model(3, [1, 1, 1, 1])
    report = verify_per_layer(model, "ansi-c", ram_budget=IN_PLACE_BUDGET, sanitize=True)
    assert report.ok, report.format()
    graph = lowered_graph(model, "ssse3")
    assert not band_plan.plan_layers(graph, "speed", 300_000, get_target("ssse3")).in_place  # fits without it
    assert not band_plan.plan_layers(graph, "speed", 0, get_target("ssse3")).in_place


def test_a_plan_runs_no_layer_both_in_bands_and_in_place():
    graph = lowered_graph(depthwise_peak_model(3, [1, 1, 1, 1]), "ssse3")
    for memory in band_plan.MEMORY_MODES:
        for budget in (0, IN_PLACE_BUDGET, 100_000):
            plan = plan_layers(graph, memory, budget, get_target("ssse3"))
            assert not plan.in_place & {name for group in plan.groups for name in group.nodes}


# ---------------------------------------------------------------------------- the planner and options


def test_speed_is_the_default_and_plans_nothing():
    graph = lowered_graph(ROBOT)
    assert plan_layers(graph) == band_plan.BandPlan()
    assert nncg.compile(ROBOT, target="ssse3").source == nncg.compile(ROBOT, target="ssse3", memory="speed").source


def _plans(graph, target):
    """(bytes, estimated latency) of the fastest plan under every memory bound, and speed's."""
    steps = band_plan.candidate_steps(graph, band_plan.StepCosts(get_target(target)))
    plans = (band_plan._cheapest(len(graph.nodes), steps, bound) for bound in sorted({s.bytes for s in steps}))
    speed = band_plan.plan_steps(graph, "speed", 0, get_target(target))
    return [_figures(p) for p in plans if p], _figures(speed)


def _figures(plan):
    return max(s.bytes for s in plan), sum(s.cost for s in plan)


@pytest.mark.parametrize("target", ["ansi-c", "ssse3", "avx2"])
@pytest.mark.parametrize("model", [ROBOT, PEDESTRIAN, RESNET8, MOBILENET])
def test_balanced_is_the_fastest_plan_with_half_the_arena_within_the_latency_bound(model, target):
    """Issue 18: balanced takes the fastest plan with at most half of speed's memory when its estimated
    latency is within 1.3x of speed's; when none is, the smallest memory within 1.3x."""
    graph = lowered_graph(model, target)
    plans, (speed_bytes, speed_time) = _plans(graph, target)
    fast = [(size, time) for size, time in plans if time <= speed_time * band_plan.BALANCED_LATENCY]
    cut = [(time, size) for size, time in fast if size <= speed_bytes / band_plan.BALANCED_CUT]
    size, time = _figures(band_plan.plan_steps(graph, "balanced", 0, get_target(target)))
    assert time <= speed_time * band_plan.BALANCED_LATENCY
    if cut:
        assert size <= speed_bytes / band_plan.BALANCED_CUT and time == min(cut)[0]
    else:
        assert size == min(f for f, _ in fast)


def test_balanced_halves_the_arena_where_a_plan_is_fast_enough():
    """mobilenet (no Winograd): bands cost little, so balanced has at most half of speed's arena."""
    for target in ("ssse3", "avx2"):
        speed = nncg.compile(MOBILENET, target=target).arena_bytes
        compiled = nncg.compile(MOBILENET, target=target, memory="balanced")
        assert compiled.arena_bytes <= speed / 2
    check_against_onnxruntime(onnx.load(MOBILENET), compiled)


def test_plans_are_priced_for_the_target():
    """ball: bands cost less on scalar C than on avx2, so balanced cuts deeper there; compile hands
    lower its target, and the report names the plan priced for it."""
    plans = {t: plan_layers(lowered_graph(BALL, t), "balanced", 0, get_target(t)).groups for t in ("ansi-c", "avx2")}
    assert plans["ansi-c"] != plans["avx2"]
    for target, groups in plans.items():
        compiled = nncg.compile(BALL, target=target, memory="balanced")
        assert nncg.compiler.memory_figures(compiled).plan == band_plan.describe_plan(groups)


def test_a_residual_conv_written_over_its_residual_counts_once():
    """resnet8: each residual Conv writes over its dying residual (plan-memory), so the layer bound is
    one input + output pair (issue 18's 131,072 B) and speed's estimate is its real arena."""
    graph = lowered_graph(RESNET8, "avx2")
    assert layer_bound_bytes(graph) == 131_072
    _, (speed_bytes, _) = _plans(graph, "avx2")
    assert speed_bytes == nncg.compile(RESNET8, target="avx2").arena_bytes


def test_settings_order_the_arena():
    arenas = [nncg.compile(ROBOT, target="ssse3", memory=m).arena_bytes for m in ("speed", "balanced", "min")]
    assert arenas[0] > arenas[1] > arenas[2]


def test_budget_is_met_at_least_work():
    smallest = nncg.compile(ROBOT, target="ssse3", memory="min").arena_bytes
    for budget in (60_000, 120_000):
        compiled = nncg.compile(ROBOT, target="ssse3", ram_budget=budget)
        assert smallest <= compiled.arena_bytes <= budget
        check_against_onnxruntime(onnx.load(ROBOT), compiled)


def test_budget_of_exactly_the_minimum_is_met():
    smallest = nncg.compile(PEDESTRIAN, target="ansi-c", memory="min").arena_bytes
    assert nncg.compile(PEDESTRIAN, target="ansi-c", ram_budget=smallest).arena_bytes == smallest


def test_budget_below_the_minimum_is_refused_with_the_smallest_figure():
    smallest = nncg.compile(PEDESTRIAN, target="ansi-c", memory="min").arena_bytes
    with pytest.raises(nncg.NncgError, match=f"smallest activation arena is {smallest} bytes") as error:
        nncg.compile(PEDESTRIAN, target="ansi-c", ram_budget=smallest - 1)
    assert "\n" not in str(error.value)


def test_banded_output_is_deterministic():
    first = nncg.compile(MOBILENET, target="avx2", memory="min")
    second = nncg.compile(MOBILENET, target="avx2", memory="min")
    assert first.source == second.source and first.header == second.header
    assert "lower{memory=min}" in first.source.splitlines()[0]


@pytest.mark.parametrize("bad", [{"memory": "tiny"}, {"ram_budget": 0}, {"ram_budget": "1k"}])
def test_bad_memory_arguments_are_refused(bad):
    with pytest.raises(nncg.NncgError):
        nncg.compile(ROBOT, **bad)


def test_cli_refuses_an_unmet_budget_in_one_line_and_leaves_the_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("kept")
    result = nncg_onnx(ROBOT, "--target", "ansi-c", "-o", tmp_path, "--ram-budget", "1000")
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "smallest activation arena is" in result.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_cli_memory_min_writes_the_smaller_arena_in_the_header(tmp_path):
    result = nncg_onnx(ROBOT, "--target", "ansi-c", "-o", tmp_path, "--memory", "min")
    assert result.returncode == 0, result.stderr
    arena = nncg.compile(ROBOT, target="ansi-c", memory="min").arena_bytes
    assert f"#define ROBOT_ARENA_BYTES {arena}\n" in (tmp_path / "robot.h").read_text()


def test_every_backend_has_its_band_costs():
    """A target missing from band_costs.COSTS would be priced as a 4-lane one without anyone noticing."""
    assert set(BACKENDS) <= set(COSTS)
