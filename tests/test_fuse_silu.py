"""Gated activations: Mul(x, Sigmoid(x)) (SiLU, Swish) and Mul(x, HardSigmoid(x)) become one activation
in fuse-activation, which x's producer then applies at its store; HardSwish and Clip fuse the same way.
Graph-level Before/Expected, then small ONNX models against onnxruntime on every target."""

import numpy as np
import pytest
from helpers import compile_and_check, kernel_ops, onnx_model, weights
from onnx import helper

from nncg.backends import BACKENDS
from nncg.backends.simd_needs import interleaved_runs
from nncg.ir.graph import Activation, ConvAttrs, Graph, Node, Value
from nncg.ir.loops import Affine, Call, Load, Store
from nncg.passes.fuse_activation import fuse_activation

TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")
CONV = ConvAttrs((1, 1), (1, 1), (1, 1), (0, 0), (0, 0))
SHAPE = (1, 4, 3, 3)
SIGMOID = Activation("sigmoid")


def graph(nodes, outputs=("y",), values=("x", "c", "s", "y"), with_weights=True):
    shapes = dict.fromkeys(values, SHAPE)
    constants = {"w": np.ones((4, 4, 1, 1), np.float32)} if with_weights else {}
    outs = tuple(Value(name, SHAPE) for name in outputs)
    return Graph("g", (Value("x", SHAPE),), outs, tuple(nodes), constants, shapes)


def conv_silu(sigmoid_first=False):
    conv = Node("Conv", "conv", ("x", "w"), ("c",), CONV)
    sig = Node("Sigmoid", "sig", ("c",), ("s",), SIGMOID)
    mul = Node("Mul", "mul", ("s", "c") if sigmoid_first else ("c", "s"), ("y",))
    return [conv, sig, mul]


# ------------------------------------------------------------------------------------ graph level


@pytest.mark.parametrize("sigmoid_first", [False, True])
def test_conv_sigmoid_mul_becomes_conv_with_silu(sigmoid_first):
    before = graph(conv_silu(sigmoid_first))
    expected = graph(
        [Node("Conv", "conv", ("x", "w"), ("y",), ConvAttrs(**{**vars(CONV), "activation": Activation("silu")}))],
        values=("x", "y"),
    )
    assert fuse_activation(before) == expected


def test_silu_without_producer_is_one_standalone_node():
    before = graph([Node("Sigmoid", "sig", ("x",), ("s",), SIGMOID), Node("Mul", "mul", ("x", "s"), ("y",))])
    expected = graph([Node("Silu", "mul", ("x",), ("y",), Activation("silu"))], values=("x", "y"), with_weights=False)
    assert fuse_activation(before) == expected


def test_hard_sigmoid_mul_becomes_hard_swish_with_its_slope():
    gate = Activation("hard_sigmoid", alpha=0.2, beta=0.5)
    before = graph([Node("HardSigmoid", "hs", ("x",), ("s",), gate), Node("Mul", "mul", ("s", "x"), ("y",))])
    (node,) = fuse_activation(before).nodes
    assert (node.op, node.inputs, node.outputs) == ("HardSwish", ("x",), ("y",))
    assert node.attrs == Activation("hard_swish", alpha=0.2, beta=0.5)
    assert str(node.attrs) == "hard_swish(alpha=0.2, beta=0.5)"


def test_sigmoid_read_elsewhere_is_not_fused():
    """The sigmoid's output is also a graph output: it must be stored, so the Mul stays."""
    before = graph(conv_silu(), outputs=("y", "s"))
    assert [n.op for n in fuse_activation(before).nodes] == ["Conv", "Sigmoid", "Mul"]


def test_mul_of_another_tensors_sigmoid_is_not_silu():
    nodes = [
        Node("Conv", "conv", ("x", "w"), ("c",), CONV),
        Node("Sigmoid", "sig", ("x",), ("s",), SIGMOID),
        Node("Mul", "mul", ("c", "s"), ("y",)),
    ]
    before = graph(nodes)
    assert [n.op for n in fuse_activation(before).nodes] == ["Conv", "Sigmoid", "Mul"]


def test_producer_read_by_another_node_keeps_a_standalone_silu():
    """c is also a graph output: the conv stores it plain, the Silu is its own pass."""
    out = fuse_activation(graph(conv_silu(), outputs=("y", "c")))
    assert [n.op for n in out.nodes] == ["Conv", "Silu"]
    assert out.nodes[0].attrs.activation is None


# ------------------------------------------------------------------------------ against onnxruntime


def conv_model(act_nodes, opset=14, channels=6, size=5, inputs=(), inits=None):
    """Conv (3x3, 6 channels: a vector block and a scalar tail) -> the given nodes reading c, writing y."""
    nodes = [helper.make_node("Conv", ["x", "w", "b"], ["c"], pads=[1, 1, 1, 1]), *act_nodes]
    initializers = {"w": 3 * weights(channels, 3, 3, 3), "b": weights(channels), **(inits or {})}
    return onnx_model(nodes, inputs={"x": (1, 3, size, size)}, initializers=initializers, opset=opset)


