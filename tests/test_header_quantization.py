"""The header states each integer graph input's and output's scale and zero point (issue 16):
NAME_X_SCALE (a float literal that reads back to the model's float32) and NAME_X_ZERO_POINT, so a
caller (de)quantises without opening the ONNX model. A strict C89 program includes the header,
prints the macros and dequantises the model's output with them; both are checked against the
model's constants and onnxruntime's DequantizeLinear of the same output."""

from __future__ import annotations

import subprocess

import numpy as np
import onnx
import pytest
from helpers import skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import TensorProto, helper, numpy_helper
from test_int8_io import STRICT, qdq_conv_model, qlinear_conv_model

import nncg
from nncg.frontend.io_quantization import io_quantization
from nncg.verify import random_inputs

C_TYPE = {"int8": "nncg_int8", "uint8": "nncg_uint8"}


def _constant(model: onnx.ModelProto, name: str) -> np.ndarray:
    return next(numpy_helper.to_array(t) for t in model.graph.initializer if t.name == name)


def _with_dequantized_output(model: onnx.ModelProto) -> onnx.ModelProto:
    """The model with its output y also dequantised by its own ys and yz: onnxruntime's real values."""
    extended = onnx.ModelProto()
    extended.CopyFrom(model)
    extended.graph.node.append(helper.make_node("DequantizeLinear", ["y", "ys", "yz"], ["real"]))
    extended.graph.output.append(helper.make_tensor_value_info("real", TensorProto.FLOAT, None))
    return extended


def _program(prefix: str, x_type: str, y_type: str, x: np.ndarray) -> str:
    values = ", ".join(str(int(v)) for v in x.ravel())
    return "\n".join([
        "#include <stdio.h>",
        '#include "net.h"',
        f"static const {C_TYPE[x_type]} x[{prefix}_X_SIZE] = {{{values}}};",
        f"static {C_TYPE[y_type]} y[{prefix}_Y_SIZE];",
        "int main(void)",
        "{",
        "    long i;",
        "    net(x, y);",
        f'    printf("%.9g %d %.9g %d\\n", (double){prefix}_X_SCALE, {prefix}_X_ZERO_POINT,'
        f" (double){prefix}_Y_SCALE, {prefix}_Y_ZERO_POINT);",
        f"    for (i = 0; i < {prefix}_Y_SIZE; i++) {{",
        f"        float real = (float)(y[i] - {prefix}_Y_ZERO_POINT) * {prefix}_Y_SCALE;",
        '        printf("%.9g\\n", (double)real);',
        "    }",
        "    return 0;",
        "}",
        "",
    ])  # fmt: skip


@pytest.mark.parametrize(
    ("model", "x_type", "y_type"),
    [(qlinear_conv_model(np.int8, np.int8), "int8", "int8"), (qdq_conv_model(np.uint8), "uint8", "uint8")],
    ids=["qlinear-int8", "qdq-uint8"],
)
def test_a_c89_program_dequantises_with_the_header_macros(model, x_type, y_type, tmp_path):
    skip_unless_host_runs("ansi-c")
    compiled = nncg.compile(model, name="net")
    compiled.write(tmp_path)
    x = random_inputs(compiled.inputs, 3)[0]
    (tmp_path / "main.c").write_text(_program("NET", x_type, y_type, x))
    subprocess.run(["gcc", *STRICT, "main.c", "net.c", "-o", "main", "-lm"], cwd=tmp_path, check=True)
    lines = subprocess.run(["./main"], cwd=tmp_path, check=True, capture_output=True, text=True).stdout.splitlines()
    x_scale, x_zero, y_scale, y_zero = lines[0].split()
    assert np.float32(x_scale) == _constant(model, "xs") and int(x_zero) == int(_constant(model, "xz"))
    assert np.float32(y_scale) == _constant(model, "ys") and int(y_zero) == int(_constant(model, "yz"))
    real = np.array(lines[1:], np.float32)
    expected = onnxruntime_outputs(_with_dequantized_output(model), {"x": x})[1]
    np.testing.assert_array_equal(real, expected.ravel())


def test_scale_literal_is_exact_and_macro_names_are_the_c_names():
    """An awkward scale (no short decimal) and a tensor name that is no C identifier."""
    model = qlinear_conv_model(np.uint8, np.uint8)
    model.graph.initializer.remove(next(t for t in model.graph.initializer if t.name == "ys"))
    model.graph.initializer.append(numpy_helper.from_array(np.float32(1 / 3), "ys"))
    for node in model.graph.node:
        node.input[0] = "in put*/"
    model.graph.input[0].name = "in put*/"
    compiled = nncg.compile(model, name="net")
    c_name = compiled.inputs[0].c_name
    assert f"#define NET_{c_name.upper()}_SCALE 0.02f" in compiled.header
    assert f"#define NET_{c_name.upper()}_ZERO_POINT 121" in compiled.header
    assert "#define NET_Y_SCALE 0.33333334f" in compiled.header and np.float32("0.33333334") == np.float32(1 / 3)
    assert "in put*/" not in compiled.header


def test_no_macros_without_one_scale_and_zero_point():
    """A float model has none; an integer input read with two different zero points has none."""
    float_model = helper.make_model(
        helper.make_graph(
            [helper.make_node("Relu", ["x"], ["y"])], "f",
            [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
            [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        ),
        opset_imports=[helper.make_opsetid("", 17)],
    )  # fmt: skip
    assert "_SCALE" not in nncg.compile(float_model).header
    model = qdq_conv_model(np.uint8)
    assert io_quantization(model) == {"x": (pytest.approx(0.02), 121), "y": (pytest.approx(0.05), 111)}
    model.graph.node.append(helper.make_node("DequantizeLinear", ["x", "xs"], ["x_other"]))
    model.graph.output.append(helper.make_tensor_value_info("x_other", TensorProto.FLOAT, None))
    assert io_quantization(model) == {"y": (pytest.approx(0.05), 111)}
