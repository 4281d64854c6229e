"""A Keras-style NHWC model as tf2onnx writes it, built with onnx.helper (no TensorFlow needed).

Keras' MobileNetV2 (alpha 0.35, 96x96, 10 classes): the input is NHWC and every Conv is wrapped in
Transpose(0,3,1,2) ... Transpose(0,2,3,1), as tf2onnx emits a TensorFlow NHWC conv before its transpose
optimiser runs; BatchNormalization is folded into the conv bias (as Keras-to-ONNX converters do), ReLU6 (Clip),
the residual Adds, the global pool (ReduceMean over H and W) and the Dense layer (MatMul + Add) stay in NHWC.
So the benchmark shows what NNCG makes of layout transposes between every layer.
"""

from __future__ import annotations

import math

import numpy as np
import onnx
from onnx import TensorProto, helper

from .models import IR_VERSION, Builder, same_pads

NAME = "keras_mobilenet_nhwc"
OPSET = 13
TO_NCHW, TO_NHWC = [0, 3, 1, 2], [0, 2, 3, 1]


def make_divisible(value: float, divisor: int = 8) -> int:
    new_value = max(divisor, int(value + divisor / 2) // divisor * divisor)
    return new_value + divisor if new_value < 0.9 * value else new_value


class NhwcBuilder(Builder):
    """The benchmark models' builder with the tf2onnx conventions: NHWC shapes, Transposes around
    each conv, ReLU6 as Clip between shared constant bounds."""

    def __init__(self, size: int, seed: int):
        super().__init__(NAME, "input_1", (1, size, size, 3), seed)
        self.weight("relu6_min", np.float32(0.0))
        self.weight("relu6_max", np.float32(6.0))

    def conv(self, x: str, name: str, filters: int, kernel: int, stride: int = 1, depthwise: bool = False) -> str:
        """An NHWC conv as tf2onnx writes it: Transpose to NCHW, Conv with "same" pads, Transpose back."""
        n, h, w, c = self.shapes[x]
        groups, filters = (c, c) if depthwise else (1, filters)
        (top, bottom), (left, right) = same_pads(h, kernel, stride), same_pads(w, kernel, stride)
        oh, ow = math.ceil(h / stride), math.ceil(w / stride)
        shape = (filters, c // groups, kernel, kernel)
        weight = self.weight(f"{name}/kernel", self.rng.normal(0, math.sqrt(2 / math.prod(shape[1:])), shape))
        bias = self.weight(f"{name}/bias", self.rng.normal(0, 0.05, filters))
        nchw = self.node("Transpose", f"{name}__transpose_in", [x], (n, c, h, w), perm=TO_NCHW)
        attrs = {"kernel_shape": [kernel, kernel], "strides": [stride, stride], "pads": [top, left, bottom, right]}
        y = self.node("Conv", name, [nchw, weight, bias], (n, filters, oh, ow), group=groups, **attrs)
        return self.node("Transpose", f"{name}__transpose_out", [y], (n, oh, ow, filters), perm=TO_NHWC)

    def relu6(self, x: str, name: str) -> str:
        return self.node("Clip", name, [x, "relu6_min", "relu6_max"], self.shapes[x])

    def inverted_residual(self, x: str, name: str, expansion: int, filters: int, stride: int) -> str:
        channels = self.shapes[x][3]
        y = x
        if expansion != 1:  # Keras' first block has no expansion conv
            y = self.relu6(self.conv(x, f"{name}_expand", channels * expansion, 1), f"{name}_expand_relu")
        y = self.relu6(self.conv(y, f"{name}_depthwise", 0, 3, stride, depthwise=True), f"{name}_depthwise_relu")
        y = self.conv(y, f"{name}_project", filters, 1)
        return self.node("Add", f"{name}_add", [x, y], self.shapes[y]) if stride == 1 and channels == filters else y

    def head(self, x: str, classes: int) -> str:
        n, _, _, c = self.shapes[x]
        x = self.node("ReduceMean", "global_average_pooling2d", [x], (n, c), axes=[1, 2], keepdims=0)
        kernel = self.weight("predictions/kernel", self.rng.normal(0, math.sqrt(1 / c), (c, classes)))
        bias = self.weight("predictions/bias", np.zeros(classes))
        x = self.node("MatMul", "predictions/MatMul", [x, kernel], (n, classes))
        x = self.node("Add", "predictions/BiasAdd", [x, bias], (n, classes))
        return self.node("Softmax", "predictions", [x], (n, classes), axis=-1)


def keras_mobilenet_nhwc(size: int = 96, alpha: float = 0.35, classes: int = 10) -> onnx.ModelProto:
    b = NhwcBuilder(size, seed=5)
    x = b.relu6(b.conv("input_1", "Conv1", make_divisible(32 * alpha), 3, 2), "Conv1_relu")
    block = 0
    for t, c, n, s in [(1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1), (6, 160, 3, 2),
                       (6, 320, 1, 1)]:  # fmt: skip
        for i in range(n):
            x = b.inverted_residual(x, f"block_{block}", t, make_divisible(c * alpha), s if i == 0 else 1)
            block += 1
    x = b.relu6(b.conv(x, "Conv_1", 1280, 1), "out_relu")
    out = b.head(x, classes)
    graph = helper.make_graph(
        b.nodes, NAME, [helper.make_tensor_value_info("input_1", TensorProto.FLOAT, b.shapes["input_1"])],
        [helper.make_tensor_value_info(out, TensorProto.FLOAT, b.shapes[out])], b.weights,
    )  # fmt: skip
    model = helper.make_model(graph, producer_name="nncg-benchmarks", opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = IR_VERSION
    return onnx.shape_inference.infer_shapes(model, strict_mode=True)
