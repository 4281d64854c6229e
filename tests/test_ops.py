"""Per-operator tests: a one- or two-node ONNX model per attribute combination, compiled for every
target, run, and compared with onnxruntime on the same inputs."""

import numpy as np
import pytest
from helpers import RNG, compile_and_check, kernel_ops, onnx_model, weights
from onnx import helper

TARGETS = ["ansi-c", "ssse3"]


def batchnorm_params(c):
    """Inference statistics for BatchNormalization inputs g, beta, mu, var (float32)."""
    params = {
        "g": RNG.uniform(0.5, 1.5, c),
        "beta": RNG.normal(0, 0.1, c),
        "mu": RNG.normal(0, 0.1, c),
        "var": RNG.uniform(0.5, 1.5, c),
    }
    return {name: p.astype(np.float32) for name, p in params.items()}


def conv_model(x_shape, c_out, kernel, bias=True, **attrs):
    c_in = x_shape[1] // attrs.get("group", 1)
    inits = {"w": weights(c_out, c_in, *kernel), **({"b": weights(c_out)} if bias else {})}
    node = helper.make_node("Conv", ["x", "w"] + (["b"] if bias else []), ["y"], **attrs)
    return onnx_model([node], inputs={"x": x_shape}, initializers=inits)


CONV_CASES = {
    "3x3_pad1": ((1, 3, 7, 9), 8, (3, 3), dict(pads=[1, 1, 1, 1])),
    "asymmetric_pads": ((1, 2, 6, 6), 4, (3, 3), dict(pads=[0, 1, 2, 1])),
    "same_upper_stride2": ((1, 2, 7, 8), 8, (3, 3), dict(auto_pad="SAME_UPPER", strides=[2, 2])),
    "same_lower_stride2": ((1, 2, 7, 8), 8, (4, 4), dict(auto_pad="SAME_LOWER", strides=[2, 2])),
    "valid": ((1, 3, 6, 5), 4, (2, 3), dict(auto_pad="VALID")),
    "strides_2x1": ((1, 2, 9, 7), 4, (3, 3), dict(strides=[2, 1], pads=[1, 1, 1, 1])),
    "dilations": ((1, 2, 9, 9), 4, (3, 3), dict(dilations=[2, 2], pads=[2, 2, 2, 2])),
    "channel_tail_6": ((1, 3, 5, 5), 6, (3, 3), dict(pads=[1, 1, 1, 1])),
    "one_channel_out": ((1, 3, 5, 5), 1, (3, 3), dict()),
    "pointwise_1x1": ((1, 8, 4, 4), 12, (1, 1), dict()),
    "batch_2": ((2, 3, 5, 5), 4, (3, 3), dict(pads=[1, 1, 1, 1])),
    "conv1d": ((1, 3, 11), 4, (3,), dict(pads=[1, 1], strides=[2])),
    "conv3d": ((1, 2, 4, 5, 5), 4, (2, 3, 3), dict(pads=[0, 1, 1, 1, 1, 1])),
    "pads_exceed_kernel": ((1, 1, 4, 4), 4, (2, 2), dict(pads=[3, 3, 3, 3])),
    "depthwise": ((1, 8, 6, 6), 8, (3, 3), dict(group=8, pads=[1, 1, 1, 1])),
    "depthwise_stride2_multiplier2": ((1, 4, 7, 7), 8, (3, 3), dict(group=4, strides=[2, 2], pads=[1, 1, 1, 1])),
    "grouped": ((1, 6, 5, 5), 12, (3, 3), dict(group=3, pads=[1, 1, 1, 1])),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CONV_CASES)
def test_conv(case, target):
    x_shape, c_out, kernel, attrs = CONV_CASES[case]
    compile_and_check(conv_model(x_shape, c_out, kernel, bias=case != "valid", **attrs), target)


