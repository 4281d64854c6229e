"""Reductions (ReduceSum, ReduceMax, ReduceMin, ReduceL1, ReduceL2, ReduceSumSquare, ReduceLogSum,
ReduceLogSumExp; ReduceMean has tests/test_ops_elementwise.py), ArgMax/ArgMin and the normalisations
(InstanceNormalization, GroupNormalization, LayerNormalization): small ONNX models compiled for every
target and compared with onnxruntime (NEON under qemu-user), the IR they lower to, and the one-line
errors for what NNCG refuses. Odd channel counts (13, 7) leave vector tails on every target."""

import numpy as np
import pytest
from cross_helpers import NEON_TOOLCHAINS, check_on_neon
from helpers import compile_and_check, kernel_ops, onnx_model, weights
from onnx import TensorProto, helper

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.graph import ArgMaxAttrs, NormAttrs, ReduceAttrs
from nncg.verify import random_inputs, reference_outputs

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
REDUCE_OPS = (
    "ReduceSum",
    "ReduceMax",
    "ReduceMin",
    "ReduceL1",
    "ReduceL2",
    "ReduceSumSquare",
    "ReduceLogSum",
    "ReduceLogSumExp",
)
INDEX_OUTPUT = helper.make_tensor_value_info("y", TensorProto.INT64, None)


def conv(x: str, out: str, c_in: int, c_out: int) -> tuple[helper.NodeProto, dict]:
    """A 1x1 Conv (its output is channels-last inside NNCG) and its weights."""
    return helper.make_node("Conv", [x, f"w_{out}"], [out]), {f"w_{out}": weights(c_out, c_in, 1, 1)}


def after_conv(node: helper.NodeProto, opset: int = 13, outputs=("y",), extra=None, channels: int = 13):
    """x [1, 3, 5, 6] -> Conv to `channels` channels ("c") -> node."""
    first, initializers = conv("x", "c", 3, channels)
    return onnx_model(
        [first, node],
        inputs={"x": (1, 3, 5, 6)},
        outputs=outputs,
        initializers={**initializers, **(extra or {})},
        opset=opset,
    )


def positive(op: str, x: str, out: str) -> list[helper.NodeProto]:
    """ReduceLogSum takes the log of a sum: feed it Sigmoid(x), so that the sum is positive."""
    return [helper.make_node("Sigmoid", [x], [out])] if op == "ReduceLogSum" else []


# ------------------------------------------------------------------------------------- reductions

# name: (input shape, attributes); opset 13 (axes an attribute, ReduceSum's an input: see below)
REDUCE_CASES = {
    "spatial_no_keepdims": ((1, 13, 5, 6), {"axes": [2, 3], "keepdims": 0}),
    "channels_keepdims": ((2, 7, 3, 5), {"axes": [1]}),
    "all_default": ((2, 7, 3, 5), {}),
    "negative_axes": ((2, 7, 3, 5), {"axes": [-1, 0], "keepdims": 0}),
}


def reduce_model(op: str, shape, attrs: dict, opset: int = 13):
    """ReduceSum takes its axes as an input from opset 13, the others from 18."""
    attrs = dict(attrs)
    axes = attrs.pop("axes", None)
    as_input = op == "ReduceSum" or opset >= 18
    initializers = {"axes": np.array(axes, np.int64)} if as_input and axes is not None else {}
    if axes is not None and not as_input:
        attrs["axes"] = axes
    x = "p" if op == "ReduceLogSum" else "x"
    node = helper.make_node(op, [x, *initializers], ["y"], **attrs)
    return onnx_model([*positive(op, "x", "p"), node], inputs={"x": shape}, initializers=initializers, opset=opset)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", REDUCE_CASES)
@pytest.mark.parametrize("op", REDUCE_OPS)
def test_reduce(op, case, target):
    compile_and_check(reduce_model(op, *REDUCE_CASES[case]), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ("ReduceMax", "ReduceL2", "ReduceLogSumExp"))
def test_reduce_over_a_conv_output_vectorises_over_channels(op, target):
    """The spatial reduction of a channels-last Conv output: kept channels innermost, in vectors."""
    node = helper.make_node(op, ["c"], ["y"], axes=[2, 3], keepdims=0)
    compiled = compile_and_check(after_conv(node), target)
    assert kernel_ops(compiled) == ["Conv", op]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ("ReduceMax", "ReduceSumSquare", "ReduceL2"))
def test_reduce_opset18_axes_input(op, target):
    compile_and_check(reduce_model(op, (2, 7, 3, 5), {"axes": [1, 3], "keepdims": 0}, opset=18), target)


