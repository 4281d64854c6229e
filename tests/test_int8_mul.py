"""Quantized Mul (issue 16): a Mul between DequantizeLinear nodes and a QuantizeLinear, which
onnxruntime fuses into its QLinearMul, and that op itself (com.microsoft), compiled to NNCG's integer
kernel and compared with onnxruntime running the same model: bit-identical on every element, int8
and uint8, zero points other than 0, of two tensors of one shape, broadcast, and by a constant,
inputs and outputs saturating at both ends, ansi-c and SIMD targets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import helper

import nncg
from nncg.verify import run_compiled

CONTRIB = "com.microsoft"
SHAPE = (1, 4, 5, 6)
# second operand's shape: the same, or broadcast over the channels or the rows
SECOND = {"same": SHAPE, "channels": (1, 4, 1, 1), "rows": (6,)}
# activation type: zero points of a, b and the product
ZEROS = {"uint8": (131, 118, 100), "int8": (7, -12, -30)}


def _typed(activations: str, value) -> np.ndarray:
    return np.asarray(value, np.int8 if activations == "int8" else np.uint8)


def _params(activations: str) -> dict[str, np.ndarray]:
    za, zb, zy = ZEROS[activations]
    return {
        "as": np.float32(0.04), "az": _typed(activations, za), "bs": np.float32(0.03),
        "bz": _typed(activations, zb), "ys": np.float32(0.011), "yz": _typed(activations, zy),
    }  # fmt: skip


def qdq_model(activations: str, second: str, constant: bool = False) -> onnx.ModelProto:
    """x * z between QuantizeLinear/DequantizeLinear pairs; z a graph input or a quantized constant."""
    params = _params(activations)
    inputs = {"x": SHAPE}
    if constant:
        rng = np.random.default_rng(2)
        low, high = np.iinfo(params["bz"].dtype).min, np.iinfo(params["bz"].dtype).max
        params["zq"] = rng.integers(low, high + 1, SECOND[second]).astype(params["bz"].dtype)
        b = [helper.make_node("DequantizeLinear", ["zq", "bs", "bz"], ["db"])]
    else:
        inputs["z"] = SECOND[second]
        b = [
            helper.make_node("QuantizeLinear", ["z", "bs", "bz"], ["zq"]),
            helper.make_node("DequantizeLinear", ["zq", "bs", "bz"], ["db"]),
        ]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "as", "az"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "as", "az"], ["da"]),
        *b,
        helper.make_node("Mul", ["da", "db"], ["m"]),
        helper.make_node("QuantizeLinear", ["m", "ys", "yz"], ["mq"]),
        helper.make_node("DequantizeLinear", ["mq", "ys", "yz"], ["y"]),
    ]
    return onnx_model(nodes, inputs=inputs, initializers=params)


def contrib_model(activations: str, second: str) -> onnx.ModelProto:
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "as", "az"], ["xq"]),
        helper.make_node("QuantizeLinear", ["z", "bs", "bz"], ["zq"]),
        helper.make_node("QLinearMul", ["xq", "as", "az", "zq", "bs", "bz", "ys", "yz"], ["mq"], domain=CONTRIB),
        helper.make_node("DequantizeLinear", ["mq", "ys", "yz"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": SHAPE, "z": SECOND[second]}, initializers=_params(activations))
    model.opset_import.append(helper.make_opsetid(CONTRIB, 1))
    return model


def check(model: onnx.ModelProto, target: str = "ansi-c") -> None:
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearMul" in kernel_ops(compiled)
    rng = np.random.default_rng(9)
    shapes = {i.name: tuple(d.dim_value for d in i.type.tensor_type.shape.dim) for i in model.graph.input}
    for spread in (0.5, 2.0, 9.0):
        feeds = {name: (rng.standard_normal(shape) * spread).astype(np.float32) for name, shape in shapes.items()}
        expected = onnxruntime_outputs(model, feeds)[0]
        ours = run_compiled(compiled, list(feeds.values()))[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("second", sorted(SECOND))
def test_qdq_mul_matches_onnxruntime_to_the_bit(activations, second):
    check(qdq_model(activations, second))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_qdq_mul_by_a_constant(activations):
    check(qdq_model(activations, "channels", constant=True))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
def test_contrib_qlinear_mul(activations):
    check(contrib_model(activations, "rows"))


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
def test_simd_targets(target):
    check(qdq_model("int8", "same"), target)
