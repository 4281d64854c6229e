"""Graph passes and the pass manager, checked on the IR directly."""

import io

import numpy as np
import pytest

from nncg.errors import NncgError
from nncg.ir.graph import Activation, BatchNormAttrs, ConvAttrs, DenseAttrs, Graph, Node, Value
from nncg.ir.loops import Program
from nncg.passes import PassManager, default_pipeline, parse_pipeline
from nncg.passes.drop_identity import drop_identity
from nncg.passes.fold_batchnorm import fold_batchnorm
from nncg.passes.fuse_activation import fuse_activation
from nncg.passes.fuse_bias import fuse_bias

RNG = np.random.default_rng(7)
CONV = ConvAttrs((3, 3), (1, 1), (1, 1), (1, 1), (1, 1))


def rand(*shape):
    return RNG.standard_normal(shape).astype(np.float32)


def graph(nodes, constants, shapes, out="y"):
    return Graph("g", (Value("x", shapes["x"]),), (Value(out, shapes[out]),), tuple(nodes), constants, shapes)


def conv_bn(bn_consumers=1):
    constants = {"w": rand(4, 2, 3, 3), "b": rand(4), "g": rand(4), "beta": rand(4), "m": rand(4)}
    constants["v"] = np.abs(rand(4)) + 0.5
    nodes = [
        Node("Conv", "conv", ("x", "w", "b"), ("c",), CONV),
        Node("BatchNormalization", "bn", ("c", "g", "beta", "m", "v"), ("y",), BatchNormAttrs(1e-3)),
    ]
    return graph(nodes, constants, {"x": (1, 2, 5, 5), "c": (1, 4, 5, 5), "y": (1, 4, 5, 5)})


def test_fold_batchnorm_into_conv_matches_the_formula():
    g = conv_bn()
    out = fold_batchnorm(g)
    assert [n.op for n in out.nodes] == ["Conv"] and out.nodes[0].outputs == ("y",)
    c = g.constants
    scale = c["g"] / np.sqrt(c["v"] + 1e-3)
    w, b = (out.constants[name] for name in out.nodes[0].inputs[1:])
    np.testing.assert_allclose(w, c["w"] * scale[:, None, None, None], rtol=1e-6)
    np.testing.assert_allclose(b, (c["b"] - c["m"]) * scale + c["beta"], rtol=1e-5, atol=1e-6)
    assert set(out.constants) == set(out.nodes[0].inputs[1:])  # the unfolded arrays are gone


def test_batchnorm_without_foldable_producer_becomes_scale_shift():
    g = conv_bn()
    bn = g.nodes[1]
    standalone = graph(
        [Node(bn.op, bn.name, ("x", *bn.inputs[1:]), ("y",), bn.attrs)],
        g.constants,
        {"x": (1, 4, 5, 5), "y": (1, 4, 5, 5)},
    )
    out = fold_batchnorm(standalone)
    (node,) = out.nodes
    assert node.op == "ScaleShift"
    scale, shift = (out.constants[n] for n in node.inputs[1:])
    np.testing.assert_allclose(scale, g.constants["g"] / np.sqrt(g.constants["v"] + 1e-3), rtol=1e-6)


def test_fuse_activation_only_where_the_producer_output_is_private():
    constants = {"w": rand(4, 2, 3, 3)}
    shapes = {"x": (1, 2, 5, 5), "c": (1, 4, 5, 5), "y": (1, 4, 5, 5)}
    nodes = [
        Node("Conv", "conv", ("x", "w"), ("c",), CONV),
        Node("LeakyRelu", "act", ("c",), ("y",), Activation("leaky_relu", 0.1)),
    ]
    out = fuse_activation(graph(nodes, constants, shapes))
    assert [n.op for n in out.nodes] == ["Conv"] and out.nodes[0].attrs.activation == Activation("leaky_relu", 0.1)
    # c is also a graph output: the conv must store it before the activation, so no fusion
    g2 = Graph(
        "g",
        (Value("x", shapes["x"]),),
        (Value("c", shapes["c"]), Value("y", shapes["y"])),
        tuple(nodes),
        constants,
        shapes,
    )
    assert fuse_activation(g2) == g2


def test_drop_identity_rewires_readers_and_keeps_output_names():
    constants = {"w": rand(3, 4)}
    shapes = {"x": (1, 4), "d": (1, 3), "y": (1, 3)}
    nodes = [Node("Dense", "fc", ("x", "w"), ("d",), DenseAttrs()), Node("Identity", "drop", ("d",), ("y",))]
    out = drop_identity(graph(nodes, constants, shapes))
    assert [(n.op, n.outputs) for n in out.nodes] == [("Dense", ("y",))]


def test_fuse_bias_turns_matmul_add_into_dense_with_bias():
    constants = {"w": rand(4, 3), "bias": rand(3)}
    shapes = {"x": (2, 4), "d": (2, 3), "y": (2, 3)}
    nodes = [Node("Dense", "fc", ("x", "w"), ("d",), DenseAttrs()), Node("Add", "add", ("bias", "d"), ("y",))]
    out = fuse_bias(graph(nodes, constants, shapes))
    (node,) = out.nodes
    assert node.op == "Dense" and node.outputs == ("y",)
    np.testing.assert_array_equal(out.constants[node.inputs[2]], constants["bias"])


def test_fuse_bias_refuses_an_add_that_varies_per_row():
    constants = {"w": rand(4, 3), "bias": rand(2, 3)}
    shapes = {"x": (2, 4), "d": (2, 3), "y": (2, 3)}
    g = graph(
        [Node("Dense", "fc", ("x", "w"), ("d",), DenseAttrs()), Node("Add", "add", ("d", "bias"), ("y",))],
        constants,
        shapes,
    )
    assert fuse_bias(g) == g


# ------------------------------------------------------------------------------------ pass manager


def test_pipeline_text_round_trips():
    text = "fold-batchnorm,lower,vectorize{lanes=4},unroll{level=1},inline-constants"
    assert PassManager(text).pipeline == text
    assert parse_pipeline(" unroll{ level=none } ")[0].params == (("level", "none"),)
    assert PassManager(default_pipeline(4, "2")).pipeline == default_pipeline(4, "2")


@pytest.mark.parametrize(
    "text, message",
    [
        ("fold-batchnorm,frobnicate", "unknown pass 'frobnicate'"),
        ("unroll{depth=1}", "has no parameter 'depth'"),
        ("unroll{level=-1}", "bad value '-1'"),
        ("vectorize{lanes=3}", "bad value '3'"),
        ("lower,,unroll", "cannot parse pipeline"),
    ],
)
def test_bad_pipelines_are_clear_errors(text, message):
    with pytest.raises(NncgError, match=message):
        PassManager(text)


def test_manager_checks_stages_and_prints_ir_after_every_pass():
    with pytest.raises(NncgError, match="works on the loop-nest IR but gets the graph IR; put it after lower"):
        PassManager("unroll{level=1}").run(conv_bn())
    stream = io.StringIO()
    result = PassManager("fold-batchnorm,lower,unroll{level=0}", verify=True, print_ir_after_all=stream).run(conv_bn())
    assert isinstance(result, Program)
    text = stream.getvalue()
    assert [line for line in text.splitlines() if line.startswith("// ----- IR after")] == [
        "// ----- IR after fold-batchnorm",
        "// ----- IR after lower",
        "// ----- IR after unroll{level=0}",
    ]
    assert "= Conv(x[1, 2, 5, 5]" in text and "kernel conv (Conv)" in text
