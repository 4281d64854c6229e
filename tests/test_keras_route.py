"""The Keras route (issue 17): a keras.Model, a .keras/.h5 file or a SavedModel folder goes through
tf2onnx in-process and compiles. A small CNN in the paper's style is trained on scikit-learn's digits
(8x8 images, shipped with the package) and the generated C must classify every test image as Keras does,
for each saved format, through the CLI and the API, for ansi-c and ssse3. Skipped without tensorflow,
tf2onnx or scikit-learn (the keras extra)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from helpers import skip_unless_host_runs

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # TensorFlow's C++ start-up log
pytest.importorskip("tensorflow")
pytest.importorskip("tf2onnx")
datasets = pytest.importorskip("sklearn.datasets")
keras = pytest.importorskip("keras")

import nncg  # noqa: E402
from nncg.cli import main  # noqa: E402
from nncg.errors import NncgError  # noqa: E402
from nncg.frontend.keras_export import keras_to_onnx  # noqa: E402
from nncg.verify import build_model  # noqa: E402

FORMATS = ("model.keras", "model.h5", "saved_model")
TARGETS = ("ansi-c", "ssse3")
ROOT = Path(__file__).resolve().parents[1]


def digits_cnn():
    L = keras.layers
    return keras.Sequential(
        [
            keras.Input((8, 8, 1)),
            L.Conv2D(16, 3, padding="same"), L.BatchNormalization(), L.LeakyReLU(0.1),
            L.Conv2D(16, 3, padding="valid"), L.BatchNormalization(), L.LeakyReLU(0.1),
            L.MaxPooling2D(2), L.Dropout(0.25), L.Flatten(),
            L.Dense(32), L.LeakyReLU(0.1), L.Dense(10), L.Softmax(),
        ],
        name="digits_cnn",
    )  # fmt: skip


@pytest.fixture(scope="module")
def digits(tmp_path_factory):
    """The trained model, its files, the test images (NHWC) and Keras' own predictions on them."""
    keras.utils.set_random_seed(0)
    data = datasets.load_digits()
    x = (data.images / 16.0).astype(np.float32)[..., None]
    y = data.target
    order = np.random.default_rng(0).permutation(len(x))
    test, train = order[:360], order[360:]
    model = digits_cnn()
    model.compile(optimizer="adam", loss="sparse_categorical_crossentropy", metrics=["accuracy"])
    model.fit(x[train], y[train], epochs=8, batch_size=32, verbose=0)
    folder = tmp_path_factory.mktemp("keras")
    model.save(folder / "model.keras")
    model.save(folder / "model.h5")
    model.export(str(folder / "saved_model"), verbose=False)
    probabilities = model.predict(x[test], verbose=0)
    accuracy = float(np.mean(probabilities.argmax(1) == y[test]))
    assert accuracy > 0.9, f"the digits CNN did not train: accuracy {accuracy}"
    print(f"digits accuracy: Keras {accuracy:.4f} on {len(test)} test images")
    return {"model": model, "folder": folder, "x": x[test], "y": y[test], "keras": probabilities}


def c_predictions(compiled, images: np.ndarray, workdir: Path) -> np.ndarray:
    """The compiled model's output on every image, one run of the C program per image (batch 1)."""
    built = build_model(compiled, workdir)
    return np.concatenate([built.run([image[None]])[0] for image in images])


def check_same_classes(compiled, digits, images, workdir):
    out = c_predictions(compiled, images, workdir)
    np.testing.assert_allclose(out, digits["keras"], atol=1e-4)
    assert (out.argmax(1) == digits["keras"].argmax(1)).all()
    return float(np.mean(out.argmax(1) == digits["y"]))


def test_converted_model_matches_keras_and_onnxruntime(digits):
    proto = keras_to_onnx(digits["model"])
    assert proto.producer_name == "tf2onnx"
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    (onnx_out,) = session.run(None, {proto.graph.input[0].name: digits["x"]})
    np.testing.assert_allclose(onnx_out, digits["keras"], atol=1e-5)
    assert (onnx_out.argmax(1) == digits["keras"].argmax(1)).all()
    # tf2onnx names nodes with a process-wide counter: reset per conversion, so the same model gives
    # the same ONNX (and so the same C) every time
    again = keras_to_onnx(digits["model"])
    assert again.SerializeToString(deterministic=True) == proto.SerializeToString(deterministic=True)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("saved", FORMATS)
