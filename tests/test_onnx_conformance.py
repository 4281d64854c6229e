"""ONNX conformance: onnx's own backend test suite run through NNCG (nncg.onnx_backend).

Node cases: every onnx node test case of an operator in SUPPORTED_OPS (selection and exclusions in
nncg/conformance.py), compared with onnx's stored outputs at onnx's tolerances. Model cases: the
light_* models of onnx/backend/test/data/light, marked `zoo` (deselected by default; run them with
`python3 -m pytest -m zoo tests/test_onnx_conformance.py`). scripts/conformance_report.py writes
the per-operator table docs/conformance.md from the same selection.
"""

from __future__ import annotations

import re
import shutil
import warnings

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from onnx.backend.test import BackendTest

import nncg.onnx_backend
from nncg import conformance
from nncg.errors import NncgError
from nncg.frontend.ops import SUPPORTED_OPS
from nncg.onnx_backend import BackendError, NncgBackend, parameter_inputs
from nncg.verify import reference_session

needs_cc = pytest.mark.skipif(not any(shutil.which(c) for c in ("cc", "gcc", "clang")), reason="no C compiler on PATH")

# onnx's test classes for NNCG, by category; only the selected cases below are run from them.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", RuntimeWarning)  # onnx's case generators overflow casts on purpose
    TEST_CASES = BackendTest(NncgBackend, __name__).test_cases
NODE_CASES = conformance.select_node_cases()


@needs_cc
@pytest.mark.parametrize("name", [case.name for case in NODE_CASES])
def test_node(name: str) -> None:
    reason = conformance.exclusion_reason(name)
    if reason is not None:
        pytest.skip(f"excluded: {reason}")
    conformance.run_node_case(TEST_CASES, name)


@needs_cc
@pytest.mark.zoo
# vgg19 (146 s, CI's second-longest test) runs only the operators alexnet and zfnet512 run
@pytest.mark.parametrize("name", [m for m in conformance.ZOO_MODELS if m != "test_vgg19"])
def test_zoo_model(name: str, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    # onnx writes the generated input and expected output under $ONNX_MODELS (default ~/.onnx).
    monkeypatch.setenv("ONNX_MODELS", str(tmp_path_factory.mktemp("onnx_models")))
    conformance.run_zoo_model(TEST_CASES, name)


# --- the selection ---------------------------------------------------------------------------------


def test_selection_follows_supported_ops() -> None:
    ops = {case.op for case in NODE_CASES}
    assert ops <= set(SUPPORTED_OPS)
    assert {"Conv", "MaxPool", "Relu", "Gemm"} <= ops
    names = [case.name for case in NODE_CASES]
    assert names == sorted(names) and len(names) == len(set(names))
    # An op nobody supports yet is picked up as soon as it is in the supported set.
    sigmoid = [case.name for case in conformance.select_node_cases(["Sigmoid"])]
    assert "test_sigmoid" in sigmoid and all(n.startswith("test_sigmoid") for n in sigmoid)
    assert "test_sigmoid" not in names or "Sigmoid" in SUPPORTED_OPS


def test_case_ops_come_from_the_graph() -> None:
    assert conformance.case_op("test_relu") == "Relu"
    assert conformance.case_op("test_batchnorm_epsilon") == "BatchNormalization"
    # Expanded cases count for the op they expand, whatever ops the expansion uses.
    assert conformance.case_op("test_softmax_axis_0_expanded") == "Softmax"
    assert conformance.case_op("test_clip_default_inbounds_expanded") == "Clip"
    assert "Softmax" not in conformance.live_ops(conformance.node_test_cases()["test_softmax_axis_0_expanded"].model)


def test_live_ops_skip_what_folds_to_constants() -> None:
    graph = helper.make_graph(
        [
            helper.make_node("Shape", ["x"], ["s"]),
            helper.make_node("Constant", [], ["one"], value=helper.make_tensor("v", TensorProto.INT64, [1], [1])),
            helper.make_node("Concat", ["one", "s"], ["shape"], axis=0),
            helper.make_node("Reshape", ["x", "shape"], ["r"]),
            helper.make_node("Relu", ["r"], ["y"]),
        ],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 3])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2, 3])],
    )
    assert conformance.live_ops(helper.make_model(graph)) == {"Reshape", "Relu"}


