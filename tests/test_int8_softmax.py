"""Quantized Softmax (issue 16): a Softmax between DequantizeLinear and QuantizeLinear, which
onnxruntime fuses into its QLinearSoftmax, and that op itself (com.microsoft), compiled to NNCG's
integer kernel (a table of exp values, as onnxruntime builds it) and compared with onnxruntime on the
same model: bit-identical on every element, uint8 and int8, every axis rule, every x86 target."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import helper, numpy_helper

import nncg
from nncg.verify import run_compiled

FEEDS = 4
# (shape, axis or None for the default, opset): opset < 13 flattens the dims from axis on
CASES = {
    "classes": ((1, 10), None, 17),
    "rows": ((4, 100), None, 17),
    "inner_axis": ((2, 7, 3, 4), 2, 13),
    "flattened": ((2, 3, 5), 1, 11),
}
# activation type: (x zero point, y scale, y zero point); the first of each is what quantize_static writes
OUTPUTS = {
    "uint8": (100, 1 / 256, 0),
    "int8": (0, 1 / 256, -128),
    "uint8_zp": (10, 0.003, 3),
    "int8_zp": (-20, 0.003, 5),
}


def _params(activations: str, x_scale: float) -> dict[str, np.ndarray]:
    x_zero, y_scale, y_zero = OUTPUTS[activations]
    dtype = np.int8 if activations.startswith("int8") else np.uint8
    return {
        "xs": np.float32(x_scale), "xz": dtype(x_zero), "ys": np.float32(y_scale), "yz": dtype(y_zero),
    }  # fmt: skip


def qdq_softmax_model(case: str, activations: str) -> onnx.ModelProto:
    shape, axis, opset = CASES[case]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node("DequantizeLinear", ["q", "xs", "xz"], ["d"]),
        helper.make_node("Softmax", ["d"], ["s"], **({} if axis is None else {"axis": axis})),
        helper.make_node("QuantizeLinear", ["s", "ys", "yz"], ["sq"]),
        helper.make_node("DequantizeLinear", ["sq", "ys", "yz"], ["y"]),
    ]
    return onnx_model(nodes, inputs={"x": shape}, initializers=_params(activations, 0.07), opset=opset)


def qlinear_softmax_model(activations: str, opset: int) -> onnx.ModelProto:
    """onnxruntime's QLinearSoftmax between QuantizeLinear and DequantizeLinear (QOperator format)."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node(
            "QLinearSoftmax", ["q", "xs", "xz", "ys", "yz"], ["sq"], domain="com.microsoft", axis=1, opset=opset
        ),
        helper.make_node("DequantizeLinear", ["sq", "ys", "yz"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": (3, 4, 5)}, initializers=_params(activations, 0.05))
    model.opset_import.append(helper.make_opsetid("com.microsoft", 1))
    return model


def check(model: onnx.ModelProto, target: str = "ansi-c") -> None:
    """Bit-identical to onnxruntime on every element of FEEDS inputs, some saturating the input type."""
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearSoftmax" in kernel_ops(compiled)
    shape = tuple(d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim)
    rng = np.random.default_rng(7)
    for spread in np.linspace(0.5, 12, FEEDS):
        x = (rng.standard_normal(shape) * spread).astype(np.float32)
        ours = run_compiled(compiled, [x])[0]
        np.testing.assert_array_equal(ours, onnxruntime_outputs(model, {"x": x})[0].reshape(ours.shape))


@pytest.mark.parametrize("activations", sorted(OUTPUTS))
@pytest.mark.parametrize("case", sorted(CASES))
def test_qdq_softmax_matches_onnxruntime_to_the_bit(case, activations):
    model = qdq_softmax_model(case, activations)
    check(model)
    assert "QLinearSoftmax" in _optimised_ops(model)


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_x86_targets(target, activations):
    check(qdq_softmax_model("inner_axis", activations), target)


@pytest.mark.parametrize("opset", [11, 13])
@pytest.mark.parametrize("activations", sorted(OUTPUTS))
def test_qlinear_softmax_matches_onnxruntime_to_the_bit(activations, opset):
    """int8: onnxruntime 1.32's int8 kernel saturates (a y scale of 0.003 and zero point 5 reach 338)."""
    check(qlinear_softmax_model(activations, opset))


def test_softmax_between_other_quantizations_stays_float():
    """A Softmax whose output is no QuantizeLinear's input is a float layer, in onnxruntime too."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node("DequantizeLinear", ["q", "xs", "xz"], ["d"]),
        helper.make_node("Softmax", ["d"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": (1, 10)}, initializers=_params("uint8", 0.07))
    assert kernel_ops(nncg.compile(model)) == ["QuantizeLinear", "DequantizeLinear", "Softmax"]
    assert _optimised_ops(model) == ["QuantizeLinear", "DequantizeLinear", "Softmax"]


def test_softmax_from_uint8_to_int8():
    """onnxruntime makes the int8 output uint8 (+128) and fuses: the same saturated results."""
    model = qdq_softmax_model("classes", "uint8")
    model.graph.initializer[-1].CopyFrom(numpy_helper.from_array(np.int8(-128), "yz"))
    assert "QLinearSoftmax" in _optimised_ops(model)
    check(model)


def _optimised_ops(model: onnx.ModelProto) -> list[str]:
    """The ops of onnxruntime's optimised graph (its QDQ fusions applied)."""
    import tempfile

    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        options = ort.SessionOptions()
        options.optimized_model_filepath = f"{tmp}/optimised.onnx"
        options.log_severity_level = 3
        ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
        return [node.op_type for node in onnx.load(options.optimized_model_filepath).graph.node]
