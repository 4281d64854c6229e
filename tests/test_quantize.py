"""nncg.quantize, nncg-quantize and nncg-onnx --calibration (issue 16): a float ONNX model and calibration
inputs (.npz, a folder of .npy files, arrays) to a QDQ model written by onnxruntime.quantization, checked
with onnx.checker, for per-channel weight scales on the output-channel axis, against the float model in
onnxruntime, for determinism, and for every mistake a user can make (one line, exit 2, nothing written).
Compiling the QDQ model needs NNCG's int8 compute path: those tests skip while NNCG refuses it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from helpers import ROOT, onnx_model, weights
from onnx import helper, numpy_helper
from test_cli_errors import old_files, snapshot

import nncg
from nncg import cli, quantize_cli
from nncg.errors import NncgError
from nncg.frontend.layout import model_layout
from nncg.verify import build_model, reference_session

ROBOT = ROOT / "examples" / "robot.onnx"
RNG_SEED = 7


def robot_samples(count: int, seed: int) -> np.ndarray:
    """Images in [0, 1) as the robot detector takes them, (count, 1, 3, 60, 80)."""
    return np.random.default_rng(seed).random((count, 1, 3, 60, 80), dtype=np.float32)


def dense_model() -> onnx.ModelProto:
    """One Gemm, y = x W^T + b: small enough for an exact error bound."""
    return onnx_model(
        [helper.make_node("Gemm", ["x", "w", "b"], ["y"], transB=1)],
        inputs={"x": [1, 16]},
        outputs={"y": [1, 8]},
        initializers={"w": weights(8, 16), "b": weights(8)},
    )


def layers_model() -> onnx.ModelProto:
    """Conv, ConvTranspose, Gemm (transB 1 and 0) and MatMul: each has its own output-channel axis."""
    nodes = [
        helper.make_node("Conv", ["x", "w_conv", "b_conv"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c"], ["r"]),
        helper.make_node("ConvTranspose", ["r", "w_convt", "b_convt"], ["t"], strides=[2, 2]),
        helper.make_node("Flatten", ["t"], ["f"]),
        helper.make_node("Gemm", ["f", "w_gemm", "b_gemm"], ["g"], transB=1),
        helper.make_node("MatMul", ["g", "w_matmul"], ["m"]),
        helper.make_node("Gemm", ["m", "w_gemm_n", "b_gemm_n"], ["y"]),
    ]
    initializers = {
        "w_conv": weights(4, 2, 3, 3), "b_conv": weights(4), "w_convt": weights(4, 3, 2, 2), "b_convt": weights(3),
        "w_gemm": weights(6, 192), "b_gemm": weights(6), "w_matmul": weights(6, 5), "w_gemm_n": weights(5, 7),
        "b_gemm_n": weights(7),
    }  # fmt: skip
    return onnx_model(nodes, inputs={"x": [1, 2, 4, 4]}, outputs={"y": [1, 7]}, initializers=initializers)


# weight -> (axis of its output channels, their number)
LAYER_AXES = {"w_conv": (0, 4), "w_convt": (1, 3), "w_gemm": (0, 6), "w_matmul": (1, 5), "w_gemm_n": (1, 7)}


def session(model: onnx.ModelProto) -> ort.InferenceSession:
    return reference_session(model)


def run_all(model: onnx.ModelProto, name: str, samples: np.ndarray) -> np.ndarray:
    run = session(model)
    return np.stack([run.run(None, {name: sample})[0] for sample in samples])


def initializers(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    return {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}


def weight_dequantizers(model: onnx.ModelProto) -> dict[str, onnx.NodeProto]:
    """The DequantizeLinear of each quantised weight, by the float weight's name."""
    return {
        node.input[0].removesuffix("_quantized"): node
        for node in model.graph.node
        if node.op_type == "DequantizeLinear" and node.input[0].endswith("_quantized")
    }


def input_scale(model: onnx.ModelProto, tensor: str) -> float:
    """The scale of the QuantizeLinear that quantises `tensor`."""
    (node,) = [n for n in model.graph.node if n.op_type == "QuantizeLinear" and n.input[0] == tensor]
    return float(initializers(model)[node.input[1]])