def test_every_exclusion_names_existing_cases() -> None:
    names = list(conformance.node_test_cases())
    for pattern, reason in conformance.EXCLUDED.items():
        assert reason and "\n" not in reason, pattern
        assert any(re.fullmatch(pattern, n) for n in names), f"{pattern} matches no case"


def test_dtype_exclusions_hold_for_the_graph() -> None:
    """A case excluded for its tensor type (by a name pattern) really has such an input or output."""
    kinds = {"float64 tensors": {"float64"}, "float16 tensors": {"float16", "bfloat16"}, "integer tensors": None}
    for case in NODE_CASES:
        reason = conformance.exclusion_reason(case.name) or ""
        kind = next((k for k in kinds if reason.startswith(k)), None)
        if kind is None:
            continue
        graph = conformance.node_test_cases()[case.name].model.graph
        dtypes = {
            helper.tensor_dtype_to_np_dtype(v.type.tensor_type.elem_type).name
            for v in (*graph.input, *graph.output)
            if v.type.HasField("tensor_type")
        }
        wanted = kinds[kind] or {d for d in dtypes if re.fullmatch(r"u?int\d+", d)}
        assert dtypes & wanted, f"{case.name} is excluded for {kind} but has {sorted(dtypes)}"


# --- the adapter ------------------------------------------------------------------------------------


def _add_relu_model() -> onnx.ModelProto:
    graph = helper.make_graph(
        [helper.make_node("Add", ["a", "b"], ["s"]), helper.make_node("Relu", ["s"], ["y"])],
        "add_relu",
        [
            helper.make_tensor_value_info("a", TensorProto.FLOAT, [2, 3]),
            helper.make_tensor_value_info("b", TensorProto.FLOAT, [3]),
        ],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 3])],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


@needs_cc
def test_backend_builds_once_and_runs_lists_and_dicts() -> None:
    rep = NncgBackend.prepare(_add_relu_model(), "CPU")
    rng = np.random.default_rng(0)
    for _ in range(2):
        a, b = rng.standard_normal((2, 3), np.float32), rng.standard_normal(3, np.float32)
        (y,) = rep.run([a, b])
        assert y.dtype == np.float32 and y.shape == (2, 3)
        np.testing.assert_allclose(y, np.maximum(a + b, 0), rtol=1e-6)
        (y2,) = rep.run({"b": b, "a": a})
        np.testing.assert_array_equal(y, y2)


@needs_cc
def test_backend_rejects_bad_inputs() -> None:
    rep = NncgBackend.prepare(_add_relu_model(), target="ansi-c", unroll="none")
    a, b = np.zeros((2, 3), np.float32), np.zeros(3, np.float32)
    with pytest.raises(BackendError, match="float32"):
        rep.run([a.astype(np.float64), b])
    with pytest.raises(BackendError, match="shape"):
        rep.run([a, np.zeros(2, np.float32)])
    with pytest.raises(BackendError, match="takes 2 inputs"):
        rep.run([a])
    with pytest.raises(BackendError, match="missing"):
        rep.run({"a": a})


def test_backend_refuses_what_nncg_cannot_compile() -> None:
    graph = helper.make_graph(
        [helper.make_node("Relu", ["x"], ["y"])],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.DOUBLE, [2])],
        [helper.make_tensor_value_info("y", TensorProto.DOUBLE, [2])],
    )
    with pytest.raises(NncgError, match="float32"):
        NncgBackend.prepare(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]))
    with pytest.raises(BackendError, match="CPU"):
        NncgBackend.prepare(_add_relu_model(), "CUDA")
    assert NncgBackend.supports_device("CPU") and not NncgBackend.supports_device("CUDA")


@needs_cc
def test_run_node() -> None:
    x = np.array([[-1.0, 2.0]], np.float32)
    (y,) = NncgBackend.run_node(helper.make_node("Relu", ["x"], ["y"]), [x])
    np.testing.assert_array_equal(y, [[0.0, 2.0]])


# --- parameter inputs: bound as constants at the first run ----------------------------------------


