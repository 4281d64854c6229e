"""Quantized Concat (issue 16): a Concat between DequantizeLinear nodes and a QuantizeLinear, which
onnxruntime fuses into its QLinearConcat, and that op itself (com.microsoft): inputs quantised as the
output are copied, others requantised through onnxruntime's table; compared with onnxruntime running
the same model, bit-identical on every element, int8 and uint8, zero points other than 0,
requantisation saturating at both ends, a constant input, ansi-c and SIMD targets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import CONTRIB, assert_identical, onnxruntime_outputs, spread_feeds
from onnx import helper

import nncg
from nncg.verify import run_compiled

SHAPES = {"a": (1, 3, 4, 5), "b": (1, 2, 4, 5)}
CONSTANT_SHAPE = (1, 1, 4, 5)
# activation type: zero points of a (the output's too), b and the constant
ZEROS = {"uint8": (120, 140, 30), "int8": (-8, 15, -90)}
SCALES = {"a": 0.05, "b": 0.13, "c": 0.02}  # b's range is wider than the output's: it saturates


def _params(activations: str, axis_constant: bool) -> dict[str, np.ndarray]:
    dtype = np.int8 if activations == "int8" else np.uint8
    za, zb, zc = ZEROS[activations]
    params = {"as": np.float32(SCALES["a"]), "az": dtype(za), "bs": np.float32(SCALES["b"]), "bz": dtype(zb)}
    if axis_constant:
        info = np.iinfo(dtype)
        values = np.random.default_rng(4).integers(info.min, info.max + 1, CONSTANT_SHAPE).astype(dtype)
        params.update({"cs": np.float32(SCALES["c"]), "cz": dtype(zc), "cq": values})
    return params


def qdq_model(activations: str) -> onnx.ModelProto:
    nodes = [
        helper.make_node("QuantizeLinear", ["a", "as", "az"], ["aq"]),
        helper.make_node("DequantizeLinear", ["aq", "as", "az"], ["ad"]),
        helper.make_node("QuantizeLinear", ["b", "bs", "bz"], ["bq"]),
        helper.make_node("DequantizeLinear", ["bq", "bs", "bz"], ["bd"]),
        helper.make_node("DequantizeLinear", ["cq", "cs", "cz"], ["cd"]),
        helper.make_node("Concat", ["ad", "bd", "cd"], ["j"], axis=1),
        helper.make_node("QuantizeLinear", ["j", "as", "az"], ["jq"]),
        helper.make_node("DequantizeLinear", ["jq", "as", "az"], ["y"]),
    ]
    return onnx_model(nodes, inputs=SHAPES, initializers=_params(activations, True))


def contrib_model(activations: str) -> onnx.ModelProto:
    nodes = [
        helper.make_node("QuantizeLinear", ["a", "as", "az"], ["aq"]),
        helper.make_node("QuantizeLinear", ["b", "bs", "bz"], ["bq"]),
        helper.make_node(
            "QLinearConcat", ["as", "az", "bq", "bs", "bz", "aq", "as", "az"], ["jq"], domain=CONTRIB, axis=-3
        ),
        helper.make_node("DequantizeLinear", ["jq", "as", "az"], ["y"]),
    ]
    model = onnx_model(nodes, inputs=SHAPES, initializers=_params(activations, False))
    model.opset_import.append(helper.make_opsetid(CONTRIB, 1))
    return model


def check(model: onnx.ModelProto, target: str = "ansi-c") -> None:
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearLookup" in kernel_ops(compiled)
    assert_identical(model, compiled, spread_feeds(model, (0.5, 3.0, 15.0), 8))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_qdq_concat_matches_onnxruntime_to_the_bit(activations):
    check(qdq_model(activations))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_contrib_qlinear_concat(activations):
    check(contrib_model(activations))


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
def test_simd_targets(target):
    check(qdq_model("int8"), target)


def test_concat_of_integers_in_a_qoperator_model_moves_them():
    """A plain Concat of uint8 tensors (QOperator format): the integers are copied."""
    nodes = [
        helper.make_node("QuantizeLinear", ["a", "as", "az"], ["q"]),
        helper.make_node("Concat", ["q", "q"], ["t"], axis=1),
        helper.make_node("DequantizeLinear", ["t", "as", "az"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"a": SHAPES["a"]}, initializers=_params("uint8", False))
    compiled = nncg.compile(model, target="ansi-c", verify_ir=True)
    assert kernel_ops(compiled) == ["QuantizeLinear", "Concat", "DequantizeLinear"]
    x = (np.random.default_rng(1).standard_normal(SHAPES["a"]) * 8).astype(np.float32)
    expected = onnxruntime_outputs(model, {"a": x})[0]
    np.testing.assert_array_equal(run_compiled(compiled, [x])[0].reshape(expected.shape), expected)
