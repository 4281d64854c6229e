"""Per-operator tests of the pointwise activations, PRelu, Max/Min/Sum, LogSoftmax, LRN and
ReduceMean: small ONNX models compiled for every target and compared with onnxruntime, their
fusion into Conv/Dense, their errors, and the vector calls they need."""

import re

import numpy as np
import pytest
from helpers import RNG, check_against_onnxruntime, compile_and_check, kernel_ops, onnx_model, weights
from onnx import TensorProto, helper
from test_ops import TARGETS

import nncg
from nncg.errors import NncgError
from nncg.ir.loops import Affine, Call, Kernel, Load, Loop, Program, Store
from nncg.ir.target import Target
from nncg.passes.vectorize import vectorize
from nncg.verify import run_compiled


def scaled(node, scale=4.0, shape=(1, 3, 4, 7)):
    """x * scale -> node: inputs beyond N(0, 1) reach the saturated and negative ranges."""
    mul = helper.make_node("Mul", ["x", "k"], ["xs"])
    node.input[0] = "xs"
    return onnx_model([mul, node], inputs={"x": shape}, initializers={"k": np.float32(scale)}, opset=14)


# ------------------------------------------------------------------------------------ activations

ACTIVATIONS = {
    "sigmoid": ("Sigmoid", {}),
    "tanh": ("Tanh", {}),
    "hard_sigmoid_default": ("HardSigmoid", {}),
    "hard_sigmoid_0.3_0.4": ("HardSigmoid", dict(alpha=0.3, beta=0.4)),
    "hard_swish": ("HardSwish", {}),
    "elu_default": ("Elu", {}),
    "elu_0.5": ("Elu", dict(alpha=0.5)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ACTIVATIONS)
def test_standalone_activation(case, target):
    op, attrs = ACTIVATIONS[case]
    compile_and_check(scaled(helper.make_node(op, ["x"], ["y"], **attrs)), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", ACTIVATIONS)
def test_conv_activation_is_fused(case, target):
    """6 output channels: one vector block and a scalar tail, both applying the activation."""
    op, attrs = ACTIVATIONS[case]
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]), helper.make_node(op, ["c"], ["y"])]
    inits = {"w": 3 * weights(6, 3, 3, 3), "b": weights(6)}
    compiled = compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 5, 5)}, initializers=inits, opset=14), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]  # the copy converts channels-last to NCHW


@pytest.mark.parametrize("target", TARGETS)
def test_gemm_sigmoid_is_fused(target):
    nodes = [helper.make_node("Gemm", ["x", "w", "b"], ["g"]), helper.make_node("Sigmoid", ["g"], ["y"])]
    compiled = compile_and_check(
        onnx_model(nodes, inputs={"x": (2, 10)}, initializers={"w": weights(10, 9), "b": weights(9)}), target
    )
    assert kernel_ops(compiled) == ["Dense"]


@pytest.mark.parametrize("target", TARGETS)
def test_batchnorm_tanh_is_one_scale_shift(target):
    c = 5
    nodes = [
        helper.make_node("BatchNormalization", ["x", "g", "beta", "mu", "var"], ["bn"]),
        helper.make_node("Tanh", ["bn"], ["y"]),
    ]
    inits = {"g": RNG.uniform(1, 3, c), "beta": RNG.normal(0, 1, c), "mu": np.zeros(c), "var": np.ones(c)}
    inits = {name: array.astype(np.float32) for name, array in inits.items()}
    compiled = compile_and_check(onnx_model(nodes, inputs={"x": (1, c, 3, 4)}, initializers=inits), target)
    assert kernel_ops(compiled) == ["ScaleShift"]


@pytest.mark.parametrize("target", TARGETS)
def test_sigmoid_saturates_without_nan(target):
    """exp(-x) overflows to inf for x far below zero: the sigmoid must still be exactly 0."""
    compile_and_check(scaled(helper.make_node("Sigmoid", ["x"], ["y"]), scale=200.0), target)


