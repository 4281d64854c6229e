"""The four MLPerf Tiny inference benchmark networks as ONNX models with fixed-seed random weights.

Run `python benchmarks/models.py` to (re)write benchmarks/models/<name>.onnx; every run gives byte-identical files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

OPSET = 13
IR_VERSION = 8  # loadable by older runtimes than onnx 1.23's default
BN_EPSILON = 1e-3  # Keras' BatchNormalization default, as in the reference models
OUT_DIR = Path(__file__).resolve().parent / "models"

Kernel = int | tuple[int, int]  # square size, or (height, width)


def same_pads(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TensorFlow "same" padding along one axis: (begin, end); end gets the odd pixel."""
    out = math.ceil(size / stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


class Builder:
    """Collects nodes and random weights; each node's output tensor is named after the node."""

    def __init__(self, name: str, input_name: str, input_shape: tuple[int, ...], seed: int):
        self.name = name
        self.input = helper.make_tensor_value_info(input_name, TensorProto.FLOAT, input_shape)
        self.rng = np.random.default_rng(seed)
        self.nodes: list[onnx.NodeProto] = []
        self.weights: list[onnx.TensorProto] = []
        self.shapes = {input_name: tuple(input_shape)}  # tensor -> shape, batch included

    def weight(self, name: str, array: np.ndarray) -> str:
        self.weights.append(numpy_helper.from_array(np.asarray(array, np.float32), name))
        return name

    def node(self, op: str, name: str, inputs: list[str], shape: tuple[int, ...], **attrs) -> str:
        self.nodes.append(helper.make_node(op, inputs, [name], name=name, **attrs))
        self.shapes[name] = shape
        return name

    def he_normal(self, shape: tuple[int, ...], fan_in: int) -> np.ndarray:
        """He initialisation: keeps the activation variance roughly constant from layer to layer."""
        return self.rng.normal(0.0, math.sqrt(2.0 / fan_in), shape)

    def bias(self, size: int) -> np.ndarray:
        return self.rng.normal(0.0, 0.05, size)

    # --- layers; each takes the input tensor's name and returns the output tensor's name ---

    def conv(self, x: str, name: str, filters: int, kernel: Kernel, stride: int = 1, groups: int = 1) -> str:
        """Conv2D with bias and TensorFlow "same" padding, written as explicit (possibly asymmetric) pads."""
        n, c, h, w = self.shapes[x]
        kh, kw = (kernel, kernel) if isinstance(kernel, int) else kernel
        (top, bottom), (left, right) = same_pads(h, kh, stride), same_pads(w, kw, stride)
        fan_in = c // groups * kh * kw
        weight = self.weight(f"{name}.weight", self.he_normal((filters, c // groups, kh, kw), fan_in))
        bias = self.weight(f"{name}.bias", self.bias(filters))
        shape = (n, filters, math.ceil(h / stride), math.ceil(w / stride))
        pads = [top, left, bottom, right]
        attrs = {"kernel_shape": [kh, kw], "strides": [stride, stride], "pads": pads, "group": groups}
        return self.node("Conv", name, [x, weight, bias], shape, **attrs)

    def depthwise(self, x: str, name: str, stride: int = 1) -> str:
        """Depthwise 3x3 conv (one filter per channel, depth multiplier 1)."""
        channels = self.shapes[x][1]
        return self.conv(x, name, channels, 3, stride, groups=channels)

    def dense(self, x: str, name: str, units: int) -> str:
        """Fully connected layer as Gemm: y = x W^T + b, W stored [units, inputs] (transB=1)."""
        n, inputs = self.shapes[x]
        weight = self.weight(f"{name}.weight", self.he_normal((units, inputs), inputs))
        bias = self.weight(f"{name}.bias", self.bias(units))
        return self.node("Gemm", name, [x, weight, bias], (n, units), transB=1)

    def bn(self, x: str, name: str) -> str:
        """Inference BatchNormalization over axis 1 (channels, or features of a [N, F] tensor)."""
        channels = self.shapes[x][1]
        stats = {"scale": (0.5, 1.5), "bias": (-0.1, 0.1), "mean": (-0.1, 0.1), "var": (0.5, 1.5)}
        inputs = [self.weight(f"{name}.{k}", self.rng.uniform(lo, hi, channels)) for k, (lo, hi) in stats.items()]
        return self.node("BatchNormalization", name, [x, *inputs], self.shapes[x], epsilon=BN_EPSILON)

    def relu(self, x: str, name: str) -> str:
        return self.node("Relu", name, [x], self.shapes[x])

    def relu6(self, x: str, name: str) -> str:
        """ReLU6 as opset-13 Clip, whose bounds are (shared, scalar) constant inputs."""
        if not any(w.name == "relu6.min" for w in self.weights):
            self.weight("relu6.min", np.float32(0.0))
            self.weight("relu6.max", np.float32(6.0))
        return self.node("Clip", name, [x, "relu6.min", "relu6.max"], self.shapes[x])

    def add(self, a: str, b: str, name: str) -> str:
        return self.node("Add", name, [a, b], self.shapes[a])

    def average_pool(self, x: str, name: str) -> str:
        """Average over the whole remaining spatial extent, as Keras' AveragePooling2D(pool_size=x.shape[1:3])."""
        n, c, h, w = self.shapes[x]
        return self.node("AveragePool", name, [x], (n, c, 1, 1), kernel_shape=[h, w], strides=[h, w])

    def classifier(self, x: str, classes: int) -> str:
        """Global average pool, Flatten, Dense, Softmax: the head shared by the three classifiers."""
        x = self.average_pool(x, "pool")
        n, c, _, _ = self.shapes[x]
        x = self.node("Flatten", "flatten", [x], (n, c), axis=1)
        x = self.dense(x, "fc", classes)
        return self.node("Softmax", "softmax", [x], self.shapes[x], axis=1)

    def model(self, output: str, output_name: str) -> onnx.ModelProto:
        """The finished model; the last node's output is renamed `output_name`."""
        assert self.nodes[-1].output[0] == output
        self.nodes[-1].output[0] = output_name
        outputs = [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, self.shapes[output])]
        graph = helper.make_graph(self.nodes, self.name, [self.input], outputs, self.weights)
        model = helper.make_model(
            graph, producer_name="nncg-benchmarks", opset_imports=[helper.make_opsetid("", OPSET)]
        )
        model.ir_version = IR_VERSION
        # Record the intermediate shapes too (handy in viewers); strict mode fails on any mismatch.
        return onnx.shape_inference.infer_shapes(model, strict_mode=True)


def conv_bn(
    b: Builder, x: str, name: str, filters: int, kernel: Kernel, stride: int = 1, act: str | None = "relu"
) -> str:
    """Conv + BatchNormalization (+ activation): nodes <name>.conv, <name>.bn, <name>.<act>."""
    x = b.bn(b.conv(x, f"{name}.conv", filters, kernel, stride), f"{name}.bn")
    return getattr(b, act)(x, f"{name}.{act}") if act else x


def separable(b: Builder, x: str, name: str, filters: int, stride: int = 1, act: str = "relu") -> str:
    """Depthwise-separable block: depthwise 3x3 + BN + act, then pointwise 1x1 + BN + act."""
    x = b.depthwise(x, f"{name}.dw.conv", stride)
    x = getattr(b, act)(b.bn(x, f"{name}.dw.bn"), f"{name}.dw.{act}")
    return conv_bn(b, x, f"{name}.pw", filters, 1, act=act)


def dense_bn_relu(b: Builder, x: str, name: str, units: int) -> str:
    return b.relu(b.bn(b.dense(x, f"{name}.fc", units), f"{name}.bn"), f"{name}.relu")


# --- the four benchmark networks ------------------------------------------------------------------


def resnet8() -> onnx.ModelProto:
    """Image classification (CIFAR-10): ResNet-8 with three one-block residual stages of 16, 32, 64 filters."""
    b = Builder("resnet8", "image", (1, 3, 32, 32), seed=1)
    x = conv_bn(b, "image", "stem", 16, 3)
    for stage, (filters, stride) in enumerate([(16, 1), (32, 2), (64, 2)], start=1):
        name = f"stage{stage}"
        y = conv_bn(b, x, f"{name}.a", filters, 3, stride)
        y = conv_bn(b, y, f"{name}.b", filters, 3, act=None)
        if stride != 1:  # the shape changes: 1x1 strided conv (no BN) on the shortcut, as in the reference
            x = b.conv(x, f"{name}.shortcut", filters, 1, stride)
        x = b.relu(b.add(x, y, f"{name}.add"), f"{name}.relu")
    return b.model(b.classifier(x, 10), "probabilities")


def dscnn() -> onnx.ModelProto:
    """Keyword spotting (Speech Commands, 49 frames x 10 MFCC): DS-CNN small with 64 channels.

    Dropout (identity at inference) is left out. The reference pools 24x5 of the 25x5 map (int(49/2) rows);
    here the pool covers the whole map.
    """
    b = Builder("dscnn", "mfcc", (1, 1, 49, 10), seed=2)
    x = conv_bn(b, "mfcc", "stem", 64, (10, 4), stride=2)
    for block in range(1, 5):
        x = separable(b, x, f"block{block}", 64)
    return b.model(b.classifier(x, 12), "probabilities")


def mobilenet_v1_025() -> onnx.ModelProto:
    """Visual wake words (person / no person, 96x96 RGB): MobileNetV1 with width multiplier 0.25 and ReLU6."""
    b = Builder("mobilenet_v1_025", "image", (1, 3, 96, 96), seed=3)
    x = conv_bn(b, "image", "stem", 8, 3, stride=2, act="relu6")
    # (pointwise filters, depthwise stride) of the 13 separable layers: MobileNetV1's 64..1024 times 0.25.
    layers = [(16, 1), (32, 2), (32, 1), (64, 2), (64, 1), (128, 2), *[(128, 1)] * 5, (256, 2), (256, 1)]
    for i, (filters, stride) in enumerate(layers, start=1):
        x = separable(b, x, f"block{i}", filters, stride, act="relu6")
    return b.model(b.classifier(x, 2), "probabilities")


def autoencoder() -> onnx.ModelProto:
    """Anomaly detection (ToyADMOS, 5 frames x 128 mel bins): fully connected autoencoder with an 8-unit bottleneck."""
    b = Builder("autoencoder", "features", (1, 640), seed=4)
    x = "features"
    for i, units in enumerate([128] * 4 + [8] + [128] * 4, start=1):
        x = dense_bn_relu(b, x, f"layer{i}", units)
    return b.model(b.dense(x, "output", 640), "reconstruction")


MODELS: dict[str, Callable[[], onnx.ModelProto]] = {
    "resnet8": resnet8,
    "dscnn": dscnn,
    "mobilenet_v1_025": mobilenet_v1_025,
    "autoencoder": autoencoder,
}


def count_params_and_macs(model: onnx.ModelProto) -> tuple[int, int]:
    """Parameters of Conv, Gemm and BatchNormalization (BN statistics included, as Keras' total counts them)
    and multiply-accumulates of Conv and Gemm, for the model's static shapes."""
    model = onnx.shape_inference.infer_shapes(model, strict_mode=True)
    g = model.graph
    sizes = {t.name: list(t.dims) for t in g.initializer}
    shapes = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim] for v in (*g.input, *g.value_info, *g.output)}
    counted: set[str] = set()
    macs = 0
    for node in g.node:
        if node.op_type in ("Conv", "Gemm", "BatchNormalization"):
            counted.update(name for name in node.input if name in sizes)
        out = math.prod(shapes[node.output[0]])
        if node.op_type == "Conv":  # each output: (input channels / group) x kernel MACs
            macs += out * math.prod(sizes[node.input[1]][1:])
        elif node.op_type == "Gemm":  # each output: K MACs
            transposed = any(a.name == "transA" and a.i for a in node.attribute)
            macs += out * shapes[node.input[0]][0 if transposed else -1]
    return sum(math.prod(sizes[name]) for name in counted), macs


def main() -> None:
    OUT_DIR.mkdir(exist_ok=True)
    for name, build in MODELS.items():
        model = build()
        onnx.checker.check_model(model, full_check=True)
        path = OUT_DIR / f"{name}.onnx"
        path.write_bytes(model.SerializeToString())

        session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        (input_info,) = session.get_inputs()
        x = np.random.default_rng(0).standard_normal(input_info.shape).astype(np.float32)
        (y,) = session.run(None, {input_info.name: x})
        params, macs = count_params_and_macs(model)
        print(
            f"{path.name}: {path.stat().st_size} bytes, output {list(y.shape)} in [{y.min():.4f}, {y.max():.4f}], "
            f"{params} params, {macs} MACs"
        )


if __name__ == "__main__":
    main()
