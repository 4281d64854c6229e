"""The four MLPerf Tiny v1.x reference models, built the way their published .tflite files were made:
written in Keras as the reference training scripts define them, converted Keras -> TFLite float
(tf.lite.TFLiteConverter) -> ONNX with tf2onnx's from_tflite (opset 17).

The layers follow mlcommons/tiny, benchmark/training/:
- mlperf_ic_resnet8: image_classification/keras_model.py, resnet_v1_eembc (32x32x3 CIFAR-10; 16/32/64
  filters as in v1.0 — later revisions widened the default to 26; BN after every 3x3 conv, unnormalised 1x1
  stride-2 shortcut convs on the second and third stacks, AveragePooling2D(8), Dense 10 softmax).
- mlperf_kws_dscnn: keyword_spotting/keras_model.py, ds_cnn (49x10x1 MFCC; Conv 64 10x4 stride 2, four
  DepthwiseConv 3x3 + Conv 1x1 blocks with BN+ReLU, AveragePooling2D(24x5), Dense 12 softmax; Dropout
  layers are identities at inference and vanish in the conversion).
- mlperf_vww_mobilenet: visual_wake_words/vww_model.py, mobilenet_v1 (96x96x3, alpha 0.25: 8 filters first,
  13 depthwise-separable blocks up to 256, AveragePooling2D over the 3x3 map, Dense 2 softmax).
- mlperf_ad_autoencoder: anomaly_detection/keras_model.py, get_model (640 inputs; four Dense 128 + BN + ReLU,
  Dense 8 + BN + ReLU, four more, Dense 640 linear).

Weights are seeded random, drawn here with numpy (not Keras' initialisers, whose streams change between
versions); BatchNormalization gets non-trivial moving mean and variance so the folding into the convs and
Gemms is exercised. TensorFlow and tf2onnx (the `keras` extra) are imported only when a model is built:
they are benchmark-only. The output is deterministic: the same bytes each time.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

SEED = 0
OPSET = 17
CALIBRATION_SAMPLES = 16  # as benchmarks/int8_suite.py calibrates nncg.quantize
CALIBRATION_SEED = 1234
# name -> input shape (NHWC, or features for the autoencoder); each model has its own fixed input size.
INPUTS = {
    "mlperf_ic_resnet8": (32, 32, 3),
    "mlperf_kws_dscnn": (49, 10, 1),
    "mlperf_vww_mobilenet": (96, 96, 3),
    "mlperf_ad_autoencoder": (640,),
}
MODELS = list(INPUTS)


def _input(keras, name: str):
    """Batch 1, as in the reference .tflite files, and a fixed name (Keras' default counts up per process)."""
    return keras.Input(INPUTS[name], batch_size=1, name="input")


def _conv_bn_relu(layers, x, filters, kernel, strides=1, relu=True):
    x = layers.Conv2D(filters, kernel, strides=strides, padding="same")(x)
    x = layers.BatchNormalization()(x)
    return layers.Activation("relu")(x) if relu else x


def _depthwise_separable(layers, x, filters, strides=1):
    x = layers.DepthwiseConv2D(3, strides=strides, padding="same")(x)
    x = layers.Activation("relu")(layers.BatchNormalization()(x))
    return _conv_bn_relu(layers, x, filters, 1)


def _classifier(layers, x, pool, classes):
    x = layers.Flatten()(layers.AveragePooling2D(pool_size=pool)(x))
    return layers.Dense(classes, activation="softmax")(x)


def resnet8(keras):
    layers = keras.layers
    inputs = _input(keras, "mlperf_ic_resnet8")
    x = _conv_bn_relu(layers, inputs, 16, 3)
    y = _conv_bn_relu(layers, _conv_bn_relu(layers, x, 16, 3), 16, 3, relu=False)
    x = layers.Activation("relu")(layers.add([x, y]))
    for filters in (32, 64):  # the strided stacks, with a 1x1 stride-2 conv on the identity path
        y = _conv_bn_relu(layers, _conv_bn_relu(layers, x, filters, 3, strides=2), filters, 3, relu=False)
        shortcut = layers.Conv2D(filters, 1, strides=2, padding="same")(x)
        x = layers.Activation("relu")(layers.add([shortcut, y]))
    return keras.Model(inputs, _classifier(layers, x, 8, 10), name="mlperf_ic_resnet8")


def dscnn(keras):
    layers = keras.layers
    height, width, _ = INPUTS["mlperf_kws_dscnn"]
    inputs = _input(keras, "mlperf_kws_dscnn")
    x = layers.Dropout(0.2)(_conv_bn_relu(layers, inputs, 64, (10, 4), strides=2))
    for _ in range(4):
        x = _depthwise_separable(layers, x, 64)
    x = layers.Dropout(0.4)(x)
    return keras.Model(inputs, _classifier(layers, x, (height // 2, width // 2), 12), name="mlperf_kws_dscnn")


# (filters, stride) of MobileNetV1's 13 depthwise-separable blocks at alpha 0.25.
VWW_BLOCKS = [(16, 1), (32, 2), (32, 1), (64, 2), (64, 1), (128, 2), *[(128, 1)] * 5, (256, 2), (256, 1)]


def mobilenet_v1(keras):
    layers = keras.layers
    inputs = _input(keras, "mlperf_vww_mobilenet")
    x = _conv_bn_relu(layers, inputs, 8, 3, strides=2)
    for filters, strides in VWW_BLOCKS:
        x = _depthwise_separable(layers, x, filters, strides)
    return keras.Model(inputs, _classifier(layers, x, tuple(x.shape[1:3]), 2), name="mlperf_vww_mobilenet")


def autoencoder(keras):
    layers = keras.layers
    inputs = _input(keras, "mlperf_ad_autoencoder")
    x = inputs
    for units in [128] * 4 + [8] + [128] * 4:
        x = layers.Activation("relu")(layers.BatchNormalization()(layers.Dense(units)(x)))
    outputs = layers.Dense(INPUTS["mlperf_ad_autoencoder"][0])(x)
    return keras.Model(inputs, outputs, name="mlperf_ad_autoencoder")


BUILDERS = {
    "mlperf_ic_resnet8": resnet8,
    "mlperf_kws_dscnn": dscnn,
    "mlperf_vww_mobilenet": mobilenet_v1,
    "mlperf_ad_autoencoder": autoencoder,
}


def seeded_weights(model, seed: int = SEED) -> None:
    """Replace every weight with a numpy draw of fixed seed: kernels He-normal, biases small, and
    BatchNormalization's gamma, beta, moving mean and moving variance away from 1/0 so folding matters."""
    rng = np.random.default_rng(seed)
    for layer in model.layers:
        values = []
        for weight in layer.weights:
            shape, name = tuple(weight.shape), weight.path.rsplit("/", 1)[-1]
            if name in ("kernel", "depthwise_kernel"):
                fan_in = math.prod(shape[:-1]) if name == "kernel" else math.prod(shape[:2])
                values.append(rng.normal(0.0, math.sqrt(2.0 / fan_in), shape))
            elif name in ("gamma", "moving_variance"):
                values.append(rng.uniform(0.5, 1.5, shape))
            else:  # bias, beta, moving_mean
                values.append(rng.normal(0.0, 0.1, shape))
        if values:
            layer.set_weights([v.astype(np.float32) for v in values])


def keras_model(name: str):
    """The reference architecture `name` with seeded weights (imports keras)."""
    import keras

    keras.backend.clear_session()  # layer names count up per process: start them afresh for the same bytes
    model = BUILDERS[name](keras)
    seeded_weights(model)
    return model


def calibration_samples(name: str) -> np.ndarray:
    """The representative dataset of the int8 conversion: seeded standard-normal inputs (no real data)."""
    shape = (CALIBRATION_SAMPLES, 1, *INPUTS[name])
    return np.random.default_rng(CALIBRATION_SEED).standard_normal(shape).astype(np.float32)


def tflite_bytes(model, int8_calibration: np.ndarray | None = None) -> bytes:
    """The float TFLite model, as the reference model_converter.py scripts write it; with `int8_calibration`
    the full-integer one (int8 weights and activations calibrated on those inputs, float input and output)."""
    import tensorflow as tf

    converter = tf.lite.TFLiteConverter.from_keras_model(model)
    if int8_calibration is not None:
        converter.optimizations = [tf.lite.Optimize.DEFAULT]
        converter.representative_dataset = lambda: ([sample] for sample in int8_calibration)
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
    with contextlib.redirect_stdout(io.StringIO()):  # Keras' export prints its signature
        return converter.convert()


@contextlib.contextmanager
def _native_stderr_kept_back():
    """TensorFlow's start-up and the TFLite converter log a dozen lines per model straight to file descriptor 2
    (absl logging, which TF_CPP_MIN_LOG_LEVEL does not all reach): hold them back, show them only on failure."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        except BaseException:
            os.dup2(saved, 2)
            held.seek(0)
            sys.stderr.write(held.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def onnx_bytes(name: str, int8: bool = False) -> bytes:
    """The MLPerf Tiny model `name` as tf2onnx converts its float .tflite file (with `int8`: its full-integer
    .tflite file, which tf2onnx writes as a QDQ model)."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    with _native_stderr_kept_back():
        import tf2onnx

        from nncg.frontend.keras_export import quiet_tf2onnx

        data = tflite_bytes(keras_model(name), calibration_samples(name) if int8 else None)
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / f"{name}.tflite"
            path.write_bytes(data)
            with quiet_tf2onnx():
                proto, _ = tf2onnx.convert.from_tflite(str(path), opset=OPSET)
    return canonical_names(proto).SerializeToString()


GENERATED = re.compile(r"__(\d+)")


def structural_order(graph) -> list:
    """The nodes in post-order from the graph's outputs, each node's inputs in their order: a topological
    order that depends on the wiring only, not on the names or on the order tf2onnx wrote the nodes in."""
    producer = {name: node for node in graph.node for name in node.output}
    order, seen = [], set()

    def visit(value: str) -> None:
        node = producer.get(value)
        if node is None or id(node) in seen:
            return
        seen.add(id(node))
        for name in node.input:
            visit(name)
        order.append(node)

    for output in graph.output:
        visit(output.name)
    return order + [node for node in graph.node if id(node) not in seen]


def _name_shared_dequantizes(graph) -> None:
    """Name each DequantizeLinear of an activation after the tensor it reads: tf2onnx names it after one of
    the tensor's consumers, whichever its set gives first (the residual Adds' inputs of a QDQ model)."""
    constants = {tensor.name for tensor in graph.initializer}
    kept = {value.name for value in graph.output}
    renamed, used = {}, set()
    for node in graph.node:
        if node.op_type != "DequantizeLinear" or node.input[0] in constants or node.output[0] in kept:
            continue
        name = f"{node.input[0]}_dequant"
        while name in used:  # two of the same tensor: numbered in structural order
            name += "_"
        used.add(name)
        node.name, renamed[node.output[0]], node.output[0] = name, name, name
    for node in graph.node:
        node.input[:] = [renamed.get(value, value) for value in node.input]


def canonical_names(model):
    """`model` with its nodes in structural order, tf2onnx's generated names renumbered in that order and the
    initializers in order of first use. tf2onnx numbers the names it makes (NAME__N) from a process-wide
    counter and its optimisers visit sets, so the numbers, the nodes' order (of QDQ models) and the
    initializers' order change from run to run; the wiring and every value do not. So the file is the same
    bytes each time."""
    graph, renamed, first_use = model.graph, {}, {}
    nodes = [type(node)() for node in graph.node]  # copies: ClearField drops the originals
    for copy, node in zip(nodes, structural_order(graph)):
        copy.CopyFrom(node)
    graph.ClearField("node")
    graph.node.extend(nodes)
    _name_shared_dequantizes(graph)

    def canonical(name: str) -> str:  # every __N in the name: tf2onnx nests them (X__68_DequantizeLinear__5)
        return GENERATED.sub(lambda match: f"__{renamed.setdefault(match.group(1), len(renamed) + 1)}", name)

    for node in graph.node:
        if not node.domain:  # tf2onnx sets the default domain explicitly on some nodes, on others not
            node.ClearField("domain")
        node.input[:] = [canonical(name) for name in node.input]
        node.output[:] = [canonical(name) for name in node.output]
        node.name = canonical(node.name)
        for name in node.input:
            first_use.setdefault(name, len(first_use))
    for value in [*graph.initializer, *graph.input, *graph.output, *graph.value_info]:
        value.name = canonical(value.name)
    ordered = sorted(graph.initializer, key=lambda tensor: (first_use.get(tensor.name, len(first_use)), tensor.name))
    graph.ClearField("initializer")
    graph.initializer.extend(ordered)
    ordered_info = sorted(graph.value_info, key=lambda value: value.name)
    graph.ClearField("value_info")
    graph.value_info.extend(ordered_info)
    return model