@pytest.mark.parametrize("target", ("ansi-c", "avx2"))
@pytest.mark.parametrize("op", ("ReduceSum", "ReduceMax", "ReduceL2", "ReduceSumSquare"))
def test_reduce_noop_with_empty_axes(op, target):
    """Sum and Max over no axes are the input; L2 and SumSquare still apply their function (|x|, x * x)."""
    m = onnx_model([helper.make_node(op, ["x"], ["y"], noop_with_empty_axes=1)], inputs={"x": (2, 7, 3)}, opset=18)
    compiled = compile_and_check(m, target)
    assert (op in ("ReduceSum", "ReduceMax")) == (op not in kernel_ops(compiled))


def test_reduce_ir_records_sorted_axes_and_keepdims():
    graph = import_onnx(reduce_model("ReduceMax", (2, 7, 3, 5), {"axes": [-1, 1], "keepdims": 0}))
    (node,) = graph.nodes
    assert (node.op, node.attrs, graph.shapes["y"]) == ("ReduceMax", ReduceAttrs((1, 3), False), (2, 3))


def test_reduce_log_sum_exp_does_not_overflow():
    """exp(100) overflows float32: the max is taken out first, as onnxruntime does."""
    nodes = [helper.make_node("Add", ["x", "big"], ["b"]), helper.make_node("ReduceLogSumExp", ["b"], ["y"], axes=[1])]
    m = onnx_model(nodes, inputs={"x": (2, 7, 3)}, initializers={"big": np.float32(100.0)})
    compile_and_check(m, "ansi-c")
    compile_and_check(m, "avx2")


def test_reduce_repeated_axes_are_refused():
    m = reduce_model("ReduceMax", (2, 7, 3), {"axes": [1, -2]})
    with pytest.raises(NncgError, match=r"^ReduceMax '.*' has axes \[1, -2\]; they must be distinct and in \[-3, 3\)"):
        nncg.compile(m)


# ------------------------------------------------------------------------------------ ArgMax/ArgMin


def arg_model(op: str, shape, opset: int = 13, **attrs):
    """ArgMax/ArgMin of Clip(x, -0.3, 0.3): many ties, so select_last_index changes the result."""
    nodes = [helper.make_node("Clip", ["x", "lo", "hi"], ["t"]), helper.make_node(op, ["t"], ["y"], **attrs)]
    bounds = {"lo": np.float32(-0.3), "hi": np.float32(0.3)}
    return onnx_model(nodes, inputs={"x": shape}, outputs={"y": INDEX_OUTPUT}, initializers=bounds, opset=opset)


ARG_CASES = {
    "default_axis": {},
    "channels_no_keepdims": {"axis": 1, "keepdims": 0},
    "last_axis_last_index": {"axis": -1, "select_last_index": 1},
    "channels_last_index": {"axis": 1, "keepdims": 0, "select_last_index": 1},
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ARG_CASES)
@pytest.mark.parametrize("op", ("ArgMax", "ArgMin"))
def test_arg_extreme(op, case, target):
    compile_and_check(arg_model(op, (2, 7, 3, 5), **ARG_CASES[case]), target)


@pytest.mark.parametrize("target", TARGETS)
def test_argmax_over_conv_channels(target):
    """The class map of a segmentation head: ArgMax over the 13 channels of a Conv, per pixel."""
    node = helper.make_node("ArgMax", ["c"], ["y"], axis=1, keepdims=0)
    compile_and_check(after_conv(node, outputs={"y": INDEX_OUTPUT}), target)


def test_select_last_index_differs_from_the_first():
    """On Clip's ties the two index choices differ: the inputs the tests use exercise both."""
    models = [arg_model("ArgMax", (2, 7, 3, 5), axis=1, select_last_index=last) for last in (0, 1)]
    specs = nncg.compile(models[0]).inputs
    inputs = random_inputs(specs, 0)
    first, last = (reference_outputs(m, specs, inputs)[0] for m in models)
    assert (first < last).any() and (first <= last).all()


def test_argmax_ir_and_output_shape():
    graph = import_onnx(arg_model("ArgMin", (2, 7, 3), axis=-2, keepdims=0))
    node = graph.nodes[-1]
    assert (node.op, node.attrs, graph.shapes["y"]) == ("ArgMin", ArgMaxAttrs(1, False, False), (2, 3))


def test_argmax_with_a_bad_axis_is_refused():
    """ONNX shape inference catches it, naming the op and the attribute."""
    with pytest.raises(NncgError, match=r"^ONNX shape inference .*ArgMax.*'axis' must be in"):
        nncg.compile(arg_model("ArgMax", (2, 7, 3), axis=3))


def test_other_int64_outputs_are_still_refused():
    """Only an ArgMax/ArgMin output may be int64 (NNCG writes its indices as int32)."""
    nodes = [helper.make_node("ArgMax", ["x"], ["a"]), helper.make_node("Identity", ["a"], ["y"])]
    m = onnx_model(nodes, inputs={"x": (2, 7)}, outputs={"y": INDEX_OUTPUT})
    with pytest.raises(NncgError, match="output 'y' is int64"):
        nncg.compile(m)