def test_activations_under_sanitizers():
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("Elu", ["c"], ["e"]),
        helper.make_node("Sigmoid", ["e"], ["s"]),
        helper.make_node("HardSwish", ["s"], ["y"]),
    ]
    m = onnx_model(nodes, inputs={"x": (1, 2, 4, 5)}, initializers={"w": 3 * weights(7, 2, 3, 3)}, opset=14)
    for target in TARGETS:
        compile_and_check(m, target, sanitize=True)


# ------------------------------------------------------------------------------------------ PRelu

PRELU_SLOPES = {
    "per_channel": (3, 1, 1),
    "full": (3, 4, 5),
    "scalar": (1,),
    "last_dim": (5,),  # NumPy broadcasting aligns [5] with W, not with C
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", PRELU_SLOPES)
def test_prelu(case, target):
    slope = RNG.uniform(-0.5, 0.5, PRELU_SLOPES[case]).astype(np.float32)
    m = onnx_model(
        [helper.make_node("PRelu", ["x", "slope"], ["y"])], inputs={"x": (1, 3, 4, 5)}, initializers={"slope": slope}
    )
    compile_and_check(m, target)


@pytest.mark.parametrize("target", TARGETS)
def test_prelu_after_conv_per_channel(target):
    """Over a channels-last conv output the per-channel slope is a contiguous vector load."""
    nodes = [helper.make_node("Conv", ["x", "w"], ["c"]), helper.make_node("PRelu", ["c", "slope"], ["y"])]
    inits = {"w": weights(9, 2, 1, 1), "slope": RNG.uniform(0, 0.5, (9, 1, 1)).astype(np.float32)}
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 2, 3, 4)}, initializers=inits), target)


@pytest.mark.parametrize("target", TARGETS)
def test_prelu_runtime_slope(target):
    m = onnx_model([helper.make_node("PRelu", ["x", "slope"], ["y"])], inputs={"x": (2, 3, 4), "slope": (3, 1)})
    compile_and_check(m, target, sanitize=True)


# -------------------------------------------------------------------------------- Max, Min, Sum


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["Max", "Min", "Sum"])
def test_variadic_broadcasting(op, target):
    node = helper.make_node(op, ["x", "row", "per_channel"], ["y"])
    m = onnx_model(
        [node],
        inputs={"x": (1, 3, 4, 5), "row": (4, 1)},
        initializers={"per_channel": RNG.normal(0, 1, (3, 1, 1)).astype(np.float32)},
    )
    compile_and_check(m, target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["Max", "Min", "Sum"])
def test_variadic_four_inputs_after_conv(op, target):
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node(op, ["c", "x2", "c", "k"], ["y"]),
    ]
    inits = {"w": weights(8, 2, 3, 3), "k": RNG.normal(0, 1, (8, 1, 1)).astype(np.float32)}
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 2, 4, 5), "x2": (1, 8, 4, 5)}, initializers=inits), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["Max", "Min", "Sum"])
def test_variadic_single_input_is_a_copy(op, target):
    compile_and_check(onnx_model([helper.make_node(op, ["x"], ["y"])], inputs={"x": (1, 3, 4)}), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op, bound", [("Max", 0.0), ("Min", 0.25)])
def test_max_min_with_scalar_fuse_into_conv_as_clip(op, bound, target):
    nodes = [helper.make_node("Conv", ["x", "w"], ["c"]), helper.make_node(op, ["k", "c"], ["y"])]
    inits = {"w": weights(4, 3, 3, 3), "k": np.float32(bound)}
    compiled = compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 5, 5)}, initializers=inits), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]


def test_variadic_under_sanitizers():
    m = onnx_model(
        [helper.make_node("Sum", ["x", "a", "b"], ["y"])], inputs={"x": (2, 3, 5), "a": (5,), "b": (2, 1, 1)}
    )
    for target in TARGETS:
        compile_and_check(m, target, sanitize=True)


