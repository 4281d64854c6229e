"""Pad and nearest Resize of quantized tensors (issue 16): between a DequantizeLinear and a
QuantizeLinear of one scale and zero point they move the integers (Pad's constant value quantised,
0 becoming the zero point); compared with onnxruntime running the same model, bit-identical on every
element, int8 and uint8, zero points other than 0, inputs saturating at both ends, ansi-c and SIMD
targets. A linear Resize stays float between explicit (de)quantise layers."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import assert_identical, qdq_around, spread_feeds
from onnx import helper

import nncg

SHAPE = (1, 3, 5, 6)
ZEROS = {"uint8": 140, "int8": -17}
PADS = np.array([0, 0, 1, 2, 0, 0, 2, 1], np.int64)
# name: (op, attributes, extra initializers, extra inputs after x)
CASES = {
    "pad_zero": ("Pad", {}, {"pads": PADS}, ["pads"]),
    "pad_value": ("Pad", {}, {"pads": PADS, "value": np.float32(0.37)}, ["pads", "value"]),
    "pad_saturating_value": ("Pad", {}, {"pads": PADS, "value": np.float32(-50.0)}, ["pads", "value"]),
    "pad_reflect": ("Pad", {"mode": "reflect"}, {"pads": PADS}, ["pads"]),
    "pad_edge": ("Pad", {"mode": "edge"}, {"pads": PADS}, ["pads"]),
    "resize_twice": ("Resize", {}, {"scales": np.array([1, 1, 2, 2], np.float32)}, ["", "scales"]),
    "resize_odd_sizes": (
        "Resize",
        {"nearest_mode": "floor", "coordinate_transformation_mode": "asymmetric"},
        {"sizes": np.array([1, 3, 13, 17], np.int64)},
        ["", "", "sizes"],
    ),  # fmt: skip
}


def qdq_model(case: str, activations: str) -> onnx.ModelProto:
    op, attrs, extra, inputs = CASES[case]
    dtype = np.int8 if activations == "int8" else np.uint8
    params = {"s": np.float32(0.045), "z": dtype(ZEROS[activations]), **extra}
    nodes = qdq_around(op, inputs, ("s", "z"), ("s", "z"), **attrs)
    return onnx_model(nodes, inputs={"x": SHAPE}, initializers=params, opset=18)


def check(model: onnx.ModelProto, op: str, target: str = "ansi-c") -> None:
    skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert op in kernel_ops(compiled) and kernel_ops(compiled).count("QuantizeLinear") == 1
    assert_identical(model, compiled, spread_feeds(model, (0.5, 3.0, 12.0), 6))


@pytest.mark.parametrize("activations", ["uint8", "int8"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_moves_of_integers_match_onnxruntime_to_the_bit(case, activations):
    check(qdq_model(case, activations), CASES[case][0])


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512"])
def test_simd_targets(target):
    check(qdq_model("pad_value", "int8"), "Pad", target)
    check(qdq_model("resize_odd_sizes", "uint8"), "Resize", target)


def test_linear_resize_stays_float_between_explicit_layers():
    model = qdq_model("resize_twice", "uint8")
    model.graph.node[2].attribute.append(helper.make_attribute("mode", "linear"))
    ops = kernel_ops(nncg.compile(model, target="ansi-c"))
    assert ops.count("QuantizeLinear") == 2 and ops.count("DequantizeLinear") == 2
