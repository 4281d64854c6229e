"""The differential fuzzer (nncg.fuzz): its generator (valid, deterministic, covering every operator
NNCG converts), its shrinker, its runner's outcome classes, a fixed-seed smoke run on every host
target, and the minimal models of the bugs it found (tests/fuzz_regressions/)."""

import json
from collections import Counter
from pathlib import Path

import onnx
import pytest
from helpers import skip_unless_host_runs
from onnx import TensorProto, helper

from nncg.frontend.ops import CONVERTERS
from nncg.fuzz.__main__ import main
from nncg.fuzz.build import build, value_shapes
from nncg.fuzz.case import WINOGRAD_NODE_BYTES, Case, evaluate, make_case, size_limit
from nncg.fuzz.generator import generate
from nncg.fuzz.options import CROSS, Options
from nncg.fuzz.recipe import Recipe, Step
from nncg.fuzz.runner import run_case, validate
from nncg.fuzz.shrinker import shrink
from nncg.fuzz.ties import has_nearest_resize_tie
from nncg.host_cpu import host_targets

REGRESSIONS = Path(__file__).resolve().parent / "fuzz_regressions"
ALL_TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
SMOKE_SEED = 2025
SMOKE_CASES = 12  # per target
EXPECTED = ("pass", "refused-option")  # refused-option: a pass refusing an illegal per-layer choice


def models(seeds):
    for seed in seeds:
        yield build(generate(seed))


# ---------------------------------------------------------------------------- generator


def test_generated_graphs_are_valid():
    problems = {}
    for seed in range(40):
        recipe = generate(seed)
        shapes = value_shapes(recipe)
        problem = validate(build(recipe), {v: shapes[v] for v in recipe.outputs})
        if problem:
            problems[seed] = problem
    assert not problems, problems


def test_generator_is_deterministic_by_seed():
    first = [build(generate([7, i])).SerializeToString() for i in range(5)]
    again = [build(generate([7, i])).SerializeToString() for i in range(5)]
    assert first == again
    assert len(set(first)) == 5
    assert generate(3).key() == Recipe.from_json(json.loads(json.dumps(generate(3).to_json()))).key()


def _attribute_values(model: onnx.ModelProto) -> set[tuple[str, str, object]]:
    out = set()
    for node in model.graph.node:
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.TENSOR:  # Constant's value
                continue
            value = helper.get_attribute_value(attr)
            value = value.decode() if isinstance(value, bytes) else tuple(value) if isinstance(value, list) else value
            out.add((node.op_type, attr.name, value))
    return out


def test_generator_covers_every_operator_and_attribute():
    seen_ops: Counter = Counter()
    attrs: set = set()
    conv_ranks, depthwise = set(), 0
    for model in models(range(400)):
        seen_ops.update(node.op_type for node in model.graph.node)
        attrs |= _attribute_values(model)
        weights = {t.name: t.dims for t in model.graph.initializer}
        for node in model.graph.node:
            if node.op_type == "Conv" and node.input[1] in weights:
                conv_ranks.add(len(weights[node.input[1]]))
                depthwise += any(
                    a.name == "group" and a.i > 1 and weights[node.input[1]][1] == 1 for a in node.attribute
                )
    # The fuzzer draws float models, checked to a float tolerance; the int8 operators are checked to the
    # bit by tests/test_int8*.py instead.
    int8_modules = ("ops_quantized", "ops_qsoftmax", "ops_qlookup", "ops_qbinary", "ops_qconcat", "ops_integer")
    int8 = {name for name, convert in CONVERTERS.items() if convert.__module__.split(".")[-1] in int8_modules}
    supported = set(CONVERTERS) - {"Constant"} - int8
    assert supported <= set(seen_ops), f"never generated: {sorted(supported - set(seen_ops))}"
    assert {3, 4, 5} <= conv_ranks and depthwise > 0  # 1-D, 2-D, 3-D convolutions
    wanted = {("Conv", "auto_pad", mode) for mode in ("SAME_UPPER", "SAME_LOWER", "VALID")}
    wanted |= {
        ("Resize", "coordinate_transformation_mode", mode)
        for mode in ("half_pixel", "asymmetric", "pytorch_half_pixel", "align_corners", "tf_half_pixel_for_nn")
    }
    wanted |= {
        ("Resize", "nearest_mode", mode) for mode in ("round_prefer_floor", "round_prefer_ceil", "floor", "ceil")
    }
    wanted |= {("Resize", "mode", "linear"), ("Upsample", "mode", "linear")}
    wanted |= {("Pad", "mode", mode) for mode in ("reflect", "edge", "wrap")}
    wanted |= {("MaxPool", "ceil_mode", 1), ("AveragePool", "count_include_pad", 1)}
    wanted |= {("ConvTranspose", "auto_pad", "SAME_UPPER"), ("Gemm", "transA", 1), ("Gemm", "transB", 1)}
    wanted |= {("Gelu", "approximate", "tanh")}
    assert wanted <= attrs, f"never generated: {sorted(wanted - attrs)}"
    assert any(op == "ConvTranspose" and name == "output_shape" for op, name, _ in attrs)
    assert any(op in ("MaxPool", "Conv") and name == "dilations" and max(v) > 1 for op, name, v in attrs)
    assert any(op in ("ArgMax", "ArgMin") and name == "select_last_index" and v == 1 for op, name, v in attrs)
    assert any(op.startswith("Reduce") and name == "keepdims" and v == 0 for op, name, v in attrs)
    assert any(op.startswith("Reduce") and name == "noop_with_empty_axes" and v == 1 for op, name, v in attrs)
    assert any(op == "LayerNormalization" and name == "axis" and v != -1 for op, name, v in attrs)


