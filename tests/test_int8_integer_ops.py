"""ConvInteger and MatMulInteger (issue 16) whose int32 result a Cast to float32, a Mul by a scale
and possibly an Add of a bias dequantise (the three fused into the integer kernel's store): inputs
quantised by a QuantizeLinear (uint8 and int8, zero points other than 0), uint8 and int8 weights with
zero points per tensor, or per column for MatMulInteger (onnxruntime's ConvInteger takes one),
scales per tensor and per channel; compared with onnxruntime on every element, to the bit, on
ansi-c, the x86 targets and NEON under qemu, whose vector kernels reduce in the int8 dot products
of QLinearConv and QLinearMatMul. The int32 result also as the graph output itself, or
read by a lone Cast to float32 (then any float op), and MatMulInteger beyond 2-D (batched, a 1-D
operand, weights with batch dims of 1), as NumPy's matmul. A node reading the int32 result, weights
with a batch and a scale that varies along another axis are refused in one line."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from cross_helpers import TOOLCHAINS, missing_tools, runner
from helpers import kernel_ops, onnx_model, skip_unless_host_runs
from int8_models import onnxruntime_outputs
from onnx import TensorProto, helper
from test_cross_targets import require

import nncg
from nncg.errors import NncgError
from nncg.verify import run_compiled

CHANNELS = 20  # avx512: a 16-lane block and a 4-lane one
X_SHAPE = {"ConvInteger": (1, 4, 7, 7), "MatMulInteger": (3, 8)}
W_SHAPE = {"ConvInteger": (CHANNELS, 4, 3, 3), "MatMulInteger": (8, CHANNELS)}
# the shape of a per-channel scale or bias: NumPy-broadcast over the result's channels
PER_CHANNEL = {"ConvInteger": (1, CHANNELS, 1, 1), "MatMulInteger": (CHANNELS,)}


def _range(dtype) -> tuple[int, int]:
    info = np.iinfo(dtype)
    return int(info.min), int(info.max) + 1


def integer_model(
    op: str,
    x_type=np.uint8,
    w_type=np.int8,
    per_channel: bool = False,
    bias: bool = True,
    seed: int = 0,
    weight_zero_points: bool = True,
) -> onnx.ModelProto:
    """x -> QuantizeLinear -> op (constant weights, zero points: the weights' 0 without
    weight_zero_points) -> Cast -> Mul by scale [-> Add bias]."""
    rng = np.random.default_rng(seed)
    w_zero_shape = (CHANNELS,) if per_channel and op == "MatMulInteger" else ()
    w_zero = rng.integers(-5, 6, w_zero_shape) * weight_zero_points + (128 if w_type == np.uint8 else 0)
    scale_shape = PER_CHANNEL[op] if per_channel else ()
    init = {
        "s": np.float32(0.05),
        "z": np.asarray(17 if x_type == np.uint8 else -9, x_type),
        "w": rng.integers(*_range(w_type), W_SHAPE[op]).astype(w_type),
        "wz": np.asarray(w_zero, w_type),
        "scale": rng.uniform(0.001, 0.01, scale_shape).astype(np.float32),
        "bias": rng.standard_normal(PER_CHANNEL[op]).astype(np.float32),
    }
    geometry = {"pads": [1, 1, 1, 1], "strides": [2, 1]} if op == "ConvInteger" else {}
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]),
        helper.make_node(op, ["q", "w", "z", "wz"], ["i"], **geometry),
        helper.make_node("Cast", ["i"], ["f"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["f", "scale"], ["y" if not bias else "m"]),
        *([helper.make_node("Add", ["bias", "m"], ["y"])] if bias else []),
    ]
    if not bias:
        del init["bias"]
    return onnx_model(nodes, inputs={"x": X_SHAPE[op]}, initializers=init)


def check(model: onnx.ModelProto, target: str = "ansi-c", **run) -> str:
    """Equal to onnxruntime to the bit on inputs quantised past both ends; the C."""
    if not run:
        skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    ops = kernel_ops(compiled)
    assert ("ConvInteger" in ops or "MatMulInteger" in ops) and "Cast" not in ops and "Mul" not in ops, ops
    shape = tuple(d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim)
    rng = np.random.default_rng(3)
    for spread in (0.5, 4.0, 20.0):  # 20: the QuantizeLinear saturates at both ends
        x = (rng.standard_normal(shape) * spread).astype(np.float32)
        expected = onnxruntime_outputs(model, {"x": x})[0]
        ours = run_compiled(compiled, [x], **run)[0].reshape(expected.shape)
        np.testing.assert_array_equal(ours, expected)
    return compiled.source


@pytest.mark.parametrize("op", sorted(X_SHAPE))
@pytest.mark.parametrize("x_type", [np.uint8, np.int8])
@pytest.mark.parametrize("w_type", [np.int8, np.uint8])
@pytest.mark.parametrize("per_channel", [False, True])
def test_matches_onnxruntime_to_the_bit(op, x_type, w_type, per_channel):
    check(integer_model(op, x_type, w_type, per_channel))


@pytest.mark.parametrize("op", sorted(X_SHAPE))
def test_without_a_bias(op):
    check(integer_model(op, per_channel=True, bias=False))


# the dot products of input channels in the vector kernels QLinearConv and QLinearDense share: weights
# minus nonzero zero points (int16) in pmaddwd pairs on every x86 target; int8 weights of zero point 0
# times uint8 activations in vpdpbusd quads on avx512vnni (pmaddwd pairs or pmaddubsw quads elsewhere)
PAIRS = "_madd_epi16("
DOTS = {"ssse3": "_mm_madd_epi16(", "avx2": "_madd_epi16(", "avx512": "_madd_epi16(", "avx512vnni": "_dpbusd_epi32("}


@pytest.mark.parametrize("target", sorted(DOTS))
@pytest.mark.parametrize("op", sorted(X_SHAPE))
def test_x86_targets(op, target):
    assert PAIRS in check(integer_model(op, np.int8, np.int8, per_channel=True), target)
    model = integer_model(op, np.uint8, np.int8, per_channel=True, weight_zero_points=False)
    source = check(model, target)
    assert DOTS[target] in source and "nncg_int32 acc" not in source


@pytest.mark.parametrize("op", sorted(X_SHAPE))
def test_neon_under_qemu(op):
    """vmlal_s16 pairs (nncg_vdot2q_s32) of int8 weights; weights minus zero points are int16 (widened)."""
    tc = TOOLCHAINS["aarch64-neon"]
    require(missing_tools(tc))
    model = integer_model(op, per_channel=True, weight_zero_points=False)
    source = check(model, "neon", cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))
    assert "nncg_vdot2q_s32(" in source and "nncg_int32 acc" not in source


def test_a_scale_along_another_axis_is_refused():
    model = integer_model("ConvInteger")
    scale = next(t for t in model.graph.initializer if t.name == "scale")
    scale.CopyFrom(onnx.numpy_helper.from_array(np.full((1, 1, 4, 1), 0.01, np.float32), "scale"))
    with pytest.raises(NncgError, match=r"ConvInteger .* dequantised by a scale of shape \[1, 1, 4, 1\]"):
        nncg.compile(model)


def test_a_cast_result_that_is_also_an_output_is_written_by_the_kernel():
    """The Cast's result also a graph output: only the Cast is fused (a scale of 1), the Mul reads it."""
    model = integer_model("MatMulInteger", bias=False)
    model.graph.output.append(helper.make_tensor_value_info("f", TensorProto.FLOAT, None))
    compiled = nncg.compile(model, verify_ir=True)
    assert kernel_ops(compiled) == ["QuantizeLinear", "MatMulInteger", "Mul"]
    x = (np.random.default_rng(5).standard_normal(X_SHAPE["MatMulInteger"]) * 4).astype(np.float32)
    for ours, expected in zip(run_compiled(compiled, [x]), onnxruntime_outputs(model, {"x": x})):
        np.testing.assert_array_equal(ours.reshape(expected.shape), expected)


