"""Integer graph inputs and outputs (issue 16): a QLinearConv fed straight from a uint8 or int8 graph
input and writing its quantized result as the graph output (a TFLite model with integer I/O through
tf2onnx), and the same in QDQ form (a DequantizeLinear of the input, a QuantizeLinear as the output).
The C function takes and writes nncg_int8/nncg_uint8 arrays (typedefs from <limits.h> in the header);
compared with onnxruntime on inputs over the whole integer range, to the bit, on ansi-c, the x86
targets, NEON under qemu and the Cortex-M4 (inputs compiled in, outputs printed); --verify and
--benchmark feed and read them; a wrong input type is one clear error."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import onnx
import pytest
from cross_helpers import CORTEX_M4_TOOLS, TOOLCHAINS, missing_tools, run_cortex_m4, runner
from helpers import kernel_ops, nncg_onnx, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import TensorProto, helper, numpy_helper
from test_cli_errors import assert_one_error_line
from test_cross_targets import require

import nncg
from nncg.errors import NncgError
from nncg.verify import random_inputs, run_compiled

ELEM = {np.uint8: TensorProto.UINT8, np.int8: TensorProto.INT8}
ZERO = {np.uint8: 121, np.int8: -7}  # the input's zero point; the output's is 10 less
STRICT = ["-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror"]


def _model(nodes, x_type, y_type, init: dict[str, np.ndarray], shape=(1, 3, 8, 8)) -> onnx.ModelProto:
    graph = helper.make_graph(
        nodes,
        "int8_io",
        [helper.make_tensor_value_info("x", ELEM[x_type], list(shape))],
        [helper.make_tensor_value_info("y", ELEM[y_type], None)],
        [numpy_helper.from_array(np.asarray(a), n) for n, a in init.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def _params(x_type, y_type, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "xs": np.float32(0.02), "xz": np.asarray(ZERO[x_type], x_type),
        "w": rng.integers(-127, 128, (6, 3, 3, 3)).astype(np.int8),
        "ws": rng.uniform(0.005, 0.02, 6).astype(np.float32), "wz": np.zeros(6, np.int8),
        "ys": np.float32(0.05), "yz": np.asarray(ZERO[y_type] - 10, y_type),
        "b": rng.integers(-3000, 3000, 6).astype(np.int32),
    }  # fmt: skip


def qlinear_conv_model(x_type=np.uint8, y_type=np.uint8) -> onnx.ModelProto:
    """x (integer) -> QLinearConv -> y (integer): the QOperator form."""
    inputs = ["x", "xs", "xz", "w", "ws", "wz", "ys", "yz", "b"]
    conv = helper.make_node("QLinearConv", inputs, ["y"], pads=[1, 1, 1, 1], strides=[1, 2])
    return _model([conv], x_type, y_type, _params(x_type, y_type))


def qdq_conv_model(x_type=np.uint8) -> onnx.ModelProto:
    """x (integer) -> DequantizeLinear -> Conv (dequantised weights and bias) -> QuantizeLinear -> y."""
    params = _params(x_type, x_type)
    params["bs"] = (params["xs"] * params["ws"]).astype(np.float32)
    params["bz"] = np.zeros(6, np.int32)
    nodes = [
        helper.make_node("DequantizeLinear", ["x", "xs", "xz"], ["xd"]),
        helper.make_node("DequantizeLinear", ["w", "ws", "wz"], ["wd"], axis=0),
        helper.make_node("DequantizeLinear", ["b", "bs", "bz"], ["bd"], axis=0),
        helper.make_node("Conv", ["xd", "wd", "bd"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("QuantizeLinear", ["c", "ys", "yz"], ["y"]),
    ]
    return _model(nodes, x_type, x_type, params)


def check(model: onnx.ModelProto, target: str = "ansi-c", **run) -> nncg.CompiledModel:
    """NNCG's C equals onnxruntime, element for element and in type, on inputs over the whole range."""
    if not run:
        skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearConv" in kernel_ops(compiled)
    for seed in range(3):
        x = random_inputs(compiled.inputs, seed)[0]
        expected = onnxruntime_outputs(model, {"x": x})[0]
        ours = run_compiled(compiled, [x], **run)[0]
        assert ours.dtype == expected.dtype and ours.shape == expected.shape
        np.testing.assert_array_equal(ours, expected)
    return compiled