def test_each_format_through_api_and_cli_classifies_as_keras(digits, saved, target, tmp_path, capsys):
    skip_unless_host_runs(target)
    path = digits["folder"] / saved
    compiled = nncg.compile(path, target=target)
    assert compiled.name == Path(saved).stem
    assert "row-major NHWC (channels last, as in Keras)" in compiled.header
    accuracy = check_same_classes(compiled, digits, digits["x"], tmp_path / "run")
    with capsys.disabled():
        print(f"digits accuracy {saved} {target}: NNCG C {accuracy:.4f}")
    # the CLI writes the same files, byte for byte: tf2onnx's output is deterministic
    assert main([str(path), "--target", target, "-o", str(tmp_path / "cli")]) == 0
    name = Path(saved).stem
    assert (tmp_path / "cli" / f"{name}.c").read_text() == compiled.source
    assert (tmp_path / "cli" / f"{name}.h").read_text() == compiled.header
    assert "dynamic batch dimension" in capsys.readouterr().err  # the batch-1 note


def test_cli_in_a_fresh_process_gives_the_same_c(digits, tmp_path):
    path = digits["folder"] / "model.keras"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TF_CPP_MIN_LOG_LEVEL": "3", "PYTHONHASHSEED": "7"}
    cmd = [sys.executable, "-m", "nncg.cli", str(path), "-o", str(tmp_path)]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "model.c").read_text() == nncg.compile(path).source


def test_keras_model_object_compiles(digits, tmp_path):
    model = digits["model"]
    compiled = nncg.compile(model, target="ssse3")
    assert compiled.name == "digits_cnn"
    check_same_classes(compiled, digits, digits["x"], tmp_path)
    # the whole test set as one batch, one run of the C
    name = compiled.inputs[0].name
    batch = nncg.compile(model, input_shapes={name: (len(digits["x"]), 8, 8, 1)})
    out = build_model(batch, tmp_path / "batch").run([digits["x"]])[0]
    assert (out.argmax(1) == digits["keras"].argmax(1)).all()


@pytest.mark.parametrize("target", TARGETS)
def test_input_layout_nchw_takes_transposed_images(digits, target, tmp_path):
    skip_unless_host_runs(target)
    compiled = nncg.compile(digits["folder"] / "model.keras", target=target, input_layout="nchw")
    assert compiled.inputs[0].shape == (1, 1, 8, 8)
    assert "row-major NCHW (channels first)" in compiled.header
    assert "input-layout=nchw" in compiled.source.splitlines()[0]
    check_same_classes(compiled, digits, digits["x"].transpose(0, 3, 1, 2), tmp_path)
    assert main([str(digits["folder"] / "model.keras"), "--input-layout", "nchw", "-o", str(tmp_path / "cli")]) == 0
    assert "row-major NCHW" in (tmp_path / "cli" / "model.h").read_text()


def kernels(source: str) -> list[str]:
    return [line for line in source.splitlines() if line.startswith("static NNCG_NOINLINE void ")]