# ------------------------------------------------------------------------------------- LogSoftmax


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("axis", [0, 1, 2, 3, -1])
def test_log_softmax(axis, target):
    node = helper.make_node("LogSoftmax", ["x"], ["y"], axis=axis)
    compile_and_check(onnx_model([node], inputs={"x": (2, 3, 4, 5)}), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("axis", [1, 2, None])
def test_log_softmax_opset_11_flattens_from_axis(axis, target):
    attrs = {} if axis is None else {"axis": axis}
    node = helper.make_node("LogSoftmax", ["x"], ["y"], **attrs)
    compile_and_check(onnx_model([node], inputs={"x": (2, 3, 4, 5)}, opset=11), target)


@pytest.mark.parametrize("target", TARGETS)
def test_log_softmax_is_stable_for_large_inputs(target):
    compile_and_check(scaled(helper.make_node("LogSoftmax", ["x"], ["y"], axis=1), scale=500.0), target)


def test_register_blocked_reduction_declares_its_accumulators_in_one_block():
    """26 accumulators of a register-blocked LogSoftmax share one block; nested one block each,
    their indentation made 73 KB of C for two layers (fuzz-found)."""
    node = helper.make_node("LogSoftmax", ["x"], ["y"], axis=1)
    compiled = nncg.compile(onnx_model([node], inputs={"x": (2, 7, 13, 13)}), "avx512", unroll=None)
    check_against_onnxruntime(onnx_model([node], inputs={"x": (2, 7, 13, 13)}), compiled)
    indents = [len(line) - len(line.lstrip()) for line in compiled.source.splitlines()]
    assert max(indents) <= 6 * 4 and len(compiled.source) < 25_000


def test_log_softmax_under_sanitizers():
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"]),
        helper.make_node("LogSoftmax", ["c"], ["y"], axis=1),
    ]
    m = onnx_model(nodes, inputs={"x": (1, 2, 3, 5)}, initializers={"w": weights(6, 2, 1, 1)})
    for target in TARGETS:
        compile_and_check(m, target, sanitize=True)


# -------------------------------------------------------------------------------------------- LRN

LRN_CASES = {
    "default_size3": dict(size=3),
    "size5_all_attributes": dict(size=5, alpha=0.5, beta=0.6, bias=2.0),
    "size1": dict(size=1, alpha=0.8, beta=1.0),
    "wider_than_channels": dict(size=9, alpha=0.2, bias=1.5),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", LRN_CASES)
def test_lrn(case, target):
    node = helper.make_node("LRN", ["x"], ["y"], **LRN_CASES[case])
    compile_and_check(onnx_model([node], inputs={"x": (1, 6, 3, 5)}), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("size", [2, 4])
def test_lrn_even_size_follows_the_onnx_formula(size, target):
    """onnxruntime refuses even sizes; the spec's window is c - floor((size-1)/2) .. c + ceil((size-1)/2)."""
    attrs = dict(size=size, alpha=0.3, beta=0.8, bias=1.2)
    m = onnx_model([helper.make_node("LRN", ["x"], ["y"], **attrs)], inputs={"x": (1, 6, 3, 5)})
    x = RNG.standard_normal((1, 6, 3, 5)).astype(np.float32)
    (y,) = run_compiled(nncg.compile(m, target=target, verify_ir=True), [x])
    first, last = (size - 1) // 2, size // 2
    squares = np.stack([(x[:, max(0, c - first) : c + last + 1] ** 2).sum(axis=1) for c in range(6)], axis=1)
    expected = x / (attrs["bias"] + attrs["alpha"] / size * squares) ** attrs["beta"]
    assert np.abs(y - expected).max() <= 1e-4 * np.abs(expected).max()


@pytest.mark.parametrize("target", TARGETS)
def test_lrn_after_conv(target):
    nodes = [helper.make_node("Conv", ["x", "w"], ["c"]), helper.make_node("LRN", ["c"], ["y"], size=3, alpha=0.4)]
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 4, 4)}, initializers={"w": weights(5, 3, 1, 1)}), target)


