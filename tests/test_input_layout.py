"""A model's own input layout comes from its graph (nncg/frontend/layout.py), not from producer_name:
an input is NHWC when the graph converts it to NCHW before computing on it, as tf2onnx does."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import onnx_model, weights
from onnx import helper

import nncg
from nncg.frontend.layout import graph_layout, model_layout, with_input_layout
from nncg.verify import build_model, random_inputs, reference_outputs

NHWC_TO_NCHW = helper.make_node("Transpose", ["x"], ["t"], perm=[0, 3, 1, 2])


def conv_after(nodes: list, channels: int = 3, shape=(1, 5, 6, 3), producer: str = "") -> onnx.ModelProto:
    """`nodes` (ending in value t, NCHW) then a 1x1 Conv to two channels."""
    conv = helper.make_node("Conv", ["t", "w"], ["y"])
    h, w = (shape[1], shape[2]) if shape[3] == channels else (shape[2], shape[3])
    inits = {"w": weights(2, channels, 1, 1), "half": np.array(0.5, np.float32), "per_c": weights(3)}
    inits["shape"] = np.array([1, channels, h, w], np.int64)
    used = {i for n in nodes for i in n.input}
    model = onnx_model(
        [*nodes, conv],
        inputs={"x": list(shape)},
        outputs={"y": [1, 2, h, w]},
        initializers={k: v for k, v in inits.items() if k in used or k == "w"},
    )
    model.producer_name = producer
    return model


def test_tf2onnx_transpose_at_the_input_means_nhwc_whatever_the_producer():
    model = conv_after([NHWC_TO_NCHW], producer="anything")
    assert graph_layout(model) == model_layout(model) == "nhwc"


def test_producer_name_alone_says_nothing():
    conv = helper.make_node("Conv", ["x", "w"], ["y"])
    model = onnx_model(
        [conv], inputs={"x": [1, 3, 5, 6]}, outputs={"y": [1, 2, 5, 6]}, initializers={"w": weights(2, 3, 1, 1)}
    )
    model.producer_name = "tf2onnx"
    assert graph_layout(model) == "nchw"
    assert "NHWC" not in nncg.compile(model).header


def test_one_channel_reshape_and_axis_blind_ops_before_the_transpose():
    reshape = helper.make_node("Reshape", ["x", "shape"], ["t"])
    assert graph_layout(conv_after([reshape], channels=1, shape=(1, 5, 6, 1))) == "nhwc"
    rescale = [
        helper.make_node("Mul", ["x", "half"], ["m"]),
        helper.make_node("Transpose", ["m"], ["t"], perm=[0, 3, 1, 2]),
    ]
    assert graph_layout(conv_after(rescale)) == "nhwc"
    # A per-channel Mul depends on the layout: the graph no longer shows it, ONNX's NCHW is assumed.
    per_channel = [
        helper.make_node("Mul", ["x", "per_c"], ["m"]),
        helper.make_node("Transpose", ["m"], ["t"], perm=[0, 3, 1, 2]),
    ]
    assert graph_layout(conv_after(per_channel)) == "nchw"
    assert model_layout(conv_after(per_channel), default="nhwc") == "nchw"


def test_axis_blind_ops_alone_say_nothing():
    """Relu then the output: no conversion anywhere, so the input is ONNX's NCHW."""
    relu = onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": [1, 2, 3, 4]}, outputs={"y": [1, 2, 3, 4]})
    assert graph_layout(relu) == "nchw"
    branch = [NHWC_TO_NCHW, helper.make_node("Relu", ["x"], ["r"])]  # x also read as it is
    model = conv_after(branch)
    model.graph.output.append(helper.make_tensor_value_info("r", onnx.TensorProto.FLOAT, [1, 5, 6, 3]))
    assert graph_layout(model) == "nchw"


def test_no_image_inputs_leave_the_default():
    relu = onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": [2, 3]}, outputs={"y": [2, 3]})
    assert graph_layout(relu) is None
    assert model_layout(relu) == "nchw" and model_layout(relu, default="nhwc") == "nhwc"


def test_with_input_layout_is_read_back_from_the_graph():
    nhwc = conv_after([NHWC_TO_NCHW])
    assert graph_layout(with_input_layout(nhwc, "nchw")) == "nchw"
    nchw = onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": [1, 2, 3, 4]}, outputs={"y": [1, 2, 3, 4]})
    assert graph_layout(with_input_layout(nchw, "nhwc")) == "nhwc"
    assert with_input_layout(nhwc, "nchw").producer_name == nhwc.producer_name


@pytest.mark.parametrize("layout", (None, "nchw"))
def test_nhwc_model_compiles_in_either_layout(layout, tmp_path):
    model = conv_after([NHWC_TO_NCHW])
    compiled = nncg.compile(model, input_layout=layout)
    expected_note = "row-major NHWC" if layout is None else "row-major NCHW"
    assert expected_note in compiled.header
    x = random_inputs([type("Spec", (), {"shape": (1, 5, 6, 3)})], 0)[0]
    image = x if layout is None else x.transpose(0, 3, 1, 2)
    out = build_model(compiled, tmp_path).run([np.ascontiguousarray(image)])[0]
    np.testing.assert_allclose(out, reference_outputs(model, [model.graph.input[0]], [x])[0], rtol=1e-5, atol=1e-6)