def output_scale(model: onnx.ModelProto) -> float:
    """The scale of the DequantizeLinear that gives the (one) graph output: one quantisation step of it."""
    (node,) = [n for n in model.graph.node if n.output[0] == model.graph.output[0].name]
    assert node.op_type == "DequantizeLinear"
    return float(initializers(model)[node.input[1]])


@pytest.fixture(scope="module")
def robot_qdq() -> onnx.ModelProto:
    return nncg.quantize(ROBOT, {"image": robot_samples(16, RNG_SEED)})


# --- the QDQ model -------------------------------------------------------------------------------


@pytest.mark.parametrize("activations, dtype", [("uint8", np.uint8), ("int8", np.int8)])
def test_weights_per_channel_on_the_output_channel_axis(activations, dtype):
    samples = np.random.default_rng(0).standard_normal((8, 1, 2, 4, 4)).astype(np.float32)
    qdq = nncg.quantize(layers_model(), {"x": samples}, activations=activations)
    onnx.checker.check_model(qdq, full_check=True)
    values = initializers(qdq)
    dequantizers = weight_dequantizers(qdq)
    for weight, (axis, channels) in LAYER_AXES.items():
        node = dequantizers[weight]
        assert helper.get_attribute_value(node.attribute[0]) == axis, weight
        assert values[node.input[0]].dtype == np.int8
        assert values[node.input[1]].shape == (channels,), weight  # one scale per output channel
        assert not values[node.input[2]].any()  # symmetric: zero points 0
    activation_zero_points = [values[n.input[2]] for n in qdq.graph.node if n.op_type == "QuantizeLinear"]
    assert activation_zero_points and all(z.dtype == dtype and z.shape == () for z in activation_zero_points)
    assert {o.domain for o in qdq.opset_import} == {""}  # the optimiser's unused imports dropped


SHIPPED = [ROOT / "examples" / f"{n}.onnx" for n in ("ball", "pedestrian", "robot")] + sorted(
    (ROOT / "benchmarks" / "models").glob("*.onnx")
)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_model_quantises(path):
    """The paper's networks and the MLPerf-Tiny-shaped ones (what the int8 compute path is checked on):
    a valid QDQ model, every Conv and Gemm weight with one scale per output channel (axis 0: their Gemms
    have transB=1), run by onnxruntime."""
    model = nncg.load_model(path)
    (image,) = model.graph.input
    shape = tuple(d.dim_value for d in image.type.tensor_type.shape.dim)
    samples = np.random.default_rng(0).random((4, *shape), dtype=np.float32)
    qdq = nncg.quantize(path, {image.name: samples})
    onnx.checker.check_model(qdq, full_check=True)
    values, dequantizers = initializers(qdq), weight_dequantizers(qdq)
    layers = [n for n in qdq.graph.node if n.op_type in ("Conv", "Gemm")]
    assert layers
    for node in layers:
        (weight,) = [w for w, dq in dequantizers.items() if dq.output[0] == node.input[1]]
        assert values[dequantizers[weight].input[1]].shape == (values[dequantizers[weight].input[0]].shape[0],)
    assert np.isfinite(run_all(qdq, image.name, samples)).all()


def test_per_tensor_weights_have_one_scale():
    samples = np.random.default_rng(0).standard_normal((8, 1, 2, 4, 4)).astype(np.float32)
    qdq = nncg.quantize(layers_model(), {"x": samples}, per_channel=False)
    values = initializers(qdq)
    dequantizers = weight_dequantizers(qdq)
    assert all(values[dequantizers[weight].input[1]].shape == () for weight in LAYER_AXES)


