"""Quantized Mul (issue 16): a Mul between DequantizeLinear nodes and a QuantizeLinear, which
onnxruntime fuses into its QLinearMul, and that op itself (com.microsoft), compiled to NNCG's integer
kernel and compared with onnxruntime running the same model: bit-identical on every element, int8
and uint8, zero points other than 0, of two tensors of one shape, broadcast, and by a constant,
inputs and outputs saturating at both ends, ansi-c and SIMD targets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, skip_unless_host_runs
from int8_models import assert_identical, contrib_binary_model, qdq_binary_model, spread_feeds, typed

import nncg

SHAPE = (1, 4, 5, 6)
# second operand's shape: the same, or broadcast over the channels or the rows
SECOND = {"same": SHAPE, "channels": (1, 4, 1, 1), "rows": (6,)}
# activation type: zero points of a, b and the product
ZEROS = {"uint8": (131, 118, 100), "int8": (7, -12, -30)}


def _params(activations: str) -> dict[str, np.ndarray]:
    za, zb, zy = ZEROS[activations]
    return {
        "as": np.float32(0.04), "az": typed(activations, za), "bs": np.float32(0.03),
        "bz": typed(activations, zb), "ys": np.float32(0.011), "yz": typed(activations, zy),
    }  # fmt: skip


def qdq_model(activations: str, second: str, constant: bool = False) -> onnx.ModelProto:
    """x * z between QuantizeLinear/DequantizeLinear pairs; z a graph input or a quantized constant."""
    return qdq_binary_model("Mul", SHAPE, SECOND[second], _params(activations), constant)


def contrib_model(activations: str, second: str) -> onnx.ModelProto:
    return contrib_binary_model("QLinearMul", SHAPE, SECOND[second], _params(activations))


def check(model: onnx.ModelProto, target: str = "ansi-c") -> None:
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "QLinearMul" in kernel_ops(compiled)
    assert_identical(model, compiled, spread_feeds(model, (0.5, 2.0, 9.0), 9))


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


@pytest.mark.parametrize("second", sorted(SECOND))
@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
def test_simd_targets(target, activations, second):
    """Vectorised (tests/test_int8_vector_steps.py), saturating at both ends, broadcast operands."""
    check(qdq_model(activations, second), target)