# ---------------------------------------------------------------------------- shrinker


def _synthetic_recipe() -> Recipe:
    steps = [
        Step("Unary", ("x",), ("v0",), {"op": "Relu"}),
        Step("Conv", ("v0",), ("v1",), {"seed": 1, "c_out": 16, "kernel": [3, 3], "pads": [1, 1, 1, 1], "bias": True}),
        Step("Conv", ("v1",), ("v2",), {"seed": 2, "c_out": 5, "kernel": [3, 3], "dilations": [2, 2]}),
        Step("Unary", ("v2",), ("v3",), {"op": "Tanh"}),
        Step("MaxPool", ("v1",), ("v4",), {"kernel": [2, 2], "strides": [2, 2]}),
    ]
    return Recipe(13, {"x": (1, 7, 9, 9)}, tuple(steps), ("v3", "v4"))


def test_shrinker_reduces_to_the_step_the_predicate_needs():
    def fails(recipe: Recipe, options: Options) -> bool:
        # the "bug": a dilated Conv on at least 3 channels, compiled for avx2
        try:
            shapes = value_shapes(recipe)
        except Exception:
            return False
        return options.target == "avx2" and any(
            s.op == "Conv" and max(s.params.get("dilations", [1])) > 1 and shapes[s.inputs[0]][1] >= 3
            for s in recipe.steps
        )

    options = Options(target="avx2", unroll="1", weights="bin", sanitize=True)
    shrunk = shrink(_synthetic_recipe(), options, fails)
    assert fails(shrunk.recipe, shrunk.options)
    assert [s.op for s in shrunk.recipe.steps] == ["Conv"]
    conv = shrunk.recipe.steps[0]
    assert conv.params["dilations"] == [2, 2] and "pads" not in conv.params and "bias" not in conv.params
    assert list(shrunk.recipe.inputs.values())[0][1] == 3  # channels shrunk to the predicate's bound
    assert shrunk.options == Options(target="avx2")


def test_shrinker_stops_at_its_evaluation_budget():
    calls = []
    shrunk = shrink(_synthetic_recipe(), Options(), lambda r, o: calls.append(1) is None, max_evaluations=5)
    assert len(calls) == shrunk.evaluations == 5


# ---------------------------------------------------------------------------- runner


