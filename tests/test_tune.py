"""Per-layer autotuning: the choices it makes are valid, cached, reproducible, and the tuned code
matches onnxruntime; a tuned pipeline whose release build runs slower than the default's gives way to
it. Tests of the per-layer rounds fix that last comparison (keep_tuned): which build is faster on a
small model is the machine's call."""

import re

import pytest
from helpers import check_against_onnxruntime, onnx_model, weights
from onnx import helper

import nncg
from nncg.cli import main
from nncg.passes import REGISTRY, parse_pipeline
from nncg.passes.register_block import block_candidates, choose_blocks
from nncg.passes.unroll import TUNED_BUDGETS
from nncg.tune import _Measurer, tune, tuning_candidates, with_layer_choices
from nncg.verify import find_c_compiler


def conv_pool_conv():
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("MaxPool", ["r1"], ["p1"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node("Conv", ["p1", "w2"], ["y"], pads=[1, 1, 1, 1]),
    ]
    inits = {"w1": weights(8, 3, 3, 3), "b1": weights(8), "w2": weights(12, 8, 3, 3)}
    return onnx_model(nodes, inputs={"x": (1, 3, 12, 16)}, initializers=inits)


@pytest.fixture
def keep_tuned(monkeypatch):
    """The tuned release build measured as fast as the default's: the tuned pipeline is kept."""
    monkeypatch.setattr(_Measurer, "release_ratio", lambda self, default, tuned: 1.0)


def layer_choices(pipeline: str, pass_name: str) -> dict[str, str]:
    spec = next(s for s in parse_pipeline(pipeline) if s.name == pass_name)
    text = dict(spec.params).get("layers", "")
    return dict(item.split(":") for item in text.split(";") if item)


def test_candidates_start_with_the_cost_model_and_fit_the_registers():
    for shape, registers in (((40, 2), 16), ((6, 3), 16), ((40, 1), 32), ((40, 16), 16)):
        candidates = block_candidates(shape, registers)
        assert candidates[0] == choose_blocks(shape, registers)
        assert len(set(candidates)) == len(candidates)
        assert all(p <= shape[0] and p * c <= registers - 2 for p, c in candidates[1:])


def test_with_layer_choices_spells_values_as_each_pass_does():
    base = nncg.default_pipeline(nncg.get_target("ssse3"))
    tuned = with_layer_choices(
        base, {"register-block": {"conv1": (3, 2)}, "unroll": {"conv1": 16}, "winograd": {"conv1": True}}
    )
    assert layer_choices(tuned, "register-block") == {"conv1": "3x2"}
    assert layer_choices(tuned, "unroll") == {"conv1": "16"}
    assert layer_choices(tuned, "winograd") == {"conv1": "true"}


def test_every_tunable_pass_of_the_pipeline_is_a_round_in_pipeline_order(tmp_path):
    lines = []
    tune(conv_pool_conv(), "ssse3", cache=tmp_path / "tune.json", batches=1, progress=lines.append)
    rounds = [
        line.split(":")[1].strip()
        for line in lines
        if re.fullmatch(
            r"tune: [\w-]+: \d+ layers, .*|tune: [\w-]+: no layer to tune|tune: [\w-]+: \d+ builds of the model", line
        )
    ]
    tunable = [
        s.name for s in parse_pipeline(nncg.default_pipeline(nncg.get_target("ssse3"))) if REGISTRY[s.name].tunable
    ]
    assert tunable == ["winograd", "vectorize-pixels", "cache-block", "register-block", "unroll"]
    assert list(dict.fromkeys(rounds)) == tunable


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
def test_tuned_pipeline_matches_onnxruntime_and_is_cached(tmp_path, target, keep_tuned):
    m = conv_pool_conv()
    lines = []
    pipeline = tune(m, target, cache=tmp_path / "tune.json", batches=2, progress=lines.append)
    ssse3 = nncg.get_target("ssse3")
    layers = set(tuning_candidates(m, nncg.default_pipeline(ssse3), "register-block", ssse3))
    assert layers == {"Conv_0", "MaxPool_2", "Conv_3"}
    blocks = layer_choices(pipeline, "register-block")
    assert set(blocks) == layers and all(re.fullmatch(r"\d+x\d+", b) for b in blocks.values())
    assert {int(b) for b in layer_choices(pipeline, "unroll").values()} <= set(TUNED_BUDGETS)
    assert any("builds of the model" in line for line in lines)
    assert "tune: winograd: 2 layers, 0 cached, 2 to measure" in lines
    assert set(layer_choices(pipeline, "winograd").values()) <= {"true", "false"}
    assert set(layer_choices(pipeline, "winograd")) == {"Conv_0", "Conv_3"}
    check_against_onnxruntime(m, nncg.compile(m, target, pipeline=pipeline, verify_ir=True), opt="-O1")

    again = []
    assert tune(m, target, cache=tmp_path / "tune.json", batches=2, progress=again.append) == pipeline
    assert "tune: register-block: 3 layers, 3 cached, 0 to measure" in again
    assert not any("builds" in line for line in again)


def test_cli_tune_writes_tuned_code_through_a_runner(tmp_path, monkeypatch, capsys, keep_tuned):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "net.onnx"
    path.write_bytes(conv_pool_conv().SerializeToString())
    # `env` runs the timing program as given: proves the runner prefixes its command line
    status = main([str(path), "--target", "ssse3", "--tune", "--tune-runner", "env", "-o", str(tmp_path / "out")])
    assert status == 0
    source = (tmp_path / "out" / "net.c").read_text()
    assert "register-block{layers=Conv_0:" in source.splitlines()[0]
    assert (tmp_path / "cache" / "nncg" / "tune.json").exists()
    err = capsys.readouterr().err
    assert "tune: register-block: Conv_3: " in err
    assert "\r" not in err and "batches" not in err  # stderr is not a terminal: no progress bar


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--pipeline", "lower,plan-memory"], "give --tune or --pipeline, not both"),
        (["--unroll", "2"], "leave --unroll at auto"),
        (["--tune-runner", "/no/such/emulator"], "cannot start the benchmark harness with '/no/such/emulator'"),
    ],
)
def test_cli_tune_errors_are_clear(tmp_path, monkeypatch, capsys, extra, message):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "net.onnx"
    path.write_bytes(conv_pool_conv().SerializeToString())
    assert main([str(path), "--tune", "-o", str(tmp_path / "out"), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_pixel_axis_round_times_whole_models_and_is_cached(tmp_path, keep_tuned):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[2, 2, 2, 2]),
        helper.make_node("MaxPool", ["c"], ["y"], kernel_shape=[2, 2], strides=[2, 2]),
    ]
    m = onnx_model(nodes, inputs={"x": (1, 3, 8, 40)}, initializers={"w": weights(2, 3, 5, 5), "b": weights(2)})
    lines = []
    pipeline = tune(m, "ssse3", cache=tmp_path / "tune.json", batches=2, progress=lines.append)
    assert "tune: vectorize-pixels: 2 builds of the model" in lines  # Conv_0 over channels, over pixels
    assert any(line.startswith("tune: vectorize-pixels: Conv_0: ") for line in lines)
    assert set(layer_choices(pipeline, "vectorize-pixels")) == {"Conv_0"}
    check_against_onnxruntime(m, nncg.compile(m, "ssse3", pipeline=pipeline, verify_ir=True))
    again = []
    assert tune(m, "ssse3", cache=tmp_path / "tune.json", batches=2, progress=again.append) == pipeline
    assert not any("builds" in line for line in again)