def test_reduce_range_weights_are_7_bit(tmp_path, capsys):
    """reduce_range: weights in -64..64 (full range: -127..127); the command line's --reduce-range writes
    the API's bytes."""
    samples = np.random.default_rng(0).standard_normal((8, 1, 2, 4, 4)).astype(np.float32)
    np.savez(tmp_path / "cal.npz", x=samples)
    onnx.save(layers_model(), tmp_path / "layers.onnx")
    full, reduced = (nncg.quantize(tmp_path / "layers.onnx", {"x": samples}, reduce_range=r) for r in (False, True))
    assert largest_weight(full) == 127 and largest_weight(reduced) == 64
    out = tmp_path / "layers.qdq.onnx"
    argv = [tmp_path / "layers.onnx", "--calibration", tmp_path / "cal.npz", "-o", out, "--reduce-range"]
    assert quantize_cli.main([str(a) for a in argv]) == 0
    assert capsys.readouterr().err == ""
    assert out.read_bytes() == reduced.SerializeToString(deterministic=True)


def largest_weight(model: onnx.ModelProto) -> int:
    weights = [initializers(model)[dq.input[0]] for dq in weight_dequantizers(model).values()]
    return max(int(np.abs(w.astype(int)).max()) for w in weights if w.dtype == np.int8)  # not the int32 biases


def test_dense_layer_within_its_rounding_bound():
    """y = x W^T + b in integers, requantised: each error source is at most half a step of its scale, so
    |y_int8 - y| <= s_y/2 + s_x/2 sum_i |W_ji| + s_wj/2 sum_i (|x_i| + s_x/2) + s_x s_wj/2 (input, weight,
    bias rounding) for inputs inside the calibrated range."""
    model = dense_model()
    samples = np.random.default_rng(1).standard_normal((64, 1, 16)).astype(np.float32)
    qdq = nncg.quantize(model, {"x": samples})
    w = initializers(model)["w"]
    s_x, s_y = input_scale(qdq, "x"), output_scale(qdq)
    s_w = initializers(qdq)[weight_dequantizers(qdq)["w"].input[1]]
    bound = s_y / 2 + s_x / 2 * np.abs(w).sum(1) + s_w / 2 * (np.abs(samples) + s_x / 2).sum(-1) + s_x * s_w / 2
    error = np.abs(run_all(qdq, "x", samples) - run_all(model, "x", samples))
    assert (error <= bound * (1 + 1e-5)).all(), (error / bound).max()
    assert error.max() > 0  # the model does compute in int8


def test_robot_int8_close_to_float(robot_qdq):
    """Six quantised tensors in a chain (the input and five conv outputs, uint8): each rounds by half a
    step, 1/510 of its range, and the later layers carry that on. Over fresh images the error's RMS stays
    within 1 % of the output range (2.55 output steps) and no element is off by more than 8 %; per-channel
    weights beat per-tensor ones."""
    test = robot_samples(16, RNG_SEED + 1)
    float_out = run_all(onnx.load(ROBOT), "image", test)
    span = float_out.max() - float_out.min()
    error = run_all(robot_qdq, "image", test) - float_out
    rms = float(np.sqrt(np.mean(error**2))) / span
    assert rms <= 0.01 and np.abs(error).max() <= 0.08 * span
    per_tensor = nncg.quantize(ROBOT, {"image": robot_samples(16, RNG_SEED)}, per_channel=False)
    per_tensor_rms = float(np.sqrt(np.mean((run_all(per_tensor, "image", test) - float_out) ** 2))) / span
    print(
        f"robot uint8 vs float, of the output range: per-channel max {np.abs(error).max() / span:.4f}, rms {rms:.4f}; "
        f"per-tensor rms {per_tensor_rms:.4f}"
    )
    assert rms < per_tensor_rms


# --- the calibration inputs, determinism -----------------------------------------------------------


def test_npz_npy_folder_and_arrays_give_the_same_model(robot_qdq, tmp_path):
    samples = robot_samples(16, RNG_SEED)
    np.savez(tmp_path / "cal.npz", image=samples)
    folder = tmp_path / "samples"
    folder.mkdir()
    for k, sample in enumerate(samples):
        np.save(folder / f"{k:03}.npy", sample)
    expected = robot_qdq.SerializeToString(deterministic=True)
    for calibration in (tmp_path / "cal.npz", str(folder), samples):
        assert nncg.quantize(str(ROBOT), calibration).SerializeToString(deterministic=True) == expected