# --------------------------------------------------------------------------------- normalisations


def norm_parameters(*shape: int, bias: bool = True) -> dict:
    """scale around 1 and bias, fixed-seed."""
    params = {"scale": (1 + weights(1, *shape)[0]).astype(np.float32)}
    return {**params, "bias": weights(1, *shape)[0]} if bias else params


def instance_norm(x: str = "c", **attrs):
    return helper.make_node("InstanceNormalization", [x, "scale", "bias"], ["y"], **attrs)


def group_norm(groups: int, x: str = "c", out: str = "y", **attrs):
    return helper.make_node("GroupNormalization", [x, "scale", "bias"], [out], num_groups=groups, **attrs)


def layer_norm(x: str = "x", bias: bool = True, outputs=("y",), **attrs):
    return helper.make_node("LayerNormalization", [x, "scale", *(["bias"] if bias else [])], list(outputs), **attrs)


NORM_MODELS = {
    "instance_after_conv": lambda: after_conv(instance_norm(), extra=norm_parameters(13)),
    "instance_planar_epsilon": lambda: onnx_model(
        [instance_norm("x", epsilon=0.1)], inputs={"x": (2, 7, 4, 5)}, initializers=norm_parameters(7)
    ),
    "group_per_channel_opset21": lambda: after_conv(group_norm(3), opset=21, extra=norm_parameters(12), channels=12),
    "group_of_three_channels": lambda: after_conv(group_norm(4), opset=21, extra=norm_parameters(12), channels=12),
    "group_one_channel_each": lambda: after_conv(group_norm(7), opset=21, extra=norm_parameters(7), channels=7),
    "group_planar": lambda: onnx_model(
        [group_norm(2, "x", epsilon=1e-3)], inputs={"x": (1, 10, 3, 7)}, initializers=norm_parameters(10), opset=21
    ),
    "layer_last_axis": lambda: onnx_model(
        [layer_norm()], inputs={"x": (2, 5, 11)}, initializers=norm_parameters(11), opset=17
    ),
    "layer_two_axes_no_bias": lambda: onnx_model(
        [layer_norm(axis=1, bias=False, epsilon=0.01)],
        inputs={"x": (3, 4, 9)},
        initializers=norm_parameters(4, 9, bias=False),
        opset=17,
    ),
    "layer_broadcast_scale": lambda: onnx_model(
        [layer_norm(axis=-2)], inputs={"x": (2, 3, 6, 7)}, initializers=norm_parameters(1, 7), opset=17
    ),
    "layer_after_conv_channels": lambda: after_conv(layer_norm("c", axis=1), opset=17, extra=norm_parameters(13, 5, 6)),
    "layer_statistics_outputs": lambda: onnx_model(
        [layer_norm(axis=-1, outputs=("y", "mean", "inv_std"))],
        inputs={"x": (2, 5, 11)},
        outputs=("y", "mean", "inv_std"),
        initializers=norm_parameters(11),
        opset=17,
    ),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", NORM_MODELS)
def test_normalization(case, target):
    compile_and_check(NORM_MODELS[case](), target)


@pytest.mark.parametrize("target", TARGETS)
def test_conv_group_norm_relu(target):
    """A small model: Conv -> GroupNormalization -> Relu -> Conv; the Relu is applied at the
    normalisation's store."""
    first, w1 = conv("x", "c", 3, 12)
    second, w2 = conv("r", "y", 12, 5)
    nodes = [first, group_norm(4, "c", "g", epsilon=1e-5), helper.make_node("Relu", ["g"], ["r"])]
    m = onnx_model(
        [*nodes, second], inputs={"x": (1, 3, 8, 9)}, initializers={**w1, **w2, **norm_parameters(12)}, opset=21
    )
    compiled = compile_and_check(m, target)
    assert kernel_ops(compiled)[:3] == ["Conv", "GroupNormalization", "Conv"]  # then a layout Copy


@pytest.mark.parametrize("target", TARGETS)
def test_conv_layer_norm_over_last_axis(target):
    """A small model: Conv -> LayerNormalization over the last axis (W of NCHW)."""
    compile_and_check(after_conv(layer_norm("c", axis=-1), opset=17, extra=norm_parameters(6)), target)


@pytest.mark.parametrize("target", ("ansi-c", "avx2"))
def test_normalization_of_large_offsets_is_stable(target):
    """x + 1000 with a spread of about 1: E[x^2] - E[x]^2 would lose every digit of the variance in
    float32; the two-pass variance keeps them."""
    nodes = [helper.make_node("Add", ["x", "offset"], ["o"]), layer_norm("o", axis=-1)]
    m = onnx_model(
        nodes,
        inputs={"x": (2, 3, 16)},
        initializers={"offset": np.float32(1000.0), **norm_parameters(16)},
        opset=17,
    )
    compile_and_check(m, target)


@pytest.mark.parametrize("target", ("ansi-c", "avx2"))
def test_activation_after_layer_norm_with_statistics_stays_apart(target):
    """The fused activation would apply to y only, but merging rewrites all outputs: not fused."""
    nodes = [layer_norm(outputs=("n", "mean", "inv_std")), helper.make_node("Sigmoid", ["n"], ["y"])]
    m = onnx_model(
        nodes,
        inputs={"x": (2, 5, 11)},
        outputs=("y", "mean", "inv_std"),
        initializers=norm_parameters(11),
        opset=17,
    )
    compiled = compile_and_check(m, target)
    assert kernel_ops(compiled) == ["LayerNormalization", "Sigmoid"]


def test_normalization_ir():
    graph = import_onnx(NORM_MODELS["group_of_three_channels"]())
    node = graph.nodes[-1]
    assert (node.op, node.attrs) == ("GroupNormalization", NormAttrs(groups=4))
    graph = import_onnx(NORM_MODELS["layer_statistics_outputs"]())
    (node,) = graph.nodes
    assert node.outputs == ("y", "mean", "inv_std")
    assert node.attrs == NormAttrs(axis=2, mean_output=True, inv_std_output=True)
    assert graph.shapes["mean"] == (2, 5, 1)


def test_unused_statistics_outputs_are_not_computed():
    m = onnx_model(
        [layer_norm(outputs=("y", "mean", "inv_std"))],
        inputs={"x": (2, 5, 11)},
        initializers=norm_parameters(11),
        opset=17,
    )
    (node,) = import_onnx(m).nodes
    assert node.outputs == ("y",) and not node.attrs.mean_output


def test_group_norm_groups_must_divide_the_channels():
    m = after_conv(group_norm(5), opset=21, extra=norm_parameters(12), channels=12)
    with pytest.raises(NncgError, match=r"^GroupNormalization '.*' has num_groups=5; it must divide the 12 channels$"):
        nncg.compile(m)


def test_group_norm_before_opset_21_is_refused():
    """Opsets 18-20 scaled per group; onnx has deprecated that form and its checker refuses it."""
    m = after_conv(group_norm(4), opset=18, extra=norm_parameters(4), channels=12)
    with pytest.raises(NncgError, match=r"^operators that ONNX opset 18 does not have \(or has deprecated.*GroupNorm"):
        nncg.compile(m)


def test_group_norm_scale_of_the_wrong_shape_is_refused():
    m = after_conv(group_norm(4), opset=21, extra=norm_parameters(4), channels=12)
    with pytest.raises(NncgError, match=r"has scale of shape \[4\]; expected \[12\] \(one per channel\)$"):
        nncg.compile(m)


def test_layer_norm_scale_that_does_not_broadcast_is_refused():
    m = onnx_model([layer_norm(axis=-1)], inputs={"x": (2, 5, 11)}, initializers=norm_parameters(5), opset=17)
    with pytest.raises(NncgError, match=r"does not broadcast to the normalised dims \[11\]$"):
        nncg.compile(m)


def test_layer_norm_axis_out_of_range_is_refused():
    m = onnx_model([layer_norm(axis=3)], inputs={"x": (2, 5, 11)}, initializers=norm_parameters(11), opset=17)
    with pytest.raises(NncgError, match=r"^LayerNormalization '.*' has axis 3; it must be in \[-3, 3\) for its rank-3"):
        nncg.compile(m)


# ------------------------------------------------------------------------------------------- NEON

NEON_MODELS = {
    "reduce_l2_after_conv": lambda: after_conv(helper.make_node("ReduceL2", ["c"], ["y"], axes=[2, 3], keepdims=0)),
    "reduce_log_sum_exp": lambda: reduce_model("ReduceLogSumExp", (2, 7, 3, 5), {"axes": [1]}),
    "reduce_min_all": lambda: reduce_model("ReduceMin", (2, 7, 3, 5), {}),
    "argmax_last_index": lambda: arg_model("ArgMax", (2, 7, 3, 5), axis=1, select_last_index=1),
    "instance_after_conv": NORM_MODELS["instance_after_conv"],
    "group_of_three_channels": NORM_MODELS["group_of_three_channels"],
    "layer_statistics_outputs": NORM_MODELS["layer_statistics_outputs"],
}


@pytest.mark.parametrize("toolchain", NEON_TOOLCHAINS)
@pytest.mark.parametrize("case", NEON_MODELS)
def test_neon_matches_onnxruntime(case, toolchain):
    check_on_neon(toolchain, NEON_MODELS[case]())