@pytest.mark.parametrize("unroll", [0, 2, None])
def test_conv_padding_at_every_unroll_level_under_sanitizers(unroll):
    m = conv_model((1, 3, 6, 7), 8, (3, 3), pads=[1, 2, 1, 0], strides=[2, 1])
    for target in TARGETS:
        compile_and_check(m, target, unroll=unroll, sanitize=True)


POOL_CASES = {
    "2x2_stride2": ((1, 8, 6, 6), dict(kernel_shape=[2, 2], strides=[2, 2])),
    "3x3_stride2_pad1": ((1, 4, 7, 7), dict(kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1])),
    "ceil_mode": ((1, 4, 5, 5), dict(kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1)),
    "ceil_mode_pads": ((1, 4, 6, 6), dict(kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1], ceil_mode=1)),
    "dilations": ((1, 4, 7, 7), dict(kernel_shape=[2, 2], dilations=[2, 2])),
    "odd_floor": ((1, 5, 9, 4), dict(kernel_shape=[2, 2], strides=[2, 2])),
    "pool1d": ((1, 4, 9), dict(kernel_shape=[3], strides=[2], pads=[1, 1])),
    # both rows the dilated window reads are padding: onnxruntime gives -FLT_MAX (fuzz-found)
    "window_in_padding": ((2, 4, 1, 5), dict(kernel_shape=[2, 3], dilations=[2, 2], pads=[1, 0, 1, 1], strides=[2, 2])),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", POOL_CASES)
def test_maxpool(case, target):
    x_shape, attrs = POOL_CASES[case]
    node = helper.make_node("MaxPool", ["x"], ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"x": x_shape}), target, sanitize=case == "ceil_mode_pads")


AVERAGE_POOL_CASES = {
    "2x2_stride2": ((1, 8, 6, 6), dict(kernel_shape=[2, 2], strides=[2, 2])),
    "3x3_pads_exclude": ((1, 4, 7, 7), dict(kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1])),
    "3x3_pads_include": (
        (1, 4, 7, 7),
        dict(kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1], count_include_pad=1),
    ),
    "ceil_mode_asymmetric_pads": (
        (1, 4, 6, 7),
        dict(kernel_shape=[3, 2], strides=[2, 2], pads=[0, 1, 1, 0], ceil_mode=1),
    ),
    "ceil_mode_include_pad": (
        (1, 4, 6, 6),
        dict(kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1], ceil_mode=1, count_include_pad=1),
    ),
    "pool1d": ((1, 4, 9), dict(kernel_shape=[3], strides=[2], pads=[1, 1])),
    # both rows the dilated window reads are padding: onnxruntime gives 0
    "window_in_padding": ((2, 4, 1, 5), dict(kernel_shape=[2, 3], dilations=[2, 2], pads=[1, 0, 1, 1], strides=[2, 2])),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", AVERAGE_POOL_CASES)
def test_averagepool(case, target):
    x_shape, attrs = AVERAGE_POOL_CASES[case]
    node = helper.make_node("AveragePool", ["x"], ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"x": x_shape}, opset=19), target, unroll=1)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["GlobalAveragePool", "GlobalMaxPool"])
@pytest.mark.parametrize("unroll", [2, None])
def test_global_pools(op, unroll, target):
    compile_and_check(
        onnx_model([helper.make_node(op, ["x"], ["y"])], inputs={"x": (1, 12, 5, 7)}), target, unroll=unroll
    )


CLIP_CASES = {
    "relu6": (13, {"lo": np.float32(0.0), "hi": np.float32(6.0)}, ["x", "lo", "hi"], {}),
    "min_only": (13, {"lo": np.float32(-0.5)}, ["x", "lo"], {}),
    "max_only": (13, {"hi": np.float32(0.25)}, ["x", "", "hi"], {}),
    "opset10_attributes": (10, {}, ["x"], dict(min=-0.3, max=0.4)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CLIP_CASES)
def test_clip(case, target):
    opset, inits, inputs, attrs = CLIP_CASES[case]
    node = helper.make_node("Clip", inputs, ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"x": (1, 3, 4, 8)}, initializers=inits, opset=opset), target)


