"""Build the paper's three example CNNs (ball, pedestrian, robot) as ONNX files.

Weights are fixed-seed random, so every run writes byte-identical models.
"""

import math
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

OPSET = 13  # Dropout takes its ratio as an input from opset 12 on
IR_VERSION = 8  # loadable by older runtimes than onnx 1.23's default
BN_EPSILON = 1e-3  # Keras' BatchNormalization default
OUT_DIR = Path(__file__).resolve().parent


def same_pads(size, kernel, stride):
    """TensorFlow "same" padding along one axis: (begin, end); end gets the extra pixel."""
    out = math.ceil(size / stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


class Net:
    """Appends layers to a single-input chain, tracking shape, parameters and MACs."""

    def __init__(self, name, input_shape, seed):
        self.name = name
        self.input_shape = input_shape  # (C, H, W), batch is always 1
        self.shape = input_shape
        self.rng = np.random.default_rng(seed)
        self.tensor = "image"
        self.nodes, self.weights = [], []
        self.counts = {}
        self.params = self.macs = 0

    def _add(self, kind, op, extra_inputs=(), **attrs):
        """Add one node named kind<N>; its output tensor gets the same name."""
        self.counts[kind] = self.counts.get(kind, 0) + 1
        name = f"{kind}{self.counts[kind]}"
        inputs = [self.tensor]
        for suffix, array in extra_inputs:
            self.weights.append(numpy_helper.from_array(array, f"{name}.{suffix}"))
            inputs.append(f"{name}.{suffix}")
        self.nodes.append(helper.make_node(op, inputs, [name], name=name, **attrs))
        self.tensor = name
        return name

    def _param(self, array):
        """Count a learned tensor (BN statistics included) and store it as float32."""
        self.params += array.size
        return array.astype(np.float32)

    def conv(self, filters, kernel, stride=1, padding="same", bias=True):
        c, h, w = self.shape
        kh, kw = (kernel, kernel) if isinstance(kernel, int) else kernel
        if padding == "same":
            (pt, pb), (pl, pr) = same_pads(h, kh, stride), same_pads(w, kw, stride)
        else:
            pt = pb = pl = pr = 0
        # He initialisation keeps the activation variance roughly constant per layer.
        std = math.sqrt(2.0 / (c * kh * kw))
        inputs = [("weight", self._param(self.rng.normal(0, std, (filters, c, kh, kw))))]
        if bias:
            inputs.append(("bias", self._param(self.rng.normal(0, 0.05, filters))))
        # Explicit pads rather than auto_pad, so the begin/end split is exactly TF's.
        self._add(
            "conv",
            "Conv",
            inputs,
            kernel_shape=[kh, kw],
            strides=[stride, stride],
            pads=[pt, pl, pb, pr],
        )
        oh = (h + pt + pb - kh) // stride + 1
        ow = (w + pl + pr - kw) // stride + 1
        self.macs += filters * oh * ow * c * kh * kw
        self.shape = (filters, oh, ow)
        return self

    def bn(self):
        c = self.shape[0]
        u = self.rng.uniform
        stats = [
            ("scale", u(0.5, 1.5, c)),
            ("bias", u(-0.1, 0.1, c)),
            ("mean", u(-0.1, 0.1, c)),
            ("var", u(0.5, 1.5, c)),
        ]
        self._add(
            "bn",
            "BatchNormalization",
            [(k, self._param(v)) for k, v in stats],
            epsilon=BN_EPSILON,
        )
        return self

    def relu(self):
        self._add("relu", "Relu")
        return self

    def leaky(self, alpha=0.1):
        self._add("lrelu", "LeakyRelu", alpha=alpha)
        return self

    def pool(self):
        # 2x2/2 without padding floors odd sizes, as Keras' default "valid" pooling does.
        c, h, w = self.shape
        self._add("pool", "MaxPool", kernel_shape=[2, 2], strides=[2, 2])
        self.shape = (c, h // 2, w // 2)
        return self

    def dropout(self, ratio):
        # training_mode is left out, so the node is an identity at inference.
        self._add("dropout", "Dropout", [("ratio", np.array(ratio, np.float32))])
        return self

    def softmax(self):
        self._add("flatten", "Flatten", axis=1)
        self._add("softmax", "Softmax", axis=1)
        self.shape = (math.prod(self.shape),)
        return self

    def model(self, output_name):
        self.nodes[-1].output[0] = output_name
        graph = helper.make_graph(
            self.nodes,
            self.name,
            [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, *self.input_shape])],
            [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, [1, *self.shape])],
            self.weights,
        )
        model = helper.make_model(
            graph,
            producer_name="nncg-examples",
            opset_imports=[helper.make_opsetid("", OPSET)],
        )
        model.ir_version = IR_VERSION
        # Record intermediate shapes too (handy in viewers); strict mode fails on mismatch.
        return onnx.shape_inference.infer_shapes(model, strict_mode=True)


def ball():
    return (
        Net("ball", (1, 16, 16), seed=1)
        .conv(8, 5, stride=2)
        .relu()
        .pool()
        .conv(12, 3, padding="valid")
        .relu()
        .conv(2, 2, padding="valid")
        .softmax()
    ), "probabilities"


def pedestrian():
    # 36x18 -> 18x9 -> 9x4 -> 4x2 after the pools; the 4x2 conv then yields 1x1.
    return (
        Net("pedestrian", (1, 36, 18), seed=2)
        .conv(12, 3)
        .relu()
        .pool()
        .conv(32, 3)
        .leaky()
        .pool()
        .conv(64, 3)
        .leaky()
        .pool()
        .dropout(0.3)
        .conv(2, (4, 2), padding="valid")
        .softmax()
    ), "probabilities"


def robot():
    net = Net("robot", (3, 60, 80), seed=3)
    for i, filters in enumerate([8, 12, 8, 16, 20]):
        net.conv(filters, 3, bias=False).bn().leaky()  # no bias: BN's beta replaces it
        if i in (0, 2):
            net.pool()
    return net, "detections"


def main():
    for build in (ball, pedestrian, robot):
        net, output_name = build()
        model = net.model(output_name)
        onnx.checker.check_model(model, full_check=True)
        path = OUT_DIR / f"{net.name}.onnx"
        onnx.save(model, path)

        x = np.random.default_rng(0).uniform(0, 1, (1, *net.input_shape)).astype(np.float32)
        session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        (y,) = session.run(None, {"image": x})
        assert y.shape == (1, *net.shape), y.shape
        print(
            f"{path.name}: {path.stat().st_size} bytes, {net.params} params, "
            f"{net.macs} MACs, output {list(y.shape)} in [{y.min():.4f}, {y.max():.4f}]"
        )


if __name__ == "__main__":
    main()
