"""Per-layer verification (nncg/verify_layers.py, `--verify --per-layer`): the debug build writes every
layer's output, each is compared with onnxruntime's, and the first layer above tolerance is named."""

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers import nncg_onnx, onnx_model, skip_unless_host_runs, weights
from onnx import helper

import nncg
from nncg import cli, verify_layers
from nncg.verify_layers import verify_layers as verify_debug_build
from nncg.verify_layers import verify_per_layer

ROBOT = Path(__file__).resolve().parent.parent / "examples" / "robot.onnx"
SIMD = "avx2"


def branchy():
    """Conv+BatchNorm+Relu, then a 1x1 Conv+Relu and a MaxPool concatenated (both write their slabs of
    the Concat), then a Conv+Sigmoid: fused nodes, a Concat, channels-last internal buffers on SIMD."""
    bn = {"g": weights(6) + 1.5, "beta": weights(6), "m": weights(6), "v": np.abs(weights(6)) + 0.5}
    nodes = [
        helper.make_node("Conv", ["x", "wa", "ba"], ["a"], name="conv_a", pads=[1, 1, 1, 1]),
        helper.make_node("BatchNormalization", ["a", "g", "beta", "m", "v"], ["bn"], name="bn"),
        helper.make_node("Relu", ["bn"], ["r"], name="relu"),
        helper.make_node("Conv", ["r", "wb"], ["b"], name="conv_b"),
        helper.make_node("Relu", ["b"], ["br"], name="relu_b"),
        helper.make_node("MaxPool", ["r"], ["p"], name="pool", kernel_shape=[3, 3], pads=[1, 1, 1, 1]),
        helper.make_node("Concat", ["br", "p"], ["cat"], name="cat", axis=1),
        helper.make_node("Conv", ["cat", "wc", "bc"], ["c"], name="conv_c", pads=[1, 1, 1, 1]),
        helper.make_node("Sigmoid", ["c"], ["y"], name="sigmoid"),
    ]
    inits = {"wa": weights(6, 3, 3, 3), "ba": weights(6), "wb": weights(8, 6, 1, 1), "wc": weights(5, 14, 3, 3),
             "bc": weights(5), **bn}  # fmt: skip
    return onnx_model(nodes, inputs={"x": (1, 3, 10, 12)}, initializers=inits)


def rows(report) -> list[tuple[str, str]]:
    """(tensor, op column) per row."""
    return [(layer.stat.name, layer.cells()[1]) for layer in report.layers]


@pytest.mark.parametrize("target", ["ansi-c", SIMD])
def test_every_layer_of_the_robot_network_matches(target):
    skip_unless_host_runs(target)
    report = verify_per_layer(ROBOT, target)
    assert report.ok, report.format()
    tensors = ["lrelu1", "pool1", "lrelu2", "lrelu3", "pool2", "lrelu4", "detections"]
    assert [name for name, _ in rows(report)] == tensors
    assert rows(report)[0][1] == "Conv+BatchNormalization+LeakyRelu (fused)"
    assert report.layers[0].nodes == (("conv1", "Conv"), ("bn1", "BatchNormalization"), ("lrelu1", "LeakyRelu"))


@pytest.mark.parametrize("target", ["ansi-c", SIMD])
@pytest.mark.parametrize("halos", [False, True])
def test_fused_nodes_concat_slabs_and_channels_last_buffers_match(target, halos):
    skip_unless_host_runs(target)
    pipeline = nncg.default_pipeline(nncg.get_target(target))
    if halos:  # the Concat output inside a zero border for conv_c, its slabs written in place
        pipeline = pipeline.replace(",lower,", ",lower{halos=true},")
    report = verify_per_layer(branchy(), target, pipeline=pipeline, sanitize=target == "ansi-c")
    assert report.ok, report.format()
    assert rows(report) == [
        ("r", "Conv+BatchNormalization+Relu (fused)"),
        ("br", "Conv+Relu (fused)"),
        ("p", "MaxPool"),
        ("cat", "Concat"),
        ("y", "Conv+Sigmoid (fused)"),
    ]