@pytest.mark.parametrize("target", TARGETS)
def test_depthwise_conv_clip_is_fused_relu6(target):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], group=8, pads=[1, 1, 1, 1]),
        helper.make_node("Clip", ["c", "lo", "hi"], ["y"]),
    ]
    inits = {"w": 3 * weights(8, 1, 3, 3), "b": weights(8), "lo": np.float32(0), "hi": np.float32(6)}
    compiled = compile_and_check(onnx_model(nodes, inputs={"x": (1, 8, 5, 5)}, initializers=inits), target)
    assert "Clip" not in kernel_ops(compiled)


ACTIVATIONS = {
    "relu": ("Relu", {}),
    "leaky_relu_0.1": ("LeakyRelu", dict(alpha=0.1)),
    "leaky_relu_default": ("LeakyRelu", {}),
    "leaky_relu_1.5": ("LeakyRelu", dict(alpha=1.5)),
    "leaky_relu_negative": ("LeakyRelu", dict(alpha=-0.2)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ACTIVATIONS)
def test_standalone_activation(case, target):
    op, attrs = ACTIVATIONS[case]
    compile_and_check(onnx_model([helper.make_node(op, ["x"], ["y"], **attrs)], inputs={"x": (1, 3, 4, 8)}), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("act", ["Relu", "LeakyRelu"])
def test_conv_batchnorm_activation_fused(act, target):
    c = 8
    bn = batchnorm_params(c)
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("BatchNormalization", ["c", "g", "beta", "mu", "var"], ["bn"], epsilon=1e-3),
        helper.make_node(act, ["bn"], ["y"], **({"alpha": 0.1} if act == "LeakyRelu" else {})),
    ]
    m = onnx_model(nodes, inputs={"x": (1, 3, 6, 6)}, initializers={"w": weights(c, 3, 3, 3), **bn})
    compiled = compile_and_check(m, target)
    kernels = kernel_ops(compiled)
    assert kernels[0] == "Conv" and "ScaleShift" not in kernels and "BatchNormalization" not in kernels


@pytest.mark.parametrize("target", TARGETS)
def test_standalone_batchnorm(target):
    c = 4
    bn = batchnorm_params(c)
    node = helper.make_node("BatchNormalization", ["x", "g", "beta", "mu", "var"], ["y"])
    compile_and_check(onnx_model([node], inputs={"x": (1, c, 3, 5)}, initializers=bn), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("axis", [0, 1, 2, 3, -1])
def test_softmax(axis, target):
    node = helper.make_node("Softmax", ["x"], ["y"], axis=axis)
    compile_and_check(onnx_model([node], inputs={"x": (2, 3, 4, 5)}), target)


@pytest.mark.parametrize("axis", [1, 2])
def test_softmax_opset_11_flattens_from_axis(axis):
    node = helper.make_node("Softmax", ["x"], ["y"], axis=axis)
    compile_and_check(onnx_model([node], inputs={"x": (2, 3, 4, 5)}, opset=11), "ansi-c")


def test_softmax_is_stable_for_large_inputs():
    node = helper.make_node("Softmax", ["x"], ["y"], axis=1)
    m = onnx_model(
        [helper.make_node("Mul", ["x", "k"], ["big"]), node],
        inputs={"x": (1, 6)},
        initializers={"k": np.float32(500.0)},
    )
    m.graph.node[1].input[0] = "big"
    compile_and_check(m, "ansi-c")


@pytest.mark.parametrize("target", TARGETS)
def test_conv_dropout_flatten_gemm(target):
    nodes = [
        helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c"], ["r"]),
        helper.make_node("Dropout", ["r"], ["d"]),
        helper.make_node("Flatten", ["d"], ["f"]),
        helper.make_node("Gemm", ["f", "fc_w", "fc_b"], ["y"], transB=1),
    ]
    inits = {"w": weights(4, 2, 3, 3), "b": weights(4), "fc_w": weights(10, 4 * 5 * 6), "fc_b": weights(10)}
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 2, 5, 6)}, initializers=inits), target)


