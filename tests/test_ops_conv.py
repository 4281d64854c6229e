"""Conv-family tests: runtime weights (Conv, Gemm, MatMul, BatchNormalization), ConvTranspose and
the residual fusion, each a small ONNX model compiled for every target and compared with
onnxruntime. Runtime weights are model inputs, which the verifier fills with random data."""

import itertools
import re

import numpy as np
import pytest
from helpers import RNG, compile_and_check, kernel_ops, onnx_model, weights
from onnx import helper

import nncg
from nncg.errors import NncgError
from nncg.lowering.context import TensorRef
from nncg.lowering.weights import permuted, split

TARGETS = ["ansi-c", "ssse3"]
OPSET = 17


# ------------------------------------------------------------------------------ runtime weights


@pytest.mark.parametrize("order", list(itertools.permutations(range(4)))[::5])
def test_weight_view_reads_the_elements_numpy_would_in_any_layout(order):
    """A runtime weight may live in any layout: split + permute over it must address exactly the
    elements of the same reshape + transpose in NumPy."""
    shape = (4, 3, 2, 5)
    ref = TensorRef("w", shape, order)
    logical = RNG.standard_normal(shape)
    memory = np.empty(logical.size)
    for idx in itertools.product(*map(range, shape)):
        memory[ref.at(idx).const] = logical[idx]
    view = permuted(split(ref, 0, 2), (3, 4, 1, 0, 2))  # ConvTranspose's [k..., ci, g, co] of [2*2, 3, 2, 5]
    expected = np.transpose(logical.reshape(2, 2, 3, 2, 5), (3, 4, 1, 0, 2))
    got = np.array([memory[view.at(idx).const] for idx in itertools.product(*map(range, view.shape))])
    np.testing.assert_array_equal(got.reshape(expected.shape), expected)