def _reshape_resize_model() -> onnx.ModelProto:
    """y = Resize(Reshape(x, shape), scales), nearest: shape (int64) and scales (float32) are parameters."""
    graph = helper.make_graph(
        [
            helper.make_node("Reshape", ["x", "shape"], ["r"]),
            helper.make_node("Resize", ["r", "", "scales"], ["y"], mode="nearest"),
        ],
        "reshape_resize",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 3]),
            helper.make_tensor_value_info("shape", TensorProto.INT64, [2]),
            helper.make_tensor_value_info("scales", TensorProto.FLOAT, [2]),
        ],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def _repeated(x: np.ndarray, shape: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """What the nearest Resize by integer scales (half_pixel, round_prefer_floor) makes of x."""
    y = x.reshape(shape)
    for axis, scale in enumerate(scales):
        y = np.repeat(y, int(scale), axis=axis)
    return y


@pytest.fixture
def compiles(monkeypatch: pytest.MonkeyPatch) -> list[onnx.ModelProto]:
    """The models nncg.compile was called with by the adapter, in order."""
    calls: list[onnx.ModelProto] = []
    real = nncg.onnx_backend.nncg_compile

    def counting(model: onnx.ModelProto, **kwargs: object) -> object:
        calls.append(model)
        return real(model, **kwargs)

    monkeypatch.setattr(nncg.onnx_backend, "nncg_compile", counting)
    return calls


def test_parameter_inputs_are_found_by_slot_and_dtype() -> None:
    assert [v.name for v in parameter_inputs(_reshape_resize_model().graph)] == ["shape", "scales"]
    assert parameter_inputs(_add_relu_model().graph) == []
    # A float input read in a data slot anywhere is data, even if a parameter slot also reads it.
    graph = helper.make_graph(
        [helper.make_node("Resize", ["x", "", "m"], ["c"]), helper.make_node("Add", ["c", "m"], ["y"])],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, [2]) for n in ("x", "m")],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2])],
    )
    assert parameter_inputs(graph) == []


@needs_cc
def test_parameter_inputs_compile_at_first_run_and_cache_by_value(compiles: list) -> None:
    rep = NncgBackend.prepare(_reshape_resize_model())
    assert compiles == [] and rep.compiled is None and rep.builds == 0
    assert rep.input_names == ("x", "shape", "scales") and rep.parameter_names == ("shape", "scales")
    rng = np.random.default_rng(1)
    shape, scales = np.array([3, 2], np.int64), np.array([1, 2], np.float32)

    def run(x, shape, scales):
        (y,) = rep.run([x, shape, scales])
        np.testing.assert_array_equal(y, _repeated(x, shape, scales))
        return y

    # First run: binds shape/scales as initializers (no longer graph inputs), compiles, builds.
    run(rng.standard_normal((2, 3), np.float32), shape, scales)
    assert len(compiles) == 1 and rep.builds == 1
    bound = compiles[0].graph
    assert [v.name for v in bound.input] == ["x"]
    assert sorted(t.name for t in bound.initializer) == ["scales", "shape"]
    assert [p.name for p in rep.compiled.inputs] == ["x"]
    # Same parameter values, new data (also by name): the build is reused, x stays a runtime input.
    for _ in range(2):
        x = rng.standard_normal((2, 3), np.float32)
        run(x, shape.copy(), scales.copy())
        (y,) = rep.run({"scales": scales, "x": x, "shape": shape})
        np.testing.assert_array_equal(y, _repeated(x, shape, scales))
    assert len(compiles) == 1 and rep.builds == 1
    # Other values compile again; each set of values keeps its build.
    x = rng.standard_normal((2, 3), np.float32)
    assert run(x, np.array([6, 1], np.int64), scales).shape == (6, 2)
    assert run(x, shape, np.array([2, 1], np.float32)).shape == (6, 2)
    assert len(compiles) == 3 and rep.builds == 3
    run(x, shape, scales)
    assert len(compiles) == 3 and rep.compiled.outputs[0].shape == (3, 4)


@needs_cc
def test_parameter_inputs_are_checked(compiles: list) -> None:
    rep = NncgBackend.prepare(_reshape_resize_model())
    x, scales = np.zeros((2, 3), np.float32), np.array([1, 2], np.float32)
    with pytest.raises(BackendError, match="'shape' is int32; the model declares int64"):
        rep.run([x, np.array([3, 2], np.int32), scales])
    with pytest.raises(BackendError, match=r"'shape' has shape \[3\]"):
        rep.run([x, np.array([3, 2, 1], np.int64), scales])
    with pytest.raises(BackendError, match="takes 3 inputs"):
        rep.run([x])
    assert compiles == []
    with pytest.raises(BackendError, match="float32"):  # data inputs: checked against the build
        rep.run([x.astype(np.float64), np.array([3, 2], np.int64), scales])