def test_cli_output_is_byte_identical_across_processes(robot_qdq, tmp_path):
    """Two fresh processes with other hash seeds write the same bytes, the API's."""
    np.savez(tmp_path / "cal.npz", image=robot_samples(16, RNG_SEED))
    outputs = []
    for seed in ("1", "2"):
        out = tmp_path / f"robot{seed}.qdq.onnx"
        command = [sys.executable, "-m", "nncg.quantize_cli", ROBOT, "--calibration", tmp_path / "cal.npz", "-o", out]
        env = {**os.environ, "PYTHONHASHSEED": seed}
        result = subprocess.run(list(map(str, command)), capture_output=True, text=True, cwd=ROOT, env=env)
        assert result.returncode == 0 and result.stderr == "", result.stderr
        assert result.stdout == f"wrote {out} ({out.stat().st_size} bytes)\n"
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1] == robot_qdq.SerializeToString(deterministic=True)


def two_inputs() -> tuple[onnx.ModelProto, dict[str, np.ndarray]]:
    """A model with inputs a and b, and six calibration samples of each."""
    model = onnx_model(
        [helper.make_node("Conv", ["a", "w"], ["c"]), helper.make_node("Add", ["c", "b"], ["y"])],
        inputs={"a": [1, 2, 5, 5], "b": [1, 3, 3, 3]},
        initializers={"w": weights(3, 2, 3, 3)},
    )
    rng = np.random.default_rng(2)
    return model, {name: rng.standard_normal((6, 1, c, n, n), np.float32) for name, c, n in (("a", 2, 5), ("b", 3, 3))}


def test_several_inputs_from_an_npz(tmp_path):
    model, data = two_inputs()
    np.savez(tmp_path / "cal.npz", **data)
    qdq = nncg.quantize(model, tmp_path / "cal.npz")
    assert sorted(n.input[0] for n in qdq.graph.node if n.op_type == "QuantizeLinear")[:2] == ["a", "b"]
    assert qdq.SerializeToString() == nncg.quantize(model, data).SerializeToString()


def test_a_tf2onnx_model_keeps_its_nhwc_layout():
    """The input's layout is read from the graph (tf2onnx's Transpose to NCHW), which the quantize-
    dequantize pair before it leaves readable; the producer is kept too."""
    nodes = [
        helper.make_node("Transpose", ["x"], ["t"], perm=[0, 3, 1, 2]),
        helper.make_node("Conv", ["t", "w"], ["y"]),
    ]
    model = onnx_model(
        nodes, inputs={"x": [1, 4, 4, 3]}, outputs={"y": [1, 2, 4, 4]}, initializers={"w": weights(2, 3, 1, 1)}
    )
    model.producer_name, model.producer_version = "tf2onnx", "1.17.0"
    assert model_layout(model) == "nhwc"
    qdq = nncg.quantize(model, np.ones((2, 1, 4, 4, 3), np.float32))
    assert (qdq.producer_name, qdq.producer_version) == ("tf2onnx", "1.17.0")
    assert model_layout(qdq) == "nhwc"


def test_percentile_is_deterministic():
    model, samples = dense_model(), {"x": np.random.default_rng(3).standard_normal((16, 1, 16)).astype(np.float32)}
    first, second = (nncg.quantize(model, samples, calibrate_method="percentile") for _ in range(2))
    assert first.SerializeToString() == second.SerializeToString()
    minmax = nncg.quantize(model, samples)
    assert input_scale(first, "x") != input_scale(minmax, "x")  # the method was applied


@pytest.mark.parametrize("opset", [7, 11])
def test_an_older_opset_is_raised_to_13(opset):
    """Per-channel DequantizeLinear needs opset 13 (onnxruntime alone would write an invalid opset-11 model)."""
    model = onnx_model(
        [helper.make_node("Conv", ["x", "w", "b"], ["y"])],
        inputs={"x": [1, 2, 5, 5]},
        initializers={"w": weights(3, 2, 3, 3), "b": weights(3)},
        opset=opset,
    )
    qdq = nncg.quantize(model, np.random.default_rng(0).random((4, 1, 2, 5, 5), dtype=np.float32))
    onnx.checker.check_model(qdq, full_check=True)
    assert [(o.domain, o.version) for o in qdq.opset_import] == [("", 13)]