def silu_nodes(x="c", sigmoid_first=False):
    mul_inputs = ["s", x] if sigmoid_first else [x, "s"]
    return [helper.make_node("Sigmoid", [x], ["s"]), helper.make_node("Mul", mul_inputs, ["y"])]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("sigmoid_first", [False, True])
def test_conv_silu_is_fused(target, sigmoid_first):
    compiled = compile_and_check(conv_model(silu_nodes(sigmoid_first=sigmoid_first)), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]  # the copy converts channels-last to NCHW


@pytest.mark.parametrize("target", TARGETS)
def test_conv_batchnorm_silu_is_one_conv(target):
    """The efficientnet block: Conv -> BatchNormalization -> SiLU."""
    c = 6
    bn = helper.make_node("BatchNormalization", ["c", "g", "beta", "mu", "var"], ["n"])
    inits = {
        "g": np.linspace(0.5, 2, c, dtype=np.float32),
        "beta": np.linspace(-1, 1, c, dtype=np.float32),
        "mu": np.linspace(-0.2, 0.2, c, dtype=np.float32),
        "var": np.linspace(0.5, 1.5, c, dtype=np.float32),
    }
    compiled = compile_and_check(conv_model([bn, *silu_nodes("n")], inits=inits), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]


@pytest.mark.parametrize("target", TARGETS)
def test_gemm_silu_is_fused(target):
    nodes = [helper.make_node("Gemm", ["x", "w", "b"], ["g"]), *silu_nodes("g")]
    model = onnx_model(nodes, inputs={"x": (2, 10)}, initializers={"w": 3 * weights(10, 9), "b": weights(9)})
    assert kernel_ops(compile_and_check(model, target)) == ["Dense"]


@pytest.mark.parametrize("target", TARGETS)
def test_standalone_silu_is_one_kernel(target):
    """No producer (x is the graph input): one Silu pass, saturating far out on both sides."""
    nodes = [helper.make_node("Mul", ["x", "k"], ["xs"]), *silu_nodes("xs")]
    model = onnx_model(nodes, inputs={"x": (1, 3, 4, 7)}, initializers={"k": np.float32(40.0)})
    assert kernel_ops(compile_and_check(model, target)) == ["Mul", "Silu"]


@pytest.mark.parametrize("target", TARGETS)
def test_conv_hard_sigmoid_mul_is_fused_hard_swish(target):
    nodes = [helper.make_node("HardSigmoid", ["c"], ["s"], alpha=0.2), helper.make_node("Mul", ["s", "c"], ["y"])]
    compiled = compile_and_check(conv_model(nodes), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("op", ["HardSwish", "Clip"])
def test_conv_hard_swish_and_clip_are_fused(target, op):
    extra = ["lo", "hi"] if op == "Clip" else []
    inits = {"lo": np.float32(0.0), "hi": np.float32(6.0)} if op == "Clip" else {}
    compiled = compile_and_check(conv_model([helper.make_node(op, ["c", *extra], ["y"])], inits=inits), target)
    assert kernel_ops(compiled) == ["Conv", "Copy"]


@pytest.mark.parametrize("target", TARGETS)
def test_silu_whose_input_is_also_an_output(target):
    """c is a graph output too: the Conv stores it, a standalone Silu reads it back."""
    model = conv_model(silu_nodes())
    model.graph.output.append(helper.make_tensor_value_info("c", 1, None))
    assert kernel_ops(compile_and_check(model, target))[-1] != "Mul"


@pytest.mark.parametrize("target", ["ssse3", "avx2"])
def test_register_block_epilogue_calls_one_interleaved_sigmoid(target):
    """A SiLU conv's register block stores its vectors after one call of the sigmoid over all of them
    (backends/simd.py: math_interleave), with onnxruntime's results."""
    model = conv_model(silu_nodes(), channels=48, size=8)
    compiled = compile_and_check(model, target)
    count = BACKENDS[target].math_interleave
    assert f"sigmoid_ps_x{count}(nncg_lanes);" in compiled.source


def test_a_run_that_reads_what_it_writes_is_not_interleaved():
    """An interleaved run computes its calls before its stores: a call reading a buffer the run
    writes (an in-place activation) keeps each store with its own call."""
    widths = BACKENDS["ssse3"].widths

    def store(buffer, read, at):
        index = Affine.of(at)
        return Store(buffer, index, Call("sigmoid", Load(read, index, 4)))

    apart = tuple(store("y", "x", 4 * i) for i in range(3))
    in_place = tuple(store("x", "x", 4 * i) for i in range(3))
    assert [len(run) for run, _ in interleaved_runs(apart, widths, 8)] == [3]
    assert [len(run) for run, _ in interleaved_runs(apart, widths, 2)] == [2, 1]
    assert [len(run) for run, _ in interleaved_runs(in_place, widths, 8)] == [1, 1, 1]
    assert [len(run) for run, _ in interleaved_runs(apart, widths, 1)] == [1, 1, 1]