def _single_node_model(op: str, shape=(1, 3, 4, 4), **attrs) -> onnx.ModelProto:
    """An elementwise op on one input (the output has the input's shape)."""
    graph = helper.make_graph(
        [helper.make_node(op, ["x"], ["y"], **attrs)],
        "m",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    return model


def test_runner_outcome_classes():
    assert run_case(_single_node_model("Relu"), Options()).kind == "pass"
    assert run_case(_single_node_model("Relu"), Options(), size_limit=10).kind == "code-size"
    refused = run_case(_single_node_model("Cos"), Options())  # onnxruntime runs Cos, NNCG does not convert it
    assert refused.kind == "refused" and "Cos" in refused.message
    bad_block = Options(layers={"register-block": {"no_such_layer": [2, 2]}})
    assert run_case(_single_node_model("Relu"), bad_block).kind == "refused-option"
    assert validate(_single_node_model("Relu")) is None
    assert "onnxruntime" in validate(_single_node_model("LRN", size=2))  # onnxruntime takes odd sizes only


def test_size_limit_tracks_the_unroll_setting():
    model = _single_node_model("Relu")
    assert size_limit(model, Options(unroll="none")) < size_limit(model, Options(unroll="0"))
    assert size_limit(model, Options(unroll="0", code_budget=None)) is None


def test_size_limit_counts_a_layer_forced_to_winograd():
    """The winograd pass takes any 3x3 conv a per-layer choice names, not only those it would pick
    (fuzz-found: one input channel forced to Winograd outgrew the limit of a direct conv)."""
    model = _single_node_model("Relu")
    model.graph.node[0].name = "layer"
    forced = Options(unroll="none", layers={"winograd": {"layer": True}})
    assert size_limit(model, forced) - size_limit(model, Options(unroll="none")) == WINOGRAD_NODE_BYTES


# ---------------------------------------------------------------------------- smoke run


@pytest.mark.parametrize("target", ALL_TARGETS)
def test_smoke_run_passes(target):
    if target not in host_targets():
        pytest.skip(f"the host CPU cannot run {target} code")
    failures = {}
    first = ALL_TARGETS.index(target) * SMOKE_CASES  # other graphs for each target
    for index in range(first, first + SMOKE_CASES):
        case = make_case(SMOKE_SEED, index, [target], sanitize_fraction=0.1)
        assert isinstance(case, Case), f"case {index}: the generator made an invalid graph: {case}"
        outcome = evaluate(case.recipe, case.options)
        if outcome.kind not in EXPECTED:
            failures[index] = f"{outcome.kind}: {outcome.message[:300]} ({case.options.command()})"
    assert not failures, failures


def test_cli_prints_counts_and_is_deterministic(tmp_path, capsys):
    args = ["--count", "3", "--seed", "5", "--targets", "ansi-c", "--jobs", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    first = capsys.readouterr().out
    assert main(args) == 0
    second = capsys.readouterr().out
    counts = [line.split() for line in first.splitlines() if line.startswith("  ")]
    assert sum(int(n) for _, n in counts) == 3
    assert counts == [line.split() for line in second.splitlines() if line.startswith("  ")]


# ---------------------------------------------------------------------------- regressions


def _regressions():
    for folder in sorted(p for p in REGRESSIONS.iterdir() if p.is_dir()):
        record = json.loads((folder / "case.json").read_text())
        marks = [pytest.mark.xfail(strict=True, reason=record["xfail"])] if "xfail" in record else []
        yield pytest.param(folder, id=folder.name, marks=marks)


@pytest.mark.parametrize("folder", _regressions())
def test_fuzz_regression(folder):
    record = json.loads((folder / "case.json").read_text())
    model = onnx.load(folder / "model.onnx")
    assert validate(model) is None, "the saved model must be valid for onnxruntime"
    options = Options.from_json(record["options"])
    if options.target not in CROSS:
        skip_unless_host_runs(options.target)  # the saved case's target: x86 code runs on this CPU
    outcome = run_case(model, options, size_limit(model, options))
    assert outcome.kind == "pass", f"{record['description']}: {outcome.kind}: {outcome.message}"


def test_regression_models_match_their_recipes():
    for folder in sorted(p for p in REGRESSIONS.iterdir() if p.is_dir()):
        record = json.loads((folder / "case.json").read_text())
        rebuilt = build(Recipe.from_json(record["recipe"]))
        saved = onnx.load(folder / "model.onnx")
        assert rebuilt.SerializeToString() == saved.SerializeToString(), folder.name


def test_every_target_builds_each_graph_for_each_target():
    targets = ["ansi-c", "ssse3", "avx2"]
    cases = [make_case(5, i, targets, 0.0, every_target=True) for i in range(6)]
    assert [c.options.target for c in cases] == targets * 2
    assert cases[0].recipe == cases[1].recipe == cases[2].recipe != cases[3].recipe


def test_nearest_resize_ties_are_recognised():
    def resize(shape, scales, mode="nearest"):
        node = helper.make_node("Resize", ["x", "", "s"], ["y"], mode=mode, coordinate_transformation_mode="half_pixel")
        graph = helper.make_graph(
            [node], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, shape)],
            [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
            [helper.make_tensor("s", TensorProto.FLOAT, [len(shape)], scales)],
        )  # fmt: skip
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])

    assert has_nearest_resize_tie(resize([3, 64], [1.5, 1.3]))  # 71.5 / 1.3 - 0.5 = 54.5
    assert not has_nearest_resize_tie(resize([3, 64], [2.0, 2.0]))
    assert not has_nearest_resize_tie(resize([3, 64], [1.5, 1.3], mode="linear"))