GEMM_CASES = {
    "plain": (dict(), (1, 16), (16, 12), (12,)),
    "trans_b_alpha_beta": (dict(transB=1, alpha=0.5, beta=2.0), (1, 16), (12, 16), (1, 12)),
    "trans_a": (dict(transA=1), (16, 3), (16, 8), (8,)),
    "no_bias_rows": (dict(), (3, 7), (7, 5), None),
    "scalar_c": (dict(), (2, 9), (9, 6), ()),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", GEMM_CASES)
def test_gemm(case, target):
    attrs, a_shape, b_shape, c_shape = GEMM_CASES[case]
    inits = {"B": weights(*b_shape)}
    if c_shape is not None:
        inits["C"] = RNG.standard_normal(c_shape).astype(np.float32)
    node = helper.make_node("Gemm", ["x", "B"] + (["C"] if c_shape is not None else []), ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"x": a_shape}, initializers=inits), target)


@pytest.mark.parametrize("target", TARGETS)
def test_matmul_add_is_a_dense_layer(target):
    nodes = [helper.make_node("MatMul", ["x", "w"], ["mm"]), helper.make_node("Add", ["mm", "b"], ["y"])]
    m = onnx_model(nodes, inputs={"x": (1, 20)}, initializers={"w": weights(20, 9), "b": weights(9)})
    compile_and_check(m, target)


@pytest.mark.parametrize("target", TARGETS)
def test_matmul_rank3(target):
    m = onnx_model(
        [helper.make_node("MatMul", ["x", "w"], ["y"])], inputs={"x": (1, 3, 10)}, initializers={"w": weights(10, 8)}
    )
    compile_and_check(m, target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["Add", "Sub", "Mul", "Div"])
def test_binary_broadcasting(op, target):
    nodes = [
        helper.make_node(op, ["x", "per_channel"], ["t"]),
        helper.make_node(op, ["t", "x2"], ["y"]),
    ]
    inits = {"per_channel": RNG.uniform(0.5, 2.0, (3, 1, 1)).astype(np.float32)}
    m = onnx_model(nodes, inputs={"x": (1, 3, 4, 5), "x2": (1, 1, 4, 5)}, initializers=inits)
    if op == "Div":  # keep the divisor away from zero
        m.graph.node[1].op_type = "Mul"
    compile_and_check(m, target)


@pytest.mark.parametrize("target", TARGETS)
def test_reshape_between_layouts(target):
    """A channels-last conv output reshaped to row-major order needs a real copy."""
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Reshape", ["c", "shape"], ["y"]),
    ]
    inits = {"w": weights(4, 2, 3, 3), "shape": np.array([1, 4, 12], dtype=np.int64)}
    m = onnx_model(nodes, inputs={"x": (1, 2, 3, 4)}, initializers=inits)
    compile_and_check(m, target)


def test_identity_model_copies_input_to_output():
    compile_and_check(onnx_model([helper.make_node("Identity", ["x"], ["y"])], inputs={"x": (1, 3)}), "ansi-c")


@pytest.mark.parametrize("target", TARGETS)
def test_tensors_named_like_loop_variables_and_locals(target):
    """Inputs called `w` and `acc` and an output `oh` must not clash with the C function's locals."""
    node = helper.make_node("Conv", ["w", "acc"], ["oh"], pads=[1, 1, 1, 1])
    m = onnx_model([node], inputs={"w": (1, 3, 5, 5), "acc": (4, 3, 3, 3)}, outputs={"oh": (1, 4, 5, 5)})
    for unroll in (None, 2):
        compile_and_check(m, target, unroll=unroll)