def test_an_int32_result_a_node_reads_is_refused():
    """A graph output that a Cast also reads: no int32 tensor lives in NNCG's memory."""
    model = integer_model("ConvInteger")
    model.graph.output.append(helper.make_tensor_value_info("i", TensorProto.INT32, None))
    with pytest.raises(NncgError, match=r"ConvInteger \(node .*\) writes an int32 tensor that a node reads"):
        nncg.compile(model)


def test_weights_computed_at_run_time_are_refused():
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]),
        helper.make_node("QuantizeLinear", ["v", "s", "z"], ["wq"]),
        helper.make_node("MatMulInteger", ["q", "wq"], ["i"]),
        helper.make_node("Cast", ["i"], ["f"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["f", "scale"], ["y"]),
    ]
    init = {"s": np.float32(0.1), "z": np.uint8(3), "scale": np.float32(0.01)}
    model = onnx_model(nodes, inputs={"x": (2, 3), "v": (3, 2)}, initializers=init)
    with pytest.raises(NncgError, match="weights computed at run time"):
        nncg.compile(model)


# --- int32 results as graph outputs, a lone Cast, MatMulInteger beyond 2-D -------------------------

# name: (op, x shape, w shape); MatMulInteger's as NumPy's matmul broadcasts them
RAW_SHAPES = {
    "conv": ("ConvInteger", X_SHAPE["ConvInteger"], W_SHAPE["ConvInteger"]),
    "matrix": ("MatMulInteger", (3, 8), (8, CHANNELS)),
    "batched": ("MatMulInteger", (2, 3, 8), (8, CHANNELS)),
    "row": ("MatMulInteger", (8,), (8, CHANNELS)),
    "column": ("MatMulInteger", (2, 3, 8), (8,)),
    "weights_batch_of_1": ("MatMulInteger", (3, 8), (1, 1, 8, CHANNELS)),
}


