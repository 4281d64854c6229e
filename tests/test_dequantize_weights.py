"""Quantised weights in float models: a constant DequantizeLinear (what tf2onnx writes on the weights
of models converted from TFLite, at opset 13) folds at compile time in every opset that has the op,
per tensor and per output channel, and the model is checked against onnxruntime. Integer ops NNCG
has no kernel for and dynamic quantisation are refused with an error that names them (the int8 path
itself: test_int8.py)."""

import numpy as np
import pytest
from helpers import compile_and_check, onnx_model
from onnx import TensorProto, helper

import nncg
from nncg.errors import NncgError, UnsupportedOpsError

RNG = np.random.default_rng(7)
C_OUT, C_IN = 8, 4


def dequantized_conv(opset: int, per_channel: bool, zero_point_type=np.int8):
    """Conv(x, DequantizeLinear(w_q, scale, zero_point)) with int8 (or uint8) weights."""
    info = np.iinfo(zero_point_type)
    w_q = RNG.integers(info.min, info.max, (C_OUT, C_IN, 3, 3), endpoint=True).astype(zero_point_type)
    scale_shape = (C_OUT,) if per_channel else ()
    scale = (RNG.random(scale_shape) * 0.02 + 0.001).astype(np.float32)
    zero_point = RNG.integers(-3, 4, scale_shape) + (0 if info.min < 0 else 128)
    axis = {"axis": 0} if per_channel else {}
    nodes = [
        helper.make_node("DequantizeLinear", ["w_q", "scale", "zero_point"], ["w"], **axis),
        helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1]),
    ]
    initializers = {"w_q": w_q, "scale": scale, "zero_point": zero_point.astype(zero_point_type)}
    return onnx_model(nodes, inputs={"x": (1, C_IN, 6, 6)}, initializers=initializers, opset=opset)


# DequantizeLinear has an axis (per-channel scales) from opset 13.
@pytest.mark.parametrize(
    ("opset", "per_channel"), [(10, False), (13, False), (13, True), (19, False), (19, True), (21, True)]
)
def test_constant_dequantize_linear_folds_in_every_opset(opset, per_channel):
    compile_and_check(dequantized_conv(opset, per_channel), "ansi-c")


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_uint8_weights_per_channel_on_vector_targets(target):
    compile_and_check(dequantized_conv(13, True, np.uint8), target)


def test_integer_ops_whose_int32_tensors_a_node_reads_are_refused_by_name():
    """A MatMulInteger whose int32 result is a graph output that a Cast to float32 also reads."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]),
        helper.make_node("MatMulInteger", ["q", "w"], ["i"]),
        helper.make_node("Cast", ["i"], ["y"], to=TensorProto.FLOAT),
    ]
    init = {"s": np.float32(0.1), "z": np.uint8(0), "w": np.ones((3, 2), np.uint8)}
    outputs = {"y": (2, 2), "i": helper.make_tensor_value_info("i", TensorProto.INT32, None)}
    model = onnx_model(nodes, inputs={"x": (2, 3)}, outputs=outputs, initializers=init)
    with pytest.raises(
        NncgError, match=r"MatMulInteger \(node .*\) writes an int32 tensor that a node reads, which NNCG does not"
    ):
        nncg.compile(model)


def test_dynamic_quantization_is_refused():
    nodes = [
        helper.make_node("DynamicQuantizeLinear", ["x"], ["q", "s", "z"]),
        helper.make_node("DequantizeLinear", ["q", "s", "z"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": (1, 2, 3, 3)})
    with pytest.raises(UnsupportedOpsError, match="dynamically quantised .* compile the float model instead"):
        nncg.compile(model)