@pytest.mark.parametrize("target", TARGETS)
def test_lrn_3d_matches_4d(target):
    """onnxruntime runs LRN on 4-D inputs only: a 3-D LRN is checked against a 4-D one on the same
    data, its input unsqueezed and its output squeezed back."""
    attrs = dict(size=3, alpha=0.5, beta=0.7)
    nncg_model = onnx_model([helper.make_node("LRN", ["x"], ["y"], **attrs)], inputs={"x": (1, 5, 6)})
    reference = onnx_model(
        [
            helper.make_node("Unsqueeze", ["x", "axis"], ["x4"]),
            helper.make_node("LRN", ["x4"], ["y4"], **attrs),
            helper.make_node("Squeeze", ["y4", "axis"], ["y"]),
        ],
        inputs={"x": (1, 5, 6)},
    )
    reference.graph.initializer.append(helper.make_tensor("axis", TensorProto.INT64, [1], [3]))
    check_against_onnxruntime(reference, nncg.compile(nncg_model, target=target, verify_ir=True))


@pytest.mark.parametrize("unroll", [0, 2, None])
def test_lrn_at_every_unroll_level_under_sanitizers(unroll):
    node = helper.make_node("LRN", ["x"], ["y"], size=5, alpha=0.3)
    m = onnx_model([node], inputs={"x": (1, 7, 2, 5)})
    for target in TARGETS:
        compile_and_check(m, target, unroll=unroll, sanitize=True)


# ------------------------------------------------------------------------------------- ReduceMean

REDUCE_CASES = {
    "spatial_keepdims": (dict(axes=[2, 3]), (1, 6, 4, 5)),
    "spatial_no_keepdims": (dict(axes=[2, 3], keepdims=0), (1, 6, 4, 5)),
    "channels": (dict(axes=[1]), (2, 6, 4, 5)),
    "last_negative_no_keepdims": (dict(axes=[-1], keepdims=0), (2, 6, 4, 5)),
    "batch_and_height": (dict(axes=[0, 2]), (2, 3, 4, 5)),
    "all_default": (dict(), (2, 3, 4, 5)),
    "all_no_keepdims": (dict(keepdims=0), (2, 3, 4)),
    "rank3_spatial": (dict(axes=[2]), (1, 5, 7)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", REDUCE_CASES)
def test_reduce_mean(case, target):
    attrs, shape = REDUCE_CASES[case]
    compile_and_check(onnx_model([helper.make_node("ReduceMean", ["x"], ["y"], **attrs)], inputs={"x": shape}), target)


def test_reduce_mean_over_spatial_dims_is_a_global_average_pool():
    node = helper.make_node("ReduceMean", ["x"], ["y"], axes=[2, 3])
    graph = nncg.import_onnx(onnx_model([node], inputs={"x": (1, 6, 4, 5)}))
    assert [(n.op, n.attrs.kernel) for n in graph.nodes] == [("AveragePool", (4, 5))]


def opset18_reduce(axes, shape=(1, 4, 3, 5), **attrs):
    inputs = ["x"] + (["axes"] if axes is not None else [])
    m = onnx_model([helper.make_node("ReduceMean", inputs, ["y"], **attrs)], inputs={"x": shape}, opset=18)
    if axes is not None:
        m.graph.initializer.append(helper.make_tensor("axes", TensorProto.INT64, [len(axes)], axes))
    return m


OPSET18_CASES = {
    "spatial_input_axes": (dict(axes=[-2, -1]), None),
    "channel_input_axes_no_keepdims": (dict(axes=[1], keepdims=0), None),
    "no_axes_reduces_all": (dict(axes=None), None),
    "empty_axes_noop": (dict(axes=None, noop_with_empty_axes=1), "Identity"),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", OPSET18_CASES)
def test_reduce_mean_opset18(case, target):
    kwargs, op = OPSET18_CASES[case]
    m = opset18_reduce(**kwargs)
    compile_and_check(m, target)
    if op:
        assert [n.op for n in nncg.import_onnx(m).nodes] == [op]


@pytest.mark.parametrize("target", TARGETS)
def test_conv_then_spatial_mean_without_keepdims(target):
    """The spatial mean of a channels-last conv output, reduced with the channel loop vectorised."""
    nodes = [
        helper.make_node("Conv", ["x", "w"], ["c"], pads=[1, 1, 1, 1]),
        helper.make_node("ReduceMean", ["c"], ["y"], axes=[2, 3], keepdims=0),
    ]
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 5, 6)}, initializers={"w": weights(10, 3, 3, 3)}), target)