def corrupt_weight(source: str, layer: str) -> str:
    """The C with the first value of `layer`'s first weight array changed."""
    match = re.search(rf"const float \w*{layer}\w*\[\d+\] = {{\n\s*(\S+?),", source)
    assert match is not None, f"no weight array of {layer}"
    start, end = match.span(1)
    return source[:start] + "100.0f" + source[end:]


@pytest.mark.parametrize("target", ["ansi-c", SIMD])
def test_a_corrupted_middle_layer_is_the_first_one_named(target):
    skip_unless_host_runs(target)
    compiled = nncg.compile(ROBOT, target, expose_layers=True, weights="embed")
    broken = replace(compiled, source=corrupt_weight(compiled.source, "conv3"))
    report = verify_debug_build(nncg.load_model(ROBOT), broken)
    assert not report.ok
    assert report.first_failure.stat.name == "lrelu3"
    assert [layer.exceeds(report.tolerance) for layer in report.layers[:2]] == [False, False]
    assert "FAIL: first layer above tolerance: conv3+bn3+lrelu3 (Conv+BatchNormalization+LeakyRelu (fused))" in (
        report.format()
    )


def test_the_command_line_names_the_corrupted_layer_and_exits_1(monkeypatch, tmp_path, capsys):
    def compile_broken(*args, **kwargs):
        compiled = nncg.compile(*args, **kwargs)
        return replace(compiled, source=corrupt_weight(compiled.source, "conv4"))

    monkeypatch.setattr(verify_layers, "compile_model", compile_broken)
    status = cli.main([str(ROBOT), "--verify", "--per-layer", "--weights", "embed", "-o", str(tmp_path)])
    out = capsys.readouterr().out
    assert status == 1
    assert "PASS: max rel err <= 0.0001 required" in out  # the shipped build is fine
    assert "FAIL: first layer above tolerance: conv4+bn4+lrelu4" in out


def test_tolerance_zero_fails_at_the_first_layer_with_rounding_differences(tmp_path):
    result = nncg_onnx(ROBOT, "--verify", "--per-layer", "--tolerance", "0", "-o", tmp_path)
    assert result.returncode == 1, result.stderr
    assert "FAIL: first layer above tolerance: conv1+bn1+lrelu1" in result.stdout


def test_per_layer_without_verify_is_refused_and_writes_nothing(tmp_path):
    result = nncg_onnx(ROBOT, "--per-layer", "-o", tmp_path)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "--per-layer" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_hostile_names_are_escaped_in_the_table():
    tensor, node = "h\x1b[2J\u202eidden\nx", "n\x07ode\u200b"
    nodes = [
        helper.make_node("Conv", ["x", "w"], [tensor], name=node, pads=[1, 1, 1, 1]),
        helper.make_node("MaxPool", [tensor], ["y"], name="pool", kernel_shape=[2, 2]),
    ]
    model = onnx_model(nodes, inputs={"x": (1, 2, 5, 5)}, initializers={"w": weights(3, 2, 3, 3)})
    text = verify_per_layer(model, "ansi-c", unroll="none").format()
    assert text.startswith("verify per layer") and text.endswith("PASS: every layer's max rel err <= 0.0001")
    assert text.isascii() and not any(ch in text for ch in "\x1b\x07\u202e\u200b")
    assert "h\\x1b[2J\\u202eidden\\nx" in text and "n\\x07ode\\u200b" in text


def test_a_build_without_exposed_layers_is_refused():
    compiled = nncg.compile(ROBOT, "ansi-c")
    with pytest.raises(nncg.NncgError, match="expose_layers=True"):
        verify_debug_build(nncg.load_model(ROBOT), compiled)


def test_expose_layers_must_be_a_bool():
    with pytest.raises(nncg.NncgError, match="expose_layers"):
        nncg.compile(ROBOT, expose_layers="yes")
