"""onnxruntime's contrib QLinearAdd, QLinearAveragePool and QLinearGlobalAveragePool (com.microsoft),
loaded from a QOperator model, compiled to the integer kernels QDQ groups become and compared with
onnxruntime running the same model: bit-identical on every element, int8 and uint8, zero points
other than 0, inputs and outputs saturating at both ends, ansi-c and a SIMD target. And qdq.py's
notes on the nodes it writes are no ONNX attributes: a model carrying such names steers nothing."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import helper

import nncg
from nncg.verify import run_compiled

SHAPE = (1, 13, 6, 5)  # 13 channels: an avx2 vector of 8 and a scalar tail of 5
CONTRIB = "com.microsoft"
# activation type: zero points of the input, the second input and the output
ZEROS = {"uint8": (120, 131, 7), "int8": (-9, 4, -20)}


def _zero(activations: str, value: int) -> np.ndarray:
    return np.asarray(value, np.int8 if activations == "int8" else np.uint8)


def contrib_model(op: str, activations: str, attrs: dict | None = None) -> onnx.ModelProto:
    """x -> QuantizeLinear -> `op` (contrib) -> DequantizeLinear -> y; QLinearAdd adds x's square."""
    xz, bz, yz = ZEROS[activations]
    params = {
        "xs": np.float32(0.05), "xz": _zero(activations, xz), "bs": np.float32(0.03), "bz": _zero(activations, bz),
        "ys": np.float32(0.04), "yz": _zero(activations, yz),
    }  # fmt: skip
    nodes = [helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"])]
    if op == "QLinearAdd":
        nodes += [
            helper.make_node("Mul", ["x", "x"], ["x2"]),
            helper.make_node("QuantizeLinear", ["x2", "bs", "bz"], ["q2"]),
            helper.make_node(
                op, ["q", "xs", "xz", "q2", "bs", "bz", "ys", "yz"], ["r"], domain=CONTRIB, **(attrs or {})
            ),
        ]
    else:
        pool = {"kernel_shape": [3, 2], "strides": [2, 1], "pads": [1, 0, 1, 1]} if op == "QLinearAveragePool" else {}
        nodes.append(
            helper.make_node(op, ["q", "xs", "xz", "ys", "yz"], ["r"], domain=CONTRIB, **pool, **(attrs or {}))
        )
    nodes.append(helper.make_node("DequantizeLinear", ["r", "ys", "yz"], ["y"]))
    model = onnx_model(nodes, inputs={"x": SHAPE}, initializers=params)
    model.opset_import.append(helper.make_opsetid(CONTRIB, 1))
    return model


def check(model: onnx.ModelProto, op: str, target: str = "ansi-c") -> str:
    """Bit-identical to onnxruntime on inputs spread wide enough to saturate both ends; the C source."""
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert op in kernel_ops(compiled)
    rng = np.random.default_rng(3)
    for spread in (0.5, 3.0, 12.0):
        x = (rng.standard_normal(SHAPE) * spread).astype(np.float32)
        expected = onnxruntime_outputs(model, {"x": x})[0]
        ours = run_compiled(compiled, [x])[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)
    return compiled.source


OPS = ("QLinearAdd", "QLinearAveragePool", "QLinearGlobalAveragePool")


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("op", OPS)
def test_contrib_ops_match_onnxruntime_to_the_bit(op, activations):
    check(contrib_model(op, activations), op)


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
@pytest.mark.parametrize("op", OPS)
def test_contrib_ops_on_simd_targets(op, target, activations):
    """Vectorised over channels (tests/test_int8_vector_steps.py), saturating at both ends."""
    check(contrib_model(op, activations), op, target)


@pytest.mark.parametrize(
    "op, attrs",
    [
        ("QLinearAdd", {"nncg_low": 0.0, "nncg_high": 0.1}),
        ("QLinearAveragePool", {"nncg_u8_offset": 128}),
    ],
)
def test_attributes_named_like_nncg_notes_steer_nothing(op, attrs):
    """qdq.py once passed folded clamps and the uint8 pool offset as made-up attributes of these
    names: a model that carries them (onnxruntime refuses it) compiles to the same C as one without,
    which matches onnxruntime."""
    steered = nncg.compile(contrib_model(op, "int8", attrs), target="ansi-c").source
    assert _without_model_hash(steered) == _without_model_hash(check(contrib_model(op, "int8"), op))


def _without_model_hash(source: str) -> str:
    return "\n".join(line for line in source.splitlines() if "sha256=" not in line)