def test_dynamic_batch_is_one(tmp_path):
    model = dense_model()
    model.graph.input[0].type.tensor_type.shape.dim[0].dim_param = "N"
    with pytest.warns(nncg.NncgWarning, match="batch"):
        qdq = nncg.quantize(model, np.zeros((2, 1, 16), np.float32) + 0.5)
    assert [d.dim_value for d in qdq.graph.input[0].type.tensor_type.shape.dim] == [1, 16]


# --- mistakes: the API ---------------------------------------------------------------------------

API_MISTAKES = {
    "activations": (dict(activations="int4"), "activations must be one of uint8, int8; got str 'int4'"),
    "per_channel": (dict(per_channel="yes"), "per_channel must be True or False"),
    "reduce_range": (dict(reduce_range=1), "reduce_range must be True or False; got int 1"),
    "method": (dict(calibrate_method="entropy"), "calibrate_method must be one of minmax, percentile; got str"),
    "input_shapes": (dict(input_shapes={"x": (1, -16)}), "input_shapes['x'] must be a tuple of ints"),
}


@pytest.mark.parametrize("kwargs, message", API_MISTAKES.values(), ids=API_MISTAKES)
def test_api_argument_mistakes(kwargs, message):
    with pytest.raises(NncgError, match=message.replace("[", r"\[").replace("(", r"\(")):
        nncg.quantize(dense_model(), np.ones((2, 1, 16), np.float32), **kwargs)


CALIBRATION_MISTAKES = {
    "not numpy": (42, "calibration must be an .npz path, a folder of .npy files, a dict"),
    "dict of lists": ({"x": [[0.0] * 16]}, "calibration must map input names (str) to numpy arrays; got str -> list"),
    "no sample axis": (
        np.ones((1, 16), np.float32),
        "has shape (1, 16); the model takes (1, 16), so it needs (samples",
    ),
    "float64": (np.ones((2, 1, 16)), "is float64, the model takes float32: convert it (array.astype(numpy.float32))"),
    "empty": (np.ones((0, 1, 16), np.float32), "calibration input 'x' has no samples"),
    "nan": (np.full((2, 1, 16), np.nan, np.float32), "calibration input 'x' holds NaN or infinity"),
    "missing name": ({"image": np.ones((2, 1, 16), np.float32)}, "the calibration data lacks 'x'; it needs one array"),
}


@pytest.mark.parametrize("calibration, message", CALIBRATION_MISTAKES.values(), ids=CALIBRATION_MISTAKES)
def test_api_calibration_mistakes(calibration, message):
    with pytest.raises(NncgError) as raised:
        nncg.quantize(dense_model(), calibration)
    assert message in str(raised.value)


def test_several_inputs_mistakes(tmp_path):
    model, data = two_inputs()
    mistakes = {
        "one calibration array for a model with 2 inputs ('a', 'b'); give a dict of input name to array": data["a"],
        "a folder of .npy files is for one-input models; give an .npz keyed by input name": tmp_path,
        "the calibration inputs have different numbers of samples ('a': 6, 'b': 5)": {**data, "b": data["b"][:5]},
        "calibration must map input names (str) to numpy arrays; got int -> ndarray": {**data, 1: data["a"]},
    }
    for message, calibration in mistakes.items():
        with pytest.raises(NncgError) as raised:
            nncg.quantize(model, calibration)
        assert message in str(raised.value)


def test_a_quantised_model_is_refused(robot_qdq):
    with pytest.raises(NncgError, match=r"the model is quantised already \(QuantizeLinear\)"):
        nncg.quantize(robot_qdq, robot_samples(2, 0))


# --- mistakes: the command lines -------------------------------------------------------------------


