"""onnxruntime as the reference is exact on integer products: on x86 without VNNI its uint8 x int8
kernels add pairs of products in int16, which saturates (verify.reference_session). Here ConvInteger's
int32 sums, on inputs and weights at the ends of their ranges, equal numpy's exact sums for every
pairing of signedness."""

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from nncg.verify import reference_session

ELEM = {np.uint8: TensorProto.UINT8, np.int8: TensorProto.INT8}


def conv_integer(x_type, w_type, w: np.ndarray, w_zero) -> onnx.ModelProto:
    node = helper.make_node("ConvInteger", ["x", "w", "", "wz"], ["y"], pads=[1, 1, 1, 1])
    graph = helper.make_graph(
        [node],
        "conv_integer",
        [helper.make_tensor_value_info("x", ELEM[x_type], [1, 4, 5, 5])],
        [helper.make_tensor_value_info("y", TensorProto.INT32, None)],
        [numpy_helper.from_array(w.astype(w_type), "w"), numpy_helper.from_array(np.asarray(w_zero, w_type), "wz")],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def exact(x: np.ndarray, w: np.ndarray, w_zero: int) -> np.ndarray:
    """ConvInteger with padding 1 and stride 1 in int64: sum over c, kh, kw of x * (w - w_zero)."""
    padded = np.pad(x.astype(np.int64), ((0, 0), (0, 0), (1, 1), (1, 1)))
    taps = w.astype(np.int64) - w_zero
    out = np.zeros((1, w.shape[0], x.shape[2], x.shape[3]), np.int64)
    for i in range(x.shape[2]):
        for j in range(x.shape[3]):
            out[0, :, i, j] = np.einsum("chw,ochw->o", padded[0, :, i : i + 3, j : j + 3], taps)
    return out


@pytest.mark.parametrize("x_type", [np.uint8, np.int8])
@pytest.mark.parametrize("w_type", [np.uint8, np.int8])
def test_conv_integer_sums_are_exact_at_the_ends_of_the_ranges(x_type, w_type):
    rng = np.random.default_rng(0)
    info = np.iinfo(x_type)
    x = rng.choice([info.min, info.max], (1, 4, 5, 5)).astype(x_type)  # pairs of extremes saturate int16
    w_info = np.iinfo(w_type)
    w = rng.choice([w_info.min, w_info.max], (3, 4, 3, 3))
    w_zero = 3 if w_type == np.int8 else 131
    (y,) = reference_session(conv_integer(x_type, w_type, w, w_zero)).run(None, {"x": x})
    np.testing.assert_array_equal(y, exact(x, w, w_zero))
