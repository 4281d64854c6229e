"""The Keras int8 route (issue 16): the digits CNN of test_keras_route, trained on scikit-learn's digits,
quantised to full integer by the TFLite converter with a representative dataset (float input and output,
int8 inside), converted to ONNX by tf2onnx: a QDQ model (QuantizeLinear/DequantizeLinear around float
operators, no QLinear operators) that onnxruntime runs like the TFLite interpreter, and whose C must give
TFLite's class for every test image. The other route, the
float ONNX of the Keras model quantised by nncg.quantize, is checked against Keras. Skipped without
tensorflow, tf2onnx or scikit-learn (the keras extra)."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
import onnx
import pytest
from helpers import skip_unless_host_runs

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # TensorFlow's C++ start-up log
tf = pytest.importorskip("tensorflow")
tf2onnx = pytest.importorskip("tf2onnx")
datasets = pytest.importorskip("sklearn.datasets")
keras = pytest.importorskip("keras")

from test_keras_route import digits_cnn  # noqa: E402

import nncg  # noqa: E402
from nncg.frontend.keras_export import keras_to_onnx  # noqa: E402
from nncg.frontend.layout import model_layout  # noqa: E402
from nncg.verify import build_model, reference_session  # noqa: E402

# What tf2onnx 1.17 writes for the quantised digits CNN: float operators between QDQ pairs.
QDQ_OPS = {
    "QuantizeLinear", "DequantizeLinear", "Conv", "LeakyRelu", "MaxPool", "Transpose", "Reshape", "MatMul", "Add",
    "Softmax",
}  # fmt: skip
CALIBRATION_IMAGES = 200


def full_integer_tflite(model, images: np.ndarray) -> bytes:
    """The TFLite converter's full-integer model: int8 weights and activations, calibrated on `images`
    (the representative dataset), float input and output (as NNCG's C takes and gives them)."""
    converter = tf.lite.TFLiteConverter.from_keras_model(model)
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    converter.representative_dataset = lambda: ([image[None]] for image in images)
    converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
    return converter.convert()


def tflite_outputs(model: bytes, images: np.ndarray) -> np.ndarray:
    interpreter = tf.lite.Interpreter(model_content=model)
    interpreter.allocate_tensors()
    (given,), (taken,) = interpreter.get_input_details(), interpreter.get_output_details()
    outputs = []
    for image in images:
        interpreter.set_tensor(given["index"], image[None])
        interpreter.invoke()
        outputs.append(interpreter.get_tensor(taken["index"])[0])
    return np.stack(outputs)


@pytest.fixture(scope="module")
def digits(tmp_path_factory):
    """The trained Keras model, the ONNX conversion of its full-integer TFLite model, the test images,
    TFLite's outputs on them and the calibration (representative) images."""
    keras.utils.set_random_seed(0)
    data = datasets.load_digits()
    x = (data.images / 16.0).astype(np.float32)[..., None]
    order = np.random.default_rng(0).permutation(len(x))
    test, train = order[:360], order[360:]
    model = digits_cnn()
    model.compile(optimizer="adam", loss="sparse_categorical_crossentropy", metrics=["accuracy"])
    model.fit(x[train], data.target[train], epochs=8, batch_size=32, verbose=0)
    path = tmp_path_factory.mktemp("tflite") / "digits_int8.tflite"
    path.write_bytes(full_integer_tflite(model, x[train][:CALIBRATION_IMAGES]))
    proto, _ = tf2onnx.convert.from_tflite(str(path), opset=17)
    tflite = tflite_outputs(path.read_bytes(), x[test])
    return {
        "model": model, "onnx": proto, "x": x[test], "y": data.target[test], "tflite": tflite,
        "calibration": x[train][:CALIBRATION_IMAGES],
    }  # fmt: skip


def test_tf2onnx_writes_a_qdq_model(digits):
    proto = digits["onnx"]
    onnx.checker.check_model(proto, full_check=True)
    counts = Counter(node.op_type for node in proto.graph.node)
    print("tf2onnx ops:", ", ".join(f"{op} {n}" for op, n in sorted(counts.items())))
    assert set(counts) == QDQ_OPS
    (image,) = proto.graph.input
    assert image.type.tensor_type.elem_type == onnx.TensorProto.FLOAT  # quantised inside the graph


def test_onnxruntime_classifies_the_digits_like_tflite(digits):
    """onnxruntime runs LeakyRelu and Softmax in float between DequantizeLinear and QuantizeLinear,
    TFLite in integers (fixed-point multipliers, a softmax table), so the probabilities may differ by a
    few output steps of 1/256; the classes agree."""
    proto = digits["onnx"]
    run = reference_session(proto)
    name = proto.graph.input[0].name
    onnx_out = np.concatenate([run.run(None, {name: image[None]})[0] for image in digits["x"]])
    tflite, y = digits["tflite"], digits["y"]
    steps = np.abs(onnx_out - tflite) * 256
    same = float(np.mean(onnx_out.argmax(1) == tflite.argmax(1)))
    accuracy = {"TFLite": np.mean(tflite.argmax(1) == y), "onnxruntime": np.mean(onnx_out.argmax(1) == y)}
    print(
        f"digits int8: accuracy TFLite {accuracy['TFLite']:.4f}, ONNX in onnxruntime {accuracy['onnxruntime']:.4f}; "
        f"same class {same:.4f}; outputs identical {np.mean(steps == 0):.4f}, at most {steps.max():.0f} steps apart"
    )
    assert accuracy["TFLite"] > 0.9, "the digits CNN did not train"
    assert same >= 0.99 and abs(accuracy["TFLite"] - accuracy["onnxruntime"]) <= 1 / len(y)
    assert steps.max() <= 8


def test_the_float_model_quantised_by_nncg_classifies_like_keras(digits):
    """The other route: Keras to float ONNX (tf2onnx, as nncg-onnx model.keras does), then nncg.quantize
    on the same calibration images; the QDQ model keeps the NHWC input of tf2onnx's models. int8 rounding
    can flip an image whose two best classes are a few steps apart: at most 2 % of them (7 of 360)."""
    proto = keras_to_onnx(digits["model"])
    name = proto.graph.input[0].name
    qdq = nncg.quantize(proto, {name: digits["calibration"][:, None]}, activations="int8")
    assert model_layout(qdq) == "nhwc"
    run = reference_session(qdq)
    out = np.concatenate([run.run(None, {name: image[None]})[0] for image in digits["x"]])
    keras_classes = digits["model"].predict(digits["x"], verbose=0).argmax(1)
    same = float(np.mean(out.argmax(1) == keras_classes))
    accuracy = {"Keras": np.mean(keras_classes == digits["y"]), "QDQ": np.mean(out.argmax(1) == digits["y"])}
    print(
        f"digits, nncg.quantize int8: accuracy Keras {accuracy['Keras']:.4f}, QDQ {accuracy['QDQ']:.4f}; "
        f"same class {same:.4f}"
    )
    assert same >= 0.98 and accuracy["QDQ"] >= accuracy["Keras"] - 0.02


def test_nncg_c_gives_tflites_class_for_every_image(digits, tmp_path):
    skip_unless_host_runs("ssse3")
    compiled = nncg.compile(digits["onnx"], target="ssse3")
    built = build_model(compiled, tmp_path)
    c_out = np.concatenate([built.run([image[None]])[0] for image in digits["x"]])
    accuracy = np.mean(c_out.argmax(1) == digits["y"])
    print(f"digits int8: NNCG C accuracy {accuracy:.4f}")
    # TFLite's class is one of NNCG's best: where onnxruntime's float softmax (which NNCG computes)
    # rounds two classes to the same step, TFLite's integer softmax may order them either way.
    best = c_out == c_out.max(axis=1, keepdims=True)
    assert best[np.arange(len(best)), digits["tflite"].argmax(1)].all()