# calibration argument (a file made by calibration_files) -> the start of what the error says
CALIBRATION_CASES = {
    "missing file": ("absent.npz", "calibration file '{folder}/absent.npz' does not exist; check the path"),
    "not an npz": ("data.csv", "calibration file '{folder}/data.csv' is not an .npz; give an .npz"),
    "garbage npz": ("garbage.npz", "cannot read calibration file '{folder}/garbage.npz': "),
    "pickled objects": ("objects.npz", "cannot read calibration file '{folder}/objects.npz': Object arrays"),
    "no sample axis": ("no_sample_axis.npz", "calibration input 'image' has shape (1, 3, 60, 80); the model"),
    "wrong name": ("wrong_name.npz", "the calibration data lacks 'image'; it needs one array for each"),
    "extra name": ("extra_name.npz", "the calibration data has 'mask'; it needs one array for each model input"),
    "float64": ("float64.npz", "calibration input 'image' is float64, the model takes float32: convert it"),
    "no samples": ("empty.npz", "calibration input 'image' has no samples; give at least one"),
    "nan": ("nan.npz", "calibration input 'image' holds NaN or infinity; give finite values"),
    "folder without npy": ("no_npy", "calibration folder '{folder}/no_npy' has no .npy files"),
    "npy of two shapes": ("mixed", "the .npy files in '{folder}/mixed' differ in shape or dtype"),
    "escaped name": ("bad\x1b[31m\u202e.npz", "calibration file '{folder}/bad\\x1b[31m\\u202e.npz' does not exist"),
}


@pytest.fixture(scope="module")
def calibration_files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("mistakes")
    good = robot_samples(2, 0)
    np.savez(folder / "no_sample_axis.npz", image=good[0])
    np.savez(folder / "wrong_name.npz", images=good)
    np.savez(folder / "extra_name.npz", image=good, mask=good)
    np.savez(folder / "float64.npz", image=good.astype(np.float64))
    np.savez(folder / "empty.npz", image=good[:0])
    np.savez(folder / "nan.npz", image=np.where(good > 0.5, np.inf, good))
    np.savez(folder / "objects.npz", image=np.array([good, None], dtype=object))
    (folder / "garbage.npz").write_bytes(b"not a zip file\n")
    (folder / "data.csv").write_text("0.5\n")
    (folder / "no_npy").mkdir()
    (folder / "mixed").mkdir()
    np.save(folder / "mixed" / "a.npy", good[0])
    np.save(folder / "mixed" / "b.npy", good[0, :, :, :30])
    return folder


def run_cli(main, argv: list[object], capsys) -> tuple[int, list[str]]:
    """The exit status and the stderr lines of a command line run in this process."""
    try:
        status = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's usage errors
        status = exc.code
    out, err = capsys.readouterr()
    assert out == ""
    return status, err.splitlines()


def check_one_error(status: int, lines: list[str], prog: str, message: str) -> None:
    assert status == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"{prog}: error: {message}"), lines[0]
    assert "\x1b" not in lines[0] and "\u202e" not in lines[0]


def old_output(tmp_path: Path) -> tuple[Path, dict]:
    """An output folder with files of an earlier run, and its snapshot."""
    out = tmp_path / "out"
    old_files(out, "robot.qdq.onnx", "robot.c", "robot.h")
    return out, snapshot(out)


@pytest.mark.parametrize("case", CALIBRATION_CASES)
def test_calibration_mistakes_on_both_command_lines(calibration_files, case, tmp_path, capsys):
    name, message = CALIBRATION_CASES[case]
    message = message.format(folder=calibration_files)
    calibration = calibration_files / name
    out, before = old_output(tmp_path)
    argv = [ROBOT, "--calibration", calibration, "-o", out / "robot.qdq.onnx"]
    check_one_error(*run_cli(quantize_cli.main, argv, capsys), "nncg-quantize", message)
    argv = [ROBOT, "--calibration", calibration, "-o", out]
    check_one_error(*run_cli(cli.main, argv, capsys), "nncg-onnx", message)
    assert snapshot(out) == before