@pytest.mark.parametrize("activations", [np.uint8, np.int8])  # onnxruntime's QLinearConv: x and y of one type
def test_qlinear_conv_between_integer_input_and_output(activations):
    check(qlinear_conv_model(activations, activations))


@pytest.mark.parametrize("x_type", [np.uint8, np.int8])
def test_qdq_conv_between_integer_input_and_output(x_type):
    check(qdq_conv_model(x_type))


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512", "avx512vnni"])
@pytest.mark.parametrize("form", ["qlinear", "qdq"])
def test_x86_targets(form, target):
    check(qlinear_conv_model(np.int8, np.int8) if form == "qlinear" else qdq_conv_model(np.uint8), target)


def test_neon_under_qemu():
    tc = TOOLCHAINS["aarch64-neon"]
    require(missing_tools(tc))
    check(qdq_conv_model(np.int8), "neon", cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


def test_cortex_m4_with_inputs_compiled_in(tmp_path):
    """The test program's inputs are integer literals and its int8 outputs print as int32 words."""
    require([tool for tool in CORTEX_M4_TOOLS if shutil.which(tool) is None])
    model = qlinear_conv_model(np.int8, np.int8)
    compiled = nncg.compile(model, target="ansi-c")
    x = random_inputs(compiled.inputs, 4)[0]
    ours = run_cortex_m4(compiled, [x], tmp_path).outputs[0]
    np.testing.assert_array_equal(ours, onnxruntime_outputs(model, {"x": x})[0])


def test_header_types_the_arrays_and_two_headers_include_together(tmp_path):
    """The prototypes say the dtypes; the typedefs are guarded, so headers of two models (one with
    int8 I/O, one with only int32 outputs) compile together in strict C89."""
    first = nncg.compile(qlinear_conv_model(np.int8, np.uint8), name="first")
    assert "void first(const nncg_int8 *x, nncg_uint8 *y);" in first.header
    assert "quantized values in nncg_int8 (signed char)" in first.header
    argmax = helper.make_node("ArgMax", ["x"], ["y"], axis=1)
    graph = helper.make_graph(
        [argmax],
        "second",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2, 5])],
        [helper.make_tensor_value_info("y", TensorProto.INT64, None)],
    )
    second = nncg.compile(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), name="second")
    first.write(tmp_path)
    second.write(tmp_path)
    (tmp_path / "both.c").write_text('#include "first.h"\n#include "second.h"\nint main(void) { return 0; }\n')
    subprocess.run(["gcc", *STRICT, "-fsyntax-only", "both.c"], cwd=tmp_path, check=True)


def test_verify_and_benchmark_on_the_command_line(tmp_path):
    path = tmp_path / "model.onnx"
    onnx.save(qdq_conv_model(np.uint8), path)
    result = nncg_onnx(path, "-o", tmp_path, "--verify", "--benchmark")
    assert result.returncode == 0, result.stderr
    assert "PASS" in result.stdout and "speed-up" in result.stdout


def test_a_float_array_for_an_integer_input_is_refused():
    compiled = nncg.compile(qlinear_conv_model())
    x = np.zeros((1, 3, 8, 8), np.float32)
    with pytest.raises(NncgError, match=r"input 'x' is uint8: pass integers, not float32"):
        run_compiled(compiled, [x])
    with pytest.raises(NncgError, match=r"input 'x' is uint8: its values must lie in 0..255"):
        run_compiled(compiled, [x.astype(np.int16) - 1])


def test_an_int16_input_is_refused(tmp_path):
    model = qlinear_conv_model()
    model.graph.input[0].type.tensor_type.elem_type = TensorProto.INT16
    with pytest.raises(
        NncgError, match=r"input 'x' is int16; NNCG compiles models whose inputs are float32, int8, uint8"
    ):
        nncg.compile(model)
    onnx.save(model, tmp_path / "int16.onnx")
    assert_one_error_line(nncg_onnx(tmp_path / "int16.onnx", "-o", tmp_path), "input 'x' is int16")


def test_a_float_op_reading_an_integer_input_is_refused():
    add = helper.make_node("Add", ["x", "x"], ["y"])  # uint8 arithmetic, which NNCG computes only in float
    with pytest.raises(NncgError, match=r"Add node .* reads the uint8 tensor 'x'"):
        nncg.compile(_model([add], np.uint8, np.uint8, {}))