def test_nncg_compile_still_needs_constant_parameters() -> None:
    graph = helper.make_graph(
        [helper.make_node("Resize", ["x", "", "scales"], ["y"])],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in (("x", [2]), ("scales", [1]))],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    with pytest.raises(NncgError, match="computed at runtime"):
        nncg.compile(model)


# --- the float32 share (docs/conformance.md, README) ------------------------------------------------


def test_float32_cases_are_those_computing_on_float32_data() -> None:
    float32 = conformance.is_float32_case
    assert float32("test_relu") and float32("test_argmax_default_axis_example")  # int64 indices aside
    assert float32("test_reshape_reduced_dims")  # its int64 shape is a parameter, not data
    assert float32("test_identity_sequence")  # a sequence of float32 tensors
    assert not float32("test_dequantizelinear") and not float32("test_cast_FLOAT_to_DOUBLE")
    assert not float32("test_reduce_max_bool_inputs")


def test_exclusions_leave_over_95_percent_of_the_float32_cases_running() -> None:
    """Every case that runs must pass (test_node), so this bounds the float32 share from below."""
    float32 = [case.name for case in NODE_CASES if conformance.is_float32_case(case.name)]
    running = [name for name in float32 if conformance.exclusion_reason(name) is None]
    assert len(running) / len(float32) > 0.95, f"{len(running)} of {len(float32)}"


# --- quantised data: int8/uint8 inputs and outputs, integer kernels' weights bound -------------------


def _qlinear_conv_fed_weights() -> onnx.ModelProto:
    """x (uint8 data) -> QLinearConv -> y (uint8), its weights w (int8) and zero points graph inputs, as
    onnx's node tests feed them."""
    inputs = ["x", "xs", "xz", "w", "ws", "wz", "ys", "yz"]
    types = {"x": TensorProto.UINT8, "xz": TensorProto.UINT8, "w": TensorProto.INT8, "wz": TensorProto.INT8}
    types["yz"] = TensorProto.UINT8
    shapes = {"x": [1, 2, 4, 4], "w": [3, 2, 3, 3]}  # the others are scalars
    graph = helper.make_graph(
        [helper.make_node("QLinearConv", inputs, ["y"], pads=[1, 1, 1, 1])],
        "qconv",
        [helper.make_tensor_value_info(n, types.get(n, TensorProto.FLOAT), shapes.get(n, [])) for n in inputs],
        [helper.make_tensor_value_info("y", TensorProto.UINT8, None)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def test_integer_data_inputs_are_data_and_integer_weights_are_bound() -> None:
    """x is read as data: the C function takes it; its zero points and scales (parameter slots) and the
    int8 weights NNCG's kernels take as constants (CONSTANT_WEIGHTS) are bound."""
    bound = [v.name for v in parameter_inputs(_qlinear_conv_fed_weights().graph)]
    assert bound == ["xs", "xz", "w", "ws", "wz", "ys", "yz"]


@needs_cc
def test_backend_runs_uint8_in_and_out_like_onnxruntime(compiles: list) -> None:
    """Weights in [-64, 63]: fed as an input they escape onnxruntime's exact rewrite (verify.reference_session),
    and without VNNI its int16 sums of two uint8 x int8 products saturate beyond that."""
    model = _qlinear_conv_fed_weights()
    rng = np.random.default_rng(0)
    feeds = {
        "x": rng.integers(0, 256, (1, 2, 4, 4), dtype=np.uint8), "xs": np.float32(0.03), "xz": np.uint8(120),
        "w": rng.integers(-64, 64, (3, 2, 3, 3), dtype=np.int8), "ws": np.float32(0.01), "wz": np.int8(0),
        "ys": np.float32(0.05), "yz": np.uint8(100),
    }  # fmt: skip
    feeds = {n: np.asarray(a) for n, a in feeds.items()}
    rep = NncgBackend.prepare(model)
    (ours,) = rep.run(feeds)
    (expected,) = reference_session(model).run(None, feeds)
    assert ours.dtype == np.uint8 and rep.compiled.inputs[0].dtype == "uint8"
    np.testing.assert_array_equal(ours, expected)
    with pytest.raises(BackendError, match="input 'x' is int8; the model takes uint8"):
        rep.run({**feeds, "x": feeds["x"].astype(np.int8)})
    assert len(compiles) == 1  # the bound values did not change
