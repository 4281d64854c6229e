"""Unary ops on int8/uint8 as generation-time tables (issue 16): LeakyRelu, Sigmoid, HardSwish and Tanh
between DequantizeLinear and QuantizeLinear, and onnxruntime's QLinearLeakyRelu and QLinearSigmoid
(com.microsoft), compared with onnxruntime running the same model: every table entry, and every
output element of the compiled C, bit-identical; int8 and uint8, zero points other than 0, inputs
and outputs saturating at both ends, ansi-c and SIMD targets."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import (
    CONTRIB,
    assert_identical,
    compare,
    onnxruntime_outputs,
    qdq_around,
    random_feeds,
    spread_feeds,
    typed,
)
from onnx import TensorProto, helper, numpy_helper

import nncg
from nncg.errors import UnsupportedOpsError
from nncg.frontend.ops_qlookup import hard_swish, leaky_relu, logistic, lookup_table, tanh
from nncg.ir.kinds import DType

SHAPE = (2, 3, 5, 7)
FUNCTIONS = {"LeakyRelu": leaky_relu(0.13), "Sigmoid": logistic, "HardSwish": hard_swish, "Tanh": tanh}
ATTRS = {"LeakyRelu": {"alpha": 0.13}, "Sigmoid": {}, "HardSwish": {}, "Tanh": {}}
# activation type: x zero point, y scale, y zero point per op (Sigmoid's output in [0, 1])
PARAMS = {
    "uint8": {
        "x_zero": 140,
        "LeakyRelu": (0.03, 90),
        "Sigmoid": (1 / 300, 12),
        "HardSwish": (0.02, 30),
        "Tanh": (1 / 150, 120),
    },
    "int8": {
        "x_zero": -11,
        "LeakyRelu": (0.03, -40),
        "Sigmoid": (1 / 300, -120),
        "HardSwish": (0.02, -100),
        "Tanh": (1 / 150, -5),
    },
}


def _initializers(op: str, activations: str, x_scale: float = 0.06) -> dict[str, np.ndarray]:
    y_scale, y_zero = PARAMS[activations][op]
    x_zero = PARAMS[activations]["x_zero"]
    return {
        "xs": np.float32(x_scale), "xz": typed(activations, x_zero),
        "ys": np.float32(y_scale), "yz": typed(activations, y_zero),
    }  # fmt: skip


def qdq_model(op: str, activations: str) -> onnx.ModelProto:
    nodes = qdq_around(op, [], ("xs", "xz"), ("ys", "yz"), **ATTRS[op])
    return onnx_model(nodes, inputs={"x": SHAPE}, initializers=_initializers(op, activations), opset=17)


def contrib_model(op: str, activations: str, qop: str | None = None) -> onnx.ModelProto:
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["q"]),
        helper.make_node(qop or f"QLinear{op}", ["q", "xs", "xz", "ys", "yz"], ["fq"], domain=CONTRIB, **ATTRS[op]),
        helper.make_node("DequantizeLinear", ["fq", "ys", "yz"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": SHAPE}, initializers=_initializers(op, activations), opset=17)
    model.opset_import.append(helper.make_opsetid(CONTRIB, 1))
    return model


def check(model: onnx.ModelProto, target: str = "ansi-c") -> None:
    """Bit-identical to onnxruntime on inputs spread wide enough to saturate both ends."""
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert kernel_ops(compiled) == ["QuantizeLinear", "QLinearLookup", "DequantizeLinear"]
    assert_identical(model, compiled, spread_feeds(model, (0.7, 3.0, 20.0), 5))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("op", FUNCTIONS)
def test_qdq_unary_ops_match_onnxruntime_to_the_bit(op, activations):
    check(qdq_model(op, activations))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("op", ["LeakyRelu", "Sigmoid"])
def test_contrib_unary_ops_match_onnxruntime_to_the_bit(op, activations):
    check(contrib_model(op, activations))


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
def test_simd_targets(target):
    check(qdq_model("Sigmoid", "int8"), target)
    check(contrib_model("LeakyRelu", "uint8"), target)


@pytest.mark.parametrize("toolchain", ["aarch64-neon", "armhf"])
def test_cross_toolchains(toolchain):
    """The tables read on ARM (neon, and ansi-c under armhf) under qemu-user: bit-identical too."""
    tc = TOOLCHAINS[toolchain]
    if missing_tools(tc):
        pytest.skip(f"{', '.join(missing_tools(tc))} not installed (scripts/install-test-deps.sh installs it)")
    for model in (qdq_model("Sigmoid", "int8"), qdq_model("Tanh", "uint8")):
        compiled = nncg.compile(model, target=tc.target)
        run = {"cc": tc.cc, "extra_cflags": tc.flags, "runner": runner(tc)}
        result = compare(model, compiled, random_feeds(model, 3, 1), **run)
        assert result.max_steps == 0 and result.identical == 1.0, result


def _onnxruntime_table(op: str, activations: str, x: tuple, y: tuple) -> np.ndarray:
    """onnxruntime's output for every input value, from (scale, zero point) of input and output."""
    element = TensorProto.INT8 if activations == "int8" else TensorProto.UINT8
    params = [("xs", np.float32(x[0])), ("xz", typed(activations, x[1])), ("ys", np.float32(y[0]))]
    params.append(("yz", typed(activations, y[1])))
    nodes = [
        helper.make_node("DequantizeLinear", ["x", "xs", "xz"], ["d"]),
        helper.make_node(op, ["d"], ["f"], **ATTRS[op]),
        helper.make_node("QuantizeLinear", ["f", "ys", "yz"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes, "table", [helper.make_tensor_value_info("x", element, [256])],
        [helper.make_tensor_value_info("y", element, [256])],
        [numpy_helper.from_array(np.asarray(v), n) for n, v in params],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    low = DType(activations).range[0]
    return onnxruntime_outputs(model, {"x": np.arange(low, low + 256).astype(activations)})[0]


@pytest.mark.parametrize("op", FUNCTIONS)
def test_every_table_entry_matches_onnxruntime(op):
    """All 256 entries, over random scales and zero points (the QDQ group, which onnxruntime fuses
    into its QLinear op for LeakyRelu and Sigmoid and runs in float for HardSwish and Tanh)."""
    rng = np.random.default_rng(11)
    for trial in range(40):
        activations = ("uint8", "int8")[trial % 2]
        offset = 128 if activations == "uint8" else 0
        x = (float(np.float32(rng.uniform(0.002, 0.2))), int(rng.integers(-30, 30)) + offset)
        y = (float(np.float32(rng.uniform(0.002, 0.05))), int(rng.integers(-128, 128)) + offset)
        dtype = DType(activations)
        ours = lookup_table(FUNCTIONS[op], (*x, dtype), (*y, dtype))
        np.testing.assert_array_equal(ours, _onnxruntime_table(op, activations, x, y), err_msg=f"{x} {y}")


def test_nncg_own_qoperator_node_cannot_come_from_a_model():
    with pytest.raises(UnsupportedOpsError, match="QLinearHardSwish"):
        nncg.compile(contrib_model("HardSwish", "int8"), target="ansi-c")