@pytest.mark.parametrize("target", TARGETS)
def test_input_layout_transpose_cancels_with_tf2onnx_own(target, tmp_path):
    """Three channels: tf2onnx transposes NHWC to NCHW after the input; the Transpose --input-layout
    nchw inserts cancels with it, so the C has the same kernels and no copy of the input."""
    skip_unless_host_runs(target)
    keras.utils.set_random_seed(1)
    L = keras.layers
    model = keras.Sequential(
        [keras.Input((10, 12, 3)), L.Conv2D(8, 3, padding="same"), L.BatchNormalization(), L.ReLU(),
         L.MaxPooling2D(2), L.Conv2D(4, 3), L.Flatten(), L.Dense(5)]
    )  # fmt: skip
    proto = keras_to_onnx(model)
    assert "Transpose" in [n.op_type for n in proto.graph.node]
    nhwc = nncg.compile(proto, target=target)
    nchw = nncg.compile(proto, target=target, input_layout="nchw")
    assert len(kernels(nchw.source)) == len(kernels(nhwc.source))
    assert not any("ranspose" in k for k in kernels(nchw.source))
    x = np.random.default_rng(0).standard_normal((1, 10, 12, 3)).astype(np.float32)
    expected = model(x, training=False).numpy()
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(session.run(None, {proto.graph.input[0].name: x})[0], expected, atol=1e-5)
    for compiled, image in ((nhwc, x), (nchw, x.transpose(0, 3, 1, 2))):
        out = build_model(compiled, tmp_path / compiled.inputs[0].c_name).run([image])[0]
        np.testing.assert_allclose(out, expected, atol=1e-4)


def test_input_layout_nhwc_for_an_onnx_model(tmp_path):
    """The other way: an NCHW ONNX model whose C function takes NHWC."""
    from helpers import check_against_onnxruntime  # noqa: F401  (the helpers module is importable)

    x = onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 2, 3, 4])
    y = onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1, 2, 3, 4])
    graph = onnx.helper.make_graph([onnx.helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y])
    model = onnx.helper.make_model(graph, opset_imports=[onnx.helper.make_opsetid("", 17)])
    compiled = nncg.compile(model, input_layout="nhwc")
    assert compiled.inputs[0].shape == (1, 3, 4, 2)
    image = np.random.default_rng(0).standard_normal((1, 2, 3, 4)).astype(np.float32)
    out = build_model(compiled, tmp_path).run([image.transpose(0, 2, 3, 1)])[0]
    np.testing.assert_allclose(out, np.maximum(image, 0))


def one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("nncg-onnx: error: ")
    return lines[0]


def test_keras_file_without_tensorflow_is_one_line_exit_2(digits, monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "tensorflow", None)  # import tensorflow now raises ImportError
    out = tmp_path / "out"
    assert main([str(digits["folder"] / "model.keras"), "-o", str(out)]) == 2
    line = one_error_line(capsys)
    assert "needs tensorflow, which is not installed: pip install 'nncg[keras]'" in line
    assert not out.exists() or not any(out.iterdir())


def test_bad_keras_file_is_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "broken.keras"
    bad.write_bytes(b"not a zip")
    assert main([str(bad), "-o", str(tmp_path / "out")]) == 2
    assert "cannot load the Keras model" in one_error_line(capsys)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    assert main([str(tmp_path / "missing.h5"), "-o", str(tmp_path / "out")]) == 2
    assert "does not exist" in one_error_line(capsys)


def test_model_tensorflow_cannot_trace_is_one_error():
    """Keras allows names that TensorFlow's tracing rejects: the error names the model and the rule."""
    model = keras.Sequential([keras.Input((4, 4, 2)), keras.layers.Conv2D(3, 3)], name="my model")
    with pytest.raises(NncgError) as info:
        nncg.compile(model)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("tf2onnx cannot convert the Keras model 'my model': ValueError: ")
    assert "not a valid root scope name" in message
    trained = keras.Sequential([keras.Input((2,)), keras.layers.Dense(1)], name="after")  # Keras is unharmed
    trained.compile(optimizer="sgd", loss="mse")
    trained.fit(np.zeros((2, 2), np.float32), np.zeros((2, 1), np.float32), verbose=0)
    assert trained.layers[0].kernel.path.startswith("after/dense")  # not under "my model"


def test_bad_input_layout_argument():
    with pytest.raises(NncgError, match="input_layout must be one of 'nchw', 'nhwc'"):
        nncg.compile(b"", input_layout="NHWC")
    x = onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1, 4])
    graph = onnx.helper.make_graph([onnx.helper.make_node("Relu", ["x"], ["y"])], "g", [x], [x])
    model = onnx.helper.make_model(graph)
    with pytest.raises(NncgError, match="for models with 4-D"):
        nncg.compile(model, input_layout="nhwc")