RUNTIME_CONV_CASES = {
    "3x3_pad1_bias": ((1, 3, 6, 7), 5, (3, 3), True, dict(pads=[1, 1, 1, 1])),
    "strides_dilations": ((1, 2, 9, 8), 4, (3, 2), True, dict(strides=[2, 1], dilations=[1, 2], pads=[1, 0, 1, 2])),
    "no_bias": ((1, 3, 5, 5), 8, (3, 3), False, dict()),
    "grouped": ((1, 6, 5, 5), 4, (3, 3), True, dict(group=2, pads=[1, 1, 1, 1])),
    "depthwise": ((1, 8, 5, 6), 8, (3, 3), True, dict(group=8, pads=[1, 1, 1, 1])),
    "conv1d": ((2, 3, 10), 4, (3,), True, dict(strides=[2])),
    "conv3d": ((1, 2, 4, 4, 5), 3, (2, 3, 3), True, dict(pads=[0, 1, 1, 1, 1, 1])),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", RUNTIME_CONV_CASES)
def test_conv_with_runtime_weights(case, target):
    x_shape, c_out, kernel, bias, attrs = RUNTIME_CONV_CASES[case]
    inputs = {"x": x_shape, "W": (c_out, x_shape[1] // attrs.get("group", 1), *kernel)}
    if bias:
        inputs["B"] = (c_out,)
    m = onnx_model([helper.make_node("Conv", list(inputs), ["y"], **attrs)], inputs=inputs, opset=OPSET)
    compile_and_check(m, target)


def test_conv_runtime_weights_under_sanitizers():
    inputs = {"x": (1, 4, 5, 6), "W": (6, 2, 3, 3), "B": (6,)}
    node = helper.make_node("Conv", list(inputs), ["y"], group=2, strides=[2, 1], pads=[1, 0, 2, 1])
    for target in TARGETS:
        compile_and_check(onnx_model([node], inputs=inputs, opset=OPSET), target, unroll=2, sanitize=True)


@pytest.mark.parametrize("target", TARGETS)
def test_conv_weight_computed_by_another_layer_in_channels_last_order(target):
    """The weight is the output of a 1x1 Conv, which stores it channels-last: the conv reads it
    through a view with those strides, and a BatchNorm after it cannot be folded."""
    nodes = [
        helper.make_node("Conv", ["seed", "mix"], ["W"]),  # [4, 3, 3, 3] read as N=4, C=3, 3x3
        helper.make_node("Conv", ["x", "W", "b"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("BatchNormalization", ["c", "g", "beta", "mu", "var"], ["y"]),
    ]
    bn = {"g": RNG.uniform(0.5, 1.5, 4), "beta": RNG.normal(0, 0.1, 4), "mu": RNG.normal(0, 0.1, 4)}
    bn["var"] = RNG.uniform(0.5, 1.5, 4)
    inits = {"mix": weights(3, 3, 1, 1), "b": weights(4), **{name: p.astype(np.float32) for name, p in bn.items()}}
    inputs = {"x": (1, 3, 5, 5), "seed": (4, 3, 3, 3)}
    compiled = compile_and_check(onnx_model(nodes, inputs=inputs, initializers=inits, opset=OPSET), target)
    assert kernel_ops(compiled)[:3] == ["Conv", "Conv", "ScaleShift"]


@pytest.mark.parametrize("target", TARGETS)
def test_batchnorm_with_runtime_statistics(target):
    """ONNX node tests feed the statistics as inputs; the variance is squared here to keep it positive."""
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Mul", ["v", "v"], ["v2"]),
        helper.make_node("Add", ["v2", "eps"], ["var"]),
        helper.make_node("BatchNormalization", ["c", "g", "beta", "mu", "var"], ["bn"], epsilon=1e-3),
        helper.make_node("Relu", ["bn"], ["y"]),
    ]
    inputs = {"x": (1, 3, 5, 6), "g": (6,), "beta": (6,), "mu": (6,), "v": (6,)}
    compiled = compile_and_check(
        onnx_model(nodes, inputs=inputs, initializers={"w": weights(6, 3, 3, 3), "eps": np.float32(0.1)}, opset=OPSET),
        target,
    )
    assert "BatchNormalization" in kernel_ops(compiled)


GEMM_CASES = {
    "b_runtime": (dict(), (3, 6), {"B": (6, 5)}, None),
    "b_runtime_trans_alpha_beta": (dict(transB=1, alpha=0.5, beta=2.0), (3, 6), {"B": (5, 6)}, ("C", (5,))),
    "b_runtime_trans_a": (dict(transA=1, transB=1), (6, 3), {"B": (5, 6)}, ("C", (1, 5))),
    "c_runtime_matrix": (dict(beta=0.5), (3, 6), {"C": (3, 5)}, ("B", (6, 5))),
    "c_runtime_column": (dict(alpha=2.0), (3, 6), {"B": (6, 5), "C": (3, 1)}, None),
    "c_runtime_scalar": (dict(transB=1), (2, 6), {"B": (5, 6), "C": ()}, None),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", GEMM_CASES)
def test_gemm_with_runtime_operands(case, target):
    attrs, a_shape, runtime, constant = GEMM_CASES[case]
    inits = {constant[0]: weights(*constant[1])} if constant else {}
    names = [n for n in ("B", "C") if n in runtime or (constant and constant[0] == n)]
    node = helper.make_node("Gemm", ["a", *names], ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"a": a_shape, **runtime}, initializers=inits, opset=OPSET), target)


MATMUL_CASES = {
    "2d_x_2d": ({"a": (3, 7), "b": (7, 5)}, []),
    "constant_a": ({"b": (7, 5)}, [("a", (3, 7))]),
    "batched": ({"a": (2, 3, 4), "b": (2, 4, 6)}, []),
    "batch_broadcast": ({"a": (2, 1, 3, 5), "b": (3, 5, 4)}, []),
    "constant_batched_b": ({"a": (2, 3, 4)}, [("b", (2, 4, 5))]),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", MATMUL_CASES)
def test_matmul_with_runtime_b(case, target):
    inputs, constants = MATMUL_CASES[case]
    inits = {name: weights(*shape) for name, shape in constants}
    m = onnx_model([helper.make_node("MatMul", ["a", "b"], ["y"])], inputs=inputs, initializers=inits, opset=OPSET)
    compile_and_check(m, target)


def test_matmul_of_activations_under_sanitizers():
    nodes = [helper.make_node("MatMul", ["a", "b"], ["t"]), helper.make_node("Relu", ["t"], ["y"])]
    m = onnx_model(nodes, inputs={"a": (2, 3, 5), "b": (2, 5, 6)}, opset=OPSET)
    for target in TARGETS:
        compile_and_check(m, target, unroll=None, sanitize=True)


# ------------------------------------------------------------------------------ ConvTranspose

CONV_TRANSPOSE_CASES = {
    "stride1": ((1, 3, 4, 5), 4, (3, 3), dict()),
    "stride2_pads": ((1, 3, 4, 5), 6, (3, 3), dict(strides=[2, 2], pads=[1, 0, 0, 1])),
    "stride2_kernel4": ((1, 2, 3, 4), 4, (4, 4), dict(strides=[2, 2], pads=[1, 1, 1, 1])),
    "stride3_dilation2_outpad": (
        (1, 2, 3, 4),
        5,
        (3, 2),
        dict(strides=[3, 2], dilations=[2, 1], output_padding=[2, 1]),
    ),
    "stride_exceeds_kernel": ((1, 2, 3, 3), 3, (2, 2), dict(strides=[3, 3])),
    "dilation_shares_stride_factor": ((1, 2, 4), 4, (4,), dict(strides=[4], dilations=[2], pads=[1, 2])),
    "grouped": ((1, 4, 3, 4), 6, (3, 3), dict(group=2, strides=[2, 1])),
    "depthwise": ((1, 8, 3, 3), 8, (3, 3), dict(group=8, strides=[2, 2], pads=[1, 1, 1, 1])),
    "channel_tail_and_batch": ((2, 3, 3, 3), 6, (2, 2), dict(strides=[2, 2])),
    "conv1d": ((1, 3, 5), 4, (3,), dict(strides=[2], pads=[1, 1], output_padding=[1])),
    "conv3d": ((1, 2, 2, 3, 3), 4, (2, 3, 3), dict(strides=[2, 2, 1], pads=[0, 1, 1, 1, 0, 1])),
    "output_shape": ((1, 2, 3, 4), 4, (3, 3), dict(strides=[2, 2], output_shape=[6, 8])),
    "same_upper_shape": ((1, 2, 3, 4), 4, (3, 3), dict(strides=[2, 2], output_shape=[5, 8], auto_pad="SAME_UPPER")),
    "output_shape_beyond_full": ((1, 2, 3, 3), 4, (3, 3), dict(strides=[3, 2], output_shape=[10, 8])),
    "same_upper": ((1, 2, 3, 4), 4, (3, 3), dict(strides=[2, 2], auto_pad="SAME_UPPER")),
    "same_lower": ((1, 2, 3, 4), 4, (3, 4), dict(strides=[2, 2], auto_pad="SAME_LOWER")),
    # fuzz-found: ONNX inference adds output_padding to a SAME output, onnxruntime gives in * stride
    "same_upper_output_padding": ((1, 22, 7), 33, (2,), dict(strides=[2], auto_pad="SAME_UPPER", output_padding=[1])),
    "valid": ((1, 2, 3, 4), 4, (3, 3), dict(strides=[2, 2], auto_pad="VALID")),
}


def conv_transpose_model(x_shape, c_out, kernel, runtime=False, bias=True, **attrs):
    w_shape = (x_shape[1], c_out // attrs.get("group", 1), *kernel)
    inputs = {"x": x_shape, **({"W": w_shape} if runtime else {})}
    inits = {} if runtime else {"W": weights(*w_shape)}
    if bias:
        inits["B"] = weights(c_out)
    node = helper.make_node("ConvTranspose", ["x", "W"] + (["B"] if bias else []), ["y"], **attrs)
    return onnx_model([node], inputs=inputs, initializers=inits, opset=OPSET)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", CONV_TRANSPOSE_CASES)
def test_conv_transpose(case, target):
    x_shape, c_out, kernel, attrs = CONV_TRANSPOSE_CASES[case]
    compile_and_check(conv_transpose_model(x_shape, c_out, kernel, bias=case != "stride1", **attrs), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ["stride2_pads", "grouped", "conv1d"])
def test_conv_transpose_with_runtime_weights(case, target):
    x_shape, c_out, kernel, attrs = CONV_TRANSPOSE_CASES[case]
    compile_and_check(conv_transpose_model(x_shape, c_out, kernel, runtime=True, **attrs), target)


@pytest.mark.parametrize("unroll", [0, 2, None])
def test_conv_transpose_at_every_unroll_level_under_sanitizers(unroll):
    m = conv_transpose_model((1, 2, 3, 3), 5, (3, 3), strides=[2, 3], pads=[1, 2, 0, 1], output_padding=[1, 0])
    for target in TARGETS:
        compile_and_check(m, target, unroll=unroll, sanitize=True)


def test_conv_transpose_vectorises_over_output_channels():
    compiled = compile_and_check(conv_transpose_model((1, 3, 4, 4), 8, (3, 3), strides=[2, 2]), "ssse3")
    assert "_mm_storeu_ps" in compiled.source


@pytest.mark.parametrize(
    "attrs, message",
    [
        (dict(strides=[2, 2], auto_pad="SAME_UPPER"), "onnxruntime and the ONNX spec disagree"),
        (dict(pads=[1, 0, 1, 0]), "crop away its whole output"),
    ],
)
def test_conv_transpose_impossible_geometry_is_a_clear_error(attrs, message):
    with pytest.raises(NncgError, match=message):
        nncg.compile(conv_transpose_model((1, 2, 1, 3), 2, (1, 1), **attrs))


# ------------------------------------------------------------------------------ residual fusion


def resnet_block(stem_input: bool, downsample: bool):
    """conv-bn-relu-conv-bn + shortcut, relu. The shortcut is the stem's output (or the graph
    input with stem_input) or, with downsample, a strided 1x1 conv of it."""
    c, c2 = 4, 8 if downsample else 4
    stride = [2, 2] if downsample else [1, 1]
    nodes = [] if stem_input else [helper.make_node("Conv", ["x", "w0", "b0"], ["s0"], pads=[1, 1, 1, 1])]
    nodes += [] if stem_input else [helper.make_node("Relu", ["s0"], ["h"])]
    h = "x" if stem_input else "h"
    nodes += [
        helper.make_node("Conv", [h, "w1"], ["c1"], pads=[1, 1, 1, 1], strides=stride),
        helper.make_node("BatchNormalization", ["c1", "g1", "be1", "m1", "v1"], ["n1"]),
        helper.make_node("Relu", ["n1"], ["r1"]),
        helper.make_node("Conv", ["r1", "w2"], ["c2"], pads=[1, 1, 1, 1]),
        helper.make_node("BatchNormalization", ["c2", "g2", "be2", "m2", "v2"], ["n2"]),
    ]
    shortcut = h
    if downsample:
        nodes.append(helper.make_node("Conv", [h, "wd", "bd"], ["d"], strides=stride))
        shortcut = "d"
    nodes += [helper.make_node("Add", ["n2", shortcut], ["sum"]), helper.make_node("Relu", ["sum"], ["y"])]
    inits = {"w0": weights(c, 3, 3, 3), "b0": weights(c), "w1": weights(c2, c, 3, 3)}
    inits |= {"w2": weights(c2, c2, 3, 3), "wd": weights(c2, c, 1, 1), "bd": weights(c2)}
    for i, ch in (("1", c2), ("2", c2)):
        bn = {f"g{i}": RNG.uniform(0.5, 1.5, ch), f"be{i}": RNG.normal(0, 0.1, ch)}
        bn |= {f"m{i}": RNG.normal(0, 0.1, ch), f"v{i}": RNG.uniform(0.5, 1.5, ch)}
        inits |= {name: p.astype(np.float32) for name, p in bn.items()}
    used = {name for node in nodes for name in node.input}
    inputs = {"x": (1, c if stem_input else 3, 6, 6)}
    return onnx_model(nodes, inputs=inputs, initializers={n: a for n, a in inits.items() if n in used}, opset=OPSET)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("downsample", [False, True], ids=["identity", "downsample"])
def test_resnet_block_fuses_the_residual_add(downsample, target):
    compiled = compile_and_check(resnet_block(stem_input=False, downsample=downsample), target, unroll=2)
    ops = kernel_ops(compiled)
    assert "Add" not in ops and "Relu" not in ops and "BatchNormalization" not in ops, ops
    if target == "ssse3":  # the residual is read channels-last, so the conv still vectorises
        assert len(re.findall(r"_mm_storeu_ps", compiled.source)) >= ops.count("Conv")


@pytest.mark.parametrize("unroll", [2, None])
def test_resnet_block_under_sanitizers(unroll):
    for target in TARGETS:
        compile_and_check(resnet_block(stem_input=False, downsample=True), target, unroll=unroll, sanitize=True)


@pytest.mark.parametrize("target", TARGETS)
def test_residual_from_the_graph_input_stays_a_separate_add(target):
    compiled = compile_and_check(resnet_block(stem_input=True, downsample=False), target, unroll=2)
    assert "Add" in kernel_ops(compiled)
