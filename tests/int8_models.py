"""int8 test models: small float models built with onnx.helper (and the repository's own), quantized
with onnxruntime.quantization.quantize_static (QDQ, per-channel weights, seeded random calibration
data), and the comparison of NNCG's C with onnxruntime on the same quantized model, in quantization
steps of each output."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import onnx
from helpers import onnx_model
from onnx import TensorProto, helper, numpy_helper
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

from nncg.quant_steps import Comparison, compare_steps, tensor_steps  # noqa: F401 - tensor_steps for the tests
from nncg.verify import reference_session, run_compiled

ROOT = Path(__file__).resolve().parent.parent
OPSET = 17


class _Calibration(CalibrationDataReader):
    def __init__(self, feeds: list[dict[str, np.ndarray]]):
        self.feeds = iter(feeds)

    def get_next(self):
        return next(self.feeds, None)


def input_shapes(model: onnx.ModelProto) -> dict[str, tuple[int, ...]]:
    initializers = {t.name for t in model.graph.initializer}
    return {
        v.name: tuple(d.dim_value or 1 for d in v.type.tensor_type.shape.dim)
        for v in model.graph.input
        if v.name not in initializers
    }


def random_feeds(model: onnx.ModelProto, count: int, seed: int) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    shapes = input_shapes(model)
    return [{n: rng.standard_normal(s).astype(np.float32) for n, s in shapes.items()} for _ in range(count)]


def quantized(model: onnx.ModelProto, activations: str = "uint8", seed: int = 0) -> onnx.ModelProto:
    """The QDQ model quantize_static writes: per-tensor activations of that type, per-channel int8 weights."""
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "float.onnx", Path(tmp) / "int8.onnx"
        onnx.save(model, src)
        quantize_static(
            str(src),
            str(dst),
            _Calibration(random_feeds(model, 8, seed)),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8 if activations == "uint8" else QuantType.QInt8,
            weight_type=QuantType.QInt8,
        )
        return onnx.load(dst)


def _model(nodes, x_shape, initializers: dict[str, np.ndarray]) -> onnx.ModelProto:
    graph = helper.make_graph(
        nodes,
        "int8_test",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, x_shape)],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [numpy_helper.from_array(a.astype(np.float32), n) for n, a in initializers.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])


def _weights(rng, *shape) -> np.ndarray:
    return rng.standard_normal(shape) / np.sqrt(np.prod(shape[1:]))


def conv_model(kind: str, seed: int = 1) -> onnx.ModelProto:
    """One conv layer (and what follows it) of each geometry the tests cover."""
    rng = np.random.default_rng(seed)
    c = 6
    convs = {  # name: (c_in, c_out, kernel, attributes)
        "3x3": (3, 8, 3, {"pads": [1, 1, 1, 1]}),
        "stride2": (3, 8, 3, {"pads": [1, 0, 1, 0], "strides": [2, 2]}),
        "1x1": (c, 8, 1, {}),
        "depthwise": (c, c, 3, {"pads": [1, 1, 1, 1], "group": c}),
        "grouped": (c, 4, 3, {"pads": [1, 1, 1, 1], "group": 2, "dilations": [2, 2]}),
    }
    c_in, c_out, k, attrs = convs[kind]
    w = _weights(rng, c_out, c_in // attrs.get("group", 1), k, k)
    init = {"w": w, "b": rng.standard_normal(c_out) * 0.3}
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["c"], **attrs), helper.make_node("Relu", ["c"], ["y"])]
    return _model(nodes, [1, c_in, 9, 9], init)


def stacked_conv_model(kind: str, channels: int = 12, seed: int = 3) -> onnx.ModelProto:
    """A 1x1 Conv to `channels` (its output is channels-last), then a padded 3x3 depthwise or
    grouped (2 groups, dilated) Conv of them: the geometries that read a channels-last input."""
    rng = np.random.default_rng(seed)
    group = channels if kind == "depthwise" else 2
    init = {
        "w1": _weights(rng, channels, 3, 1, 1),
        "w": _weights(rng, channels, channels // group, 3, 3),
        "b": rng.standard_normal(channels) * 0.3,
    }
    attrs = {"pads": [1, 1, 1, 1], "group": group, **({} if kind == "depthwise" else {"dilations": [2, 2]})}
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["p"]),
        helper.make_node("Relu", ["p"], ["r"]),
        helper.make_node("Conv", ["r", "w", "b"], ["y"], **attrs),
    ]
    return _model(nodes, [1, 3, 9, 9], init)


def clip_gemm_model(seed: int = 2) -> onnx.ModelProto:
    """Conv + Clip(0, 6) (ReLU6), MaxPool, GlobalAveragePool, Flatten, Gemm."""
    rng = np.random.default_rng(seed)
    init = {
        "w": _weights(rng, 8, 3, 3, 3),
        "b": rng.standard_normal(8) * 0.3,
        "lo": np.array(0.0),
        "hi": np.array(1.0),
        "wg": _weights(rng, 5, 8) * 2,
        "bg": rng.standard_normal(5),
    }
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Clip", ["c", "lo", "hi"], ["r"]),
        helper.make_node("MaxPool", ["r"], ["m"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("GlobalAveragePool", ["m"], ["g"]),
        helper.make_node("Flatten", ["g"], ["f"]),
        helper.make_node("Gemm", ["f", "wg", "bg"], ["y"], transB=1),
    ]
    return _model(nodes, [1, 3, 10, 10], init)


def softmax_head_model(seed: int = 2) -> onnx.ModelProto:
    """clip_gemm_model with a Softmax over its 5 outputs: a classifier's head (QLinearSoftmax to onnxruntime)."""
    model = clip_gemm_model(seed)
    model.graph.node[-1].output[0] = "logits"
    model.graph.node.append(helper.make_node("Softmax", ["logits"], ["y"], axis=-1))
    return model