QUANTIZE_CLI_MISTAKES = {
    "no calibration": ([ROBOT, "-o", "{out}/m.onnx"], "the following arguments are required: --calibration"),
    "no output": ([ROBOT, "--calibration", "{cal}"], "the following arguments are required: -o/--output"),
    "bad activations": ([ROBOT, "--calibration", "{cal}", "-o", "{out}/m.onnx", "--activations", "int4"],
                        "argument --activations: invalid choice: 'int4'"),
    "bad method": ([ROBOT, "--calibration", "{cal}", "-o", "{out}/m.onnx", "--method", "kl"],
                   "argument --method: invalid choice: 'kl'"),
    "output is a folder": ([ROBOT, "--calibration", "{cal}", "-o", "{out}"], "-o '{out}' is a folder; give the file"),
    "output under a file": ([ROBOT, "--calibration", "{cal}", "-o", "{out}/robot.c/m.onnx"],
                            "the output folder '{out}/robot.c' exists and is not a folder"),
    "missing model": (["{out}/absent.onnx", "--calibration", "{cal}", "-o", "{out}/m.onnx"],
                      "model file '{out}/absent.onnx' does not exist"),
    "not a model": (["{out}/robot.c", "--calibration", "{cal}", "-o", "{out}/m.onnx"],
                    "'{out}/robot.c' is not a valid ONNX model"),
    "quantised already": (["{qdq}", "--calibration", "{cal}", "-o", "{out}/m.onnx"],
                          "the model is quantised already (QuantizeLinear): compile it as it is"),
    "input shape of a constant": ([ROBOT, "--calibration", "{cal}", "-o", "{out}/m.onnx", "--input-shape", "x=1x2"],
                                  "input_shapes names 'x', which is not an input of the model"),
}  # fmt: skip


@pytest.mark.parametrize("case", QUANTIZE_CLI_MISTAKES)
def test_quantize_command_mistakes(case, robot_qdq, tmp_path, capsys):
    out, before = old_output(tmp_path)
    np.savez(tmp_path / "cal.npz", image=robot_samples(2, 0))
    onnx.save(robot_qdq, tmp_path / "robot.qdq.onnx")
    names = {"out": out, "cal": tmp_path / "cal.npz", "qdq": tmp_path / "robot.qdq.onnx"}
    argv, message = QUANTIZE_CLI_MISTAKES[case]
    result = run_cli(quantize_cli.main, [str(a).format(**names) for a in argv], capsys)
    check_one_error(*result, "nncg-quantize", message.format(**names))
    assert snapshot(out) == before


def test_nncg_onnx_refuses_to_quantise_a_quantised_model(robot_qdq, tmp_path, capsys):
    out, before = old_output(tmp_path)
    onnx.save(robot_qdq, tmp_path / "robot.qdq.onnx")
    np.savez(tmp_path / "cal.npz", image=robot_samples(2, 0))
    argv = [tmp_path / "robot.qdq.onnx", "--calibration", tmp_path / "cal.npz", "-o", out]
    check_one_error(*run_cli(cli.main, argv, capsys), "nncg-onnx", "the model is quantised already")
    assert snapshot(out) == before


# --- compiled: the int8 C against onnxruntime on the QDQ model -------------------------------------------


def test_robot_c_matches_onnxruntime_int8_within_one_step(robot_qdq, tmp_path):
    compiled = nncg.compile(robot_qdq, target="ansi-c")
    built = build_model(compiled, tmp_path)
    test = robot_samples(4, RNG_SEED + 1)
    c_out = np.stack([built.run([x])[0] for x in test])
    error = np.abs(c_out - run_all(robot_qdq, "image", test))
    assert error.max() <= output_scale(robot_qdq) * (1 + 1e-6), error.max() / output_scale(robot_qdq)


def test_nncg_onnx_calibration_writes_the_qdq_model_beside_the_c(robot_qdq, tmp_path):
    compiled = nncg.compile(robot_qdq, name="robot")
    np.savez(tmp_path / "cal.npz", image=robot_samples(16, RNG_SEED))
    out = tmp_path / "out"
    assert cli.main([str(ROBOT), "--calibration", str(tmp_path / "cal.npz"), "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["robot.c", "robot.h", "robot.qdq.onnx"]
    assert (out / "robot.qdq.onnx").read_bytes() == robot_qdq.SerializeToString(deterministic=True)
    assert (out / "robot.c").read_text() == compiled.source