def test_reduce_mean_under_sanitizers():
    m = onnx_model([helper.make_node("ReduceMean", ["x"], ["y"], axes=[1, 3], keepdims=0)], inputs={"x": (2, 5, 3, 6)})
    for target in TARGETS:
        compile_and_check(m, target, unroll=0, sanitize=True)


# ------------------------------------------------------------------------------------------ errors


def test_reduce_mean_repeated_axes_are_refused():
    m = opset18_reduce(axes=[1, -2], shape=(1, 4, 3))
    with pytest.raises(NncgError, match=r"ReduceMean .*axes \[1, -2\]; they must be distinct"):
        nncg.import_onnx(m)


def test_lrn_without_channel_window_is_refused():
    m = onnx_model([helper.make_node("LRN", ["x"], ["y"], size=0)], inputs={"x": (1, 3, 4, 4)})
    with pytest.raises(NncgError, match=r"LRN .*size=0"):
        nncg.import_onnx(m)


def test_lrn_on_a_matrix_is_refused():
    m = onnx_model([helper.make_node("LRN", ["x"], ["y"], size=3)], inputs={"x": (2, 6)})
    with pytest.raises(NncgError, match=r"LRN .*rank-2 input"):
        nncg.import_onnx(m)


def test_prelu_slope_that_would_grow_x_is_refused():
    m = onnx_model(
        [helper.make_node("PRelu", ["x", "slope"], ["y"])],
        inputs={"x": (3, 1)},
        initializers={"slope": np.ones((3, 4), np.float32)},
    )
    with pytest.raises(NncgError, match=r"PRelu .*slope of shape \[3, 4\].*X \[3, 1\]"):
        nncg.import_onnx(m)


# -------------------------------------------------------------------------------- vector calls


def test_vectorize_turns_calls_into_vector_calls():
    loop = Loop("c", 8, (Store("y", Affine.of("c"), Call("tanh", Load("x", Affine.of("c")))),), parallel=True)
    out = vectorize(Program("p", (), (Kernel("k", "Tanh", (loop,)),)), Target("t", (4,)))
    assert out.kernels[0].body[0].body[0].value == Call("tanh", Load("x", Affine.of("c") * 4, 4))


def test_unknown_function_is_refused_where_the_call_is_made():
    with pytest.raises(ValueError, match="Call.fn is 'cbrt', not one of 'exp', 'log', 'tanh', 'sigmoid', 'erf', 'abs'"):
        Call("cbrt", Load("x", Affine()))


def test_ssse3_defines_a_lane_wise_helper_per_function_called_on_vectors():
    nodes = [helper.make_node("Tanh", ["x"], ["t"]), helper.make_node("LogSoftmax", ["t"], ["y"], axis=1)]
    compiled = compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 8)}), "ssse3")
    helpers = re.findall(r"^static NNCG_INLINE __m128 nncg_(\w+)_ps\(__m128 x\)$", compiled.source, re.M)
    assert helpers == ["exp", "log", "tanh"]