def residual_model(seed: int = 3) -> onnx.ModelProto:
    """Conv, Relu, Conv, Add of the two (different scales), MaxPool, Reshape, MatMul."""
    rng = np.random.default_rng(seed)
    init = {
        "w1": _weights(rng, 8, 4, 3, 3),
        "b1": rng.standard_normal(8) * 0.2,
        "w2": _weights(rng, 8, 8, 3, 3),
        "b2": rng.standard_normal(8) * 0.2,
        "shape": np.array([1, 8 * 4 * 4]),
        "wm": _weights(rng, 8 * 4 * 4, 10),
    }
    nodes = [
        helper.make_node("Conv", ["x", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("Conv", ["r1", "w2", "b2"], ["c2"], pads=[1, 1, 1, 1]),
        helper.make_node("Add", ["c2", "r1"], ["a"]),
        helper.make_node("MaxPool", ["a"], ["m"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node("Reshape", ["m", "shape"], ["f"]),
        helper.make_node("MatMul", ["f", "wm"], ["y"]),
    ]
    model = _model(nodes, [1, 4, 8, 8], init)
    model.graph.initializer[-2].CopyFrom(numpy_helper.from_array(np.array([1, 128], np.int64), "shape"))
    return model


def add_model(seed: int = 4) -> onnx.ModelProto:
    """Two Convs added (each input with its own scale and zero point), the sum the output."""
    rng = np.random.default_rng(seed)
    init = {"w1": _weights(rng, 8, 4, 3, 3), "w2": _weights(rng, 8, 4, 1, 1) * 3, "b2": rng.standard_normal(8)}
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Conv", ["x", "w2", "b2"], ["c2"]),
        helper.make_node("Add", ["c1", "c2"], ["y"]),
    ]
    return _model(nodes, [1, 4, 8, 8], init)


def broadcast_add_model(
    seed: int = 7, average_first: bool = False, channels: int = 2, size: int = 4
) -> onnx.ModelProto:
    """A Conv plus its own global average (an Add that broadcasts: onnxruntime's QLinearAdd), the
    average the second operand or the first."""
    rng = np.random.default_rng(seed)
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"]),
        helper.make_node("GlobalAveragePool", ["c"], ["g"]),
        helper.make_node("Add", ["g", "c"] if average_first else ["c", "g"], ["y"]),
    ]
    return _model(nodes, [1, channels, size, size], {"w": _weights(rng, channels + 1, channels, 1, 1)})


def average_pool_model(seed: int = 5, whole_image: bool = False) -> onnx.ModelProto:
    """Conv, then AveragePool with padding (windows of different counts), or of the whole image (a
    global pool to onnxruntime), the output."""
    rng = np.random.default_rng(seed)
    window = {"kernel_shape": [9, 9]} if whole_image else {"kernel_shape": [3, 3], "strides": [2, 2], "pads": [1] * 4}
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("AveragePool", ["c"], ["y"], **window),
    ]
    return _model(nodes, [1, 4, 9, 9], {"w": _weights(rng, 8, 4, 3, 3)})


def hand_qdq_model(activation: str, seed: int = 6) -> onnx.ModelProto:
    """A QDQ Conv written by hand, with the `activation` (Relu or Clip(0, 2)) that quantize_static
    would have folded away left between the Conv and its QuantizeLinear (zero point 0: onnxruntime
    drops the Relu or Clip into the output range, as NNCG does)."""
    rng = np.random.default_rng(seed)
    w_scale = rng.uniform(0.005, 0.02, 8).astype(np.float32)
    x_scale = np.float32(0.03)
    init = {
        "xs": x_scale, "xz": np.uint8(120), "ys": np.float32(0.01), "yz": np.uint8(0),
        "wq": rng.integers(-127, 128, (8, 3, 3, 3)).astype(np.int8), "wsc": w_scale, "wz": np.zeros(8, np.int8),
        "bq": rng.integers(-2000, 2000, 8).astype(np.int32), "bs": (x_scale * w_scale).astype(np.float32),
        "bz": np.zeros(8, np.int32), "lo": np.float32(0), "hi": np.float32(2),
    }  # fmt: skip
    clamp = (
        helper.make_node("Relu", ["c"], ["r"])
        if activation == "Relu"
        else helper.make_node("Clip", ["c", "lo", "hi"], ["r"])
    )
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "xs", "xz"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "xs", "xz"], ["xd"]),
        helper.make_node("DequantizeLinear", ["wq", "wsc", "wz"], ["w"], axis=0),
        helper.make_node("DequantizeLinear", ["bq", "bs", "bz"], ["b"], axis=0),
        helper.make_node("Conv", ["xd", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        clamp,
        helper.make_node("QuantizeLinear", ["r", "ys", "yz"], ["rq"]),
        helper.make_node("DequantizeLinear", ["rq", "ys", "yz"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "hand_qdq",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [numpy_helper.from_array(np.asarray(a), n) for n, a in init.items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])


def repository_model(path: str, softmax: bool = True) -> onnx.ModelProto:
    """One of the repository's float models, BatchNormalization folded into the Convs (onnxruntime's
    quant_pre_process, the step its quantizer asks for); softmax=False removes a final Softmax."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    model = onnx.load(ROOT / path)
    last = model.graph.node[-1]
    if last.op_type == "Softmax" and not softmax:
        model.graph.node.remove(last)
        model.graph.output[0].CopyFrom(helper.make_tensor_value_info(last.input[0], TensorProto.FLOAT, None))
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "model.onnx", Path(tmp) / "prepared.onnx"
        onnx.save(model, src)
        quant_pre_process(str(src), str(dst), skip_symbolic_shape=True)
        return onnx.load(dst)


# --- hand-written QDQ and QOperator models of one op, and their bit-exact check ----------------

CONTRIB = "com.microsoft"  # onnxruntime's contrib ops (QLinearAdd, QLinearMul, ...)


def typed(activations: str, value) -> np.ndarray:
    """`value` as the activation type ("int8" or "uint8")."""
    return np.asarray(value, np.int8 if activations == "int8" else np.uint8)


def qdq_around(op: str, operands: list[str], x: tuple[str, str], y: tuple[str, str], **attrs) -> list:
    """x quantised and dequantised by the scale and zero point named `x`, `op` of it (then
    `operands`), its result quantised and dequantised to y by those named `y`."""
    return [
        helper.make_node("QuantizeLinear", ["x", *x], ["q"]),
        helper.make_node("DequantizeLinear", ["q", *x], ["d"]),
        helper.make_node(op, ["d", *operands], ["f"], **attrs),
        helper.make_node("QuantizeLinear", ["f", *y], ["fq"]),
        helper.make_node("DequantizeLinear", ["fq", *y], ["y"]),
    ]


def qdq_binary_model(op: str, x_shape, z_shape, params: dict, constant: bool = False) -> onnx.ModelProto:
    """x `op` z between QuantizeLinear/DequantizeLinear pairs (scales and zero points as/az, bs/bz,
    ys/yz in `params`); z a graph input or a quantized constant of bs/bz's type."""
    params = dict(params)
    inputs = {"x": x_shape}
    if constant:
        info = np.iinfo(params["bz"].dtype)
        values = np.random.default_rng(2).integers(info.min, info.max + 1, z_shape)
        params["zq"] = values.astype(params["bz"].dtype)
        b = [helper.make_node("DequantizeLinear", ["zq", "bs", "bz"], ["db"])]
    else:
        inputs["z"] = z_shape
        b = [
            helper.make_node("QuantizeLinear", ["z", "bs", "bz"], ["zq"]),
            helper.make_node("DequantizeLinear", ["zq", "bs", "bz"], ["db"]),
        ]
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "as", "az"], ["xq"]),
        helper.make_node("DequantizeLinear", ["xq", "as", "az"], ["da"]),
        *b,
        helper.make_node(op, ["da", "db"], ["r"]),
        helper.make_node("QuantizeLinear", ["r", "ys", "yz"], ["rq"]),
        helper.make_node("DequantizeLinear", ["rq", "ys", "yz"], ["y"]),
    ]
    return onnx_model(nodes, inputs=inputs, initializers=params)