def test_layers_named_like_torch_and_tf2onnx_exports_are_tuned(tmp_path, keep_tuned):
    """Per-layer choices key on the layer's C name, whatever characters the model's names hold:
    torch's `/layer1/conv1/Conv`, tf2onnx's `model/act/Relu;model/bn/FusedBatchNormV3`."""
    m = conv_pool_conv()
    onnx_names = ["/layer1/layer1.0/conv1/Conv", "model/activation/Relu;model/bn/FusedBatchNormV3", "pool:1", "c{2}"]
    for node, name in zip(m.graph.node, onnx_names):
        node.name = name
    lines = []
    pipeline = tune(m, "ssse3", cache=tmp_path / "tune.json", batches=1, progress=lines.append)
    assert {"tune: winograd: c_2: true", "tune: winograd: c_2: false"} & set(lines)
    assert set(layer_choices(pipeline, "winograd")) == {"layer1_layer1_0_conv1_Conv", "c_2"}
    assert set(layer_choices(pipeline, "register-block")) == {"layer1_layer1_0_conv1_Conv", "pool_1", "c_2"}
    check_against_onnxruntime(m, nncg.compile(m, "ssse3", pipeline=pipeline, verify_ir=True))


def test_a_tuned_pipeline_slower_as_a_whole_gives_way_to_the_default(tmp_path, monkeypatch):
    asked = []

    def slower(self, default, tuned):
        asked.append((default, tuned))
        return 1.25

    monkeypatch.setattr(_Measurer, "release_ratio", slower)
    lines = []
    pipeline = tune(conv_pool_conv(), "ssse3", cache=tmp_path / "tune.json", batches=1, progress=lines.append)
    ((default, tuned),) = asked
    assert pipeline == default and "layers=" not in default and "register-block{layers=" in tuned
    verdict = "the tuned release build takes 1.250x the default's time: the default pipeline kept instead"
    assert f"tune: whole model: {verdict}" in lines
    again = []  # the verdict is cached with the choices
    assert tune(conv_pool_conv(), "ssse3", cache=tmp_path / "tune.json", batches=1, progress=again.append) == default
    assert len(asked) == 1 and not any("whole model" in line for line in again)


def test_release_ratio_times_both_release_builds():
    # the comparison itself, on real builds: a paired ratio of the two (its value is the machine's)
    base = nncg.default_pipeline(nncg.get_target("ssse3"))
    other = base.replace("register-block,", "register-block{layers=Conv_0:1x1;Conv_3:1x1},")
    lines = []
    measurer = _Measurer(conv_pool_conv(), "ssse3", find_c_compiler(None), (), None, 3, None, lines.append)
    ratio = measurer.release_ratio(base, other)
    assert 0 < ratio < float("inf")
    assert lines == ["tune: whole model: timing the tuned and the default release build"]


def test_per_layer_choices_name_layers_by_their_c_names():
    m = conv_pool_conv()
    pipeline = nncg.default_pipeline(nncg.get_target("ssse3")).replace("winograd", "winograd{layers=a/b:true}")
    with pytest.raises(nncg.NncgError, match="a layer name is a C identifier"):
        nncg.compile(m, "ssse3", pipeline=pipeline)