def raw_model(case: str, tail: str = "", x_type=np.uint8, seed: int = 1) -> onnx.ModelProto:
    """x -> QuantizeLinear -> op (zero points other than 0) -> the int32 result as the graph output, or
    read by a Cast to float32 then (`tail`) a Relu, or a Mul by a per-column scale."""
    op, x_shape, w_shape = RAW_SHAPES[case]
    rng = np.random.default_rng(seed)
    init = {
        "s": np.float32(0.05),
        "z": np.asarray(17 if x_type == np.uint8 else -9, x_type),
        "w": rng.integers(-128, 128, w_shape).astype(np.int8),
        "wz": np.int8(3),
        "scale": rng.uniform(0.001, 0.01, w_shape[-1:]).astype(np.float32),
    }
    geometry = {"pads": [1, 1, 1, 1], "strides": [2, 1]} if op == "ConvInteger" else {}
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"]),
        helper.make_node(op, ["q", "w", "z", "wz"], ["i" if tail else "y"], **geometry),
    ]
    if tail:
        nodes.append(helper.make_node("Cast", ["i"], ["f"], to=TensorProto.FLOAT))
        nodes.append(helper.make_node(tail, ["f"] if tail == "Relu" else ["f", "scale"], ["y"]))
    else:
        del init["scale"]
    y_type = TensorProto.FLOAT if tail else TensorProto.INT32
    return onnx_model(nodes, inputs={"x": x_shape}, outputs={"y": helper.make_tensor_value_info("y", y_type, None)},
                      initializers=init)  # fmt: skip


def check_raw(model: onnx.ModelProto, target: str = "ansi-c", **run) -> None:
    """Equal to onnxruntime in every element and in type, on inputs quantised past both ends."""
    if not run:
        skip_unless_host_runs(target)
    compiled = nncg.compile(model, target=target, verify_ir=True)
    assert "Cast" not in kernel_ops(compiled)
    shape = tuple(d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim)
    rng = np.random.default_rng(4)
    for spread in (0.5, 20.0):
        x = (rng.standard_normal(shape) * spread).astype(np.float32)
        expected = onnxruntime_outputs(model, {"x": x})[0]
        ours = run_compiled(compiled, [x], **run)[0]
        assert ours.dtype == expected.dtype and ours.shape == expected.shape
        np.testing.assert_array_equal(ours, expected)


@pytest.mark.parametrize("case", sorted(RAW_SHAPES))
@pytest.mark.parametrize("x_type", [np.uint8, np.int8])
def test_int32_result_as_the_graph_output(case, x_type):
    check_raw(raw_model(case, x_type=x_type))


@pytest.mark.parametrize("case", ["conv", "matrix", "batched"])
def test_int32_result_cast_to_float_then_read_by_a_float_op(case):
    check_raw(raw_model(case, "Relu"))


@pytest.mark.parametrize("case", ["batched", "row", "column"])
def test_batched_matmul_integer_dequantised_per_column(case):
    check_raw(raw_model(case, "Mul" if case != "column" else "Relu"))


@pytest.mark.parametrize("target", ["ssse3", "avx2", "avx512", "avx512vnni"])
@pytest.mark.parametrize("case", ["conv", "batched"])
def test_int32_results_on_x86_targets(case, target):
    check_raw(raw_model(case, x_type=np.int8), target)
    check_raw(raw_model(case, "Relu"), target)


@pytest.mark.parametrize("case", ["conv", "batched"])
def test_int32_results_under_qemu(case):
    tc = TOOLCHAINS["aarch64-neon"]
    require(missing_tools(tc))
    check_raw(raw_model(case), "neon", cc=tc.cc, extra_cflags=tc.flags, runner=runner(tc))


def test_weights_with_a_batch_are_refused():
    model = raw_model("matrix")
    w = next(t for t in model.graph.initializer if t.name == "w")
    w.CopyFrom(onnx.numpy_helper.from_array(np.ones((2, 8, CHANNELS), np.int8), "w"))
    with pytest.raises(NncgError, match=rf"MatMulInteger .* weights of shape \[2, 8, {CHANNELS}\]; NNCG"):
        nncg.compile(model)