def contrib_binary_model(op: str, x_shape, z_shape, params: dict) -> onnx.ModelProto:
    """onnxruntime's contrib `op` (QLinearAdd, QLinearMul) of x and z, quantised as qdq_binary_model's."""
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "as", "az"], ["xq"]),
        helper.make_node("QuantizeLinear", ["z", "bs", "bz"], ["zq"]),
        helper.make_node(op, ["xq", "as", "az", "zq", "bs", "bz", "ys", "yz"], ["rq"], domain=CONTRIB),
        helper.make_node("DequantizeLinear", ["rq", "ys", "yz"], ["y"]),
    ]
    model = onnx_model(nodes, inputs={"x": x_shape, "z": z_shape}, initializers=params)
    model.opset_import.append(helper.make_opsetid(CONTRIB, 1))
    return model


def spread_feeds(model: onnx.ModelProto, spreads, seed: int) -> list[dict[str, np.ndarray]]:
    """One feed per spread: standard-normal float32 inputs times it (wide spreads saturate)."""
    rng = np.random.default_rng(seed)
    shapes = input_shapes(model)
    return [
        {name: (rng.standard_normal(shape) * spread).astype(np.float32) for name, shape in shapes.items()}
        for spread in spreads
    ]


def assert_identical(model: onnx.ModelProto, compiled, feeds_list: list[dict[str, np.ndarray]], **run) -> None:
    """NNCG's C (run_compiled's options) equals onnxruntime on every element of every feed."""
    for feeds in feeds_list:
        expected = onnxruntime_outputs(model, feeds)[0]
        ours = run_compiled(compiled, list(feeds.values()), **run)[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)


def onnxruntime_outputs(model: onnx.ModelProto, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    return reference_session(model).run(None, feeds)


def compare(model: onnx.ModelProto, compiled, feeds: list[dict[str, np.ndarray]], **run) -> Comparison:
    """Runs NNCG's C on every feed (run_compiled's options) and onnxruntime on the same model."""
    names = list(input_shapes(model))
    return compare_steps(
        model,
        ((run_compiled(compiled, [feed[n] for n in names], **run), onnxruntime_outputs(model, feed)) for feed in feeds),
    )
