"""Graph passes and the pass manager, checked on the IR directly."""

import io
from dataclasses import replace

import numpy as np
import pytest
from helpers import target

import nncg
from nncg.errors import NncgError
from nncg.ir.graph import Activation, BatchNormAttrs, ConvAttrs, DenseAttrs, Graph, Node, Value
from nncg.ir.loops import Program
from nncg.ir.verify import verify_ir
from nncg.lowering.conv import conv_extras
from nncg.passes import PassManager, default_pipeline, parse_pipeline
from nncg.passes.drop_identity import drop_identity
from nncg.passes.fold_batchnorm import fold_batchnorm
from nncg.passes.fuse_activation import fuse_activation
from nncg.passes.fuse_bias import fuse_bias
from nncg.passes.fuse_residual import fuse_residual

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
    text = "fold-batchnorm,lower,vectorize,unroll{level=1},inline-constants,plan-memory"
    assert PassManager(text, target(4)).pipeline == text
    assert parse_pipeline(" unroll{ level=none } ")[0].params == (("level", "none"),)
    ssse3 = nncg.get_target("ssse3")
    assert PassManager(default_pipeline(ssse3, "2"), ssse3).pipeline == default_pipeline(ssse3, "2")


@pytest.mark.parametrize(
    "text, message",
    [
        ("fold-batchnorm,frobnicate", "unknown pass 'frobnicate'"),
        ("unroll{depth=1}", "has no parameter 'depth'"),
        ("unroll{level=-1}", "bad value '-1'"),
        ("vectorize{lanes=4}", "pass vectorize has no parameter 'lanes'"),
        ("lower,plan-memory,unroll", "pass plan-memory must run last, but unroll follows it"),
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
        "// ----- IR after plan-memory",
    ]
    assert "= Conv(x[1, 2, 5, 5]" in text and "kernel conv (Conv)" in text


# ------------------------------------------------------------------------------ fuse-residual


def residual_block(add_inputs=("c", "a"), outputs=("y",), extra=(), constants=None, shapes=None, inputs=None):
    """a = conv_a(x); c = conv_b(a); y = Add(*add_inputs): a ResNet shortcut around conv_b.
    `extra` nodes run before the Add."""
    constants = {"wa": rand(4, 2, 3, 3), "wb": rand(4, 4, 3, 3)} | (constants or {})
    shapes = {"x": (1, 2, 5, 5), "a": (1, 4, 5, 5), "c": (1, 4, 5, 5), "y": (1, 4, 5, 5)} | (shapes or {})
    nodes = (
        Node("Conv", "conv_a", ("x", "wa"), ("a",), CONV),
        Node("Conv", "conv_b", ("a", "wb"), ("c",), CONV),
        *extra,
        Node("Add", "add", add_inputs, ("y",)),
    )
    graph_inputs = inputs or (Value("x", shapes["x"]),)
    return Graph("g", graph_inputs, tuple(Value(n, shapes[n]) for n in outputs), nodes, constants, shapes)


@pytest.mark.parametrize("add_inputs", [("c", "a"), ("a", "c")])
def test_fuse_residual_makes_the_conv_add_the_shortcut_then_activate(add_inputs):
    g = residual_block(add_inputs)
    relu = Node("Relu", "relu", ("y",), ("z",), Activation("relu"))
    g = Graph("g", g.inputs, (Value("z", (1, 4, 5, 5)),), (*g.nodes, relu), g.constants, g.shapes | {"z": (1, 4, 5, 5)})
    out = fuse_activation(fuse_residual(g))
    # a feeds conv_b too, so only conv_b can take the Add, whichever side its output is on
    assert [(n.name, n.inputs, n.outputs) for n in out.nodes] == [
        ("conv_a", ("x", "wa"), ("a",)),
        ("conv_b", ("a", "wb", "a"), ("z",)),
    ]
    assert out.nodes[1].attrs == replace(CONV, residual=True, activation=Activation("relu"))
    assert conv_extras(out.nodes[1]) == (None, "a")


def test_fuse_residual_moves_the_conv_to_the_add_when_the_shortcut_comes_later():
    """Add(conv_a(x), conv_b(x)): fusing into conv_a makes it read conv_b's output, so the fused
    node takes the Add's place."""
    conv_b = Node("Conv", "conv_b", ("x", "wb"), ("c",), CONV)
    g = residual_block(("a", "c"), constants={"wb": rand(4, 2, 3, 3)})
    g = Graph("g", g.inputs, g.outputs, (g.nodes[0], conv_b, g.nodes[2]), g.constants, g.shapes)
    out = fuse_residual(g)
    assert [(n.name, n.inputs) for n in out.nodes] == [("conv_b", ("x", "wb")), ("conv_a", ("x", "wa", "c"))]
    assert verify_ir(out) == []


def _pooled_branch():
    """r [1, 4, 1, 1]: a per-channel runtime tensor (a valid 5x5 conv of a)."""
    pool = Node("Conv", "squeeze", ("a", "wr"), ("r",), ConvAttrs((5, 5), (1, 1), (1, 1), (0, 0), (0, 0)))
    return dict(extra=(pool,), constants={"wr": rand(4, 4, 5, 5)}, shapes={"r": (1, 4, 1, 1)})


@pytest.mark.parametrize(
    "why, graph_of",
    [
        ("the conv output is also a graph output", lambda: residual_block(outputs=("y", "c"))),
        ("the Add broadcasts", lambda: residual_block(("c", "r"), **_pooled_branch())),
        ("the shortcut is the graph input", lambda: residual_block(("c", "x"), shapes={"x": (1, 4, 5, 5)})),
        ("the conv output is added to itself", lambda: residual_block(("c", "c"))),
    ],
)
def test_fuse_residual_refuses(why, graph_of):
    g = graph_of()
    assert fuse_residual(g) == g, why


def test_fuse_residual_leaves_a_conv_with_an_activation_alone():
    g = residual_block()
    nodes = (g.nodes[0], replace(g.nodes[1], attrs=replace(CONV, activation=Activation("relu"))), g.nodes[2])
    g = Graph("g", g.inputs, g.outputs, nodes, g.constants, g.shapes)
    assert fuse_residual(g) == g


@pytest.mark.parametrize("follower", ["Add", "BatchNormalization"])
def test_fuse_bias_and_fold_batchnorm_leave_a_conv_with_a_residual_alone(follower):
    """A constant per-channel Add or a BatchNorm after the fused conv: the BN would have to scale the
    residual too, so it stays a ScaleShift; the bias stays an Add."""
    fused = fuse_residual(residual_block())
    if follower == "Add":
        node, constants = Node("Add", "bias", ("y", "k"), ("z",)), {"k": rand(1, 4, 1, 1)}
    else:
        node = Node("BatchNormalization", "bn", ("y", "g", "beta", "m", "v"), ("z",), BatchNormAttrs(1e-3))
        constants = {name: np.abs(rand(4)) + 0.5 for name in ("g", "beta", "m", "v")}
    shapes = fused.shapes | {"z": (1, 4, 5, 5)}
    g = Graph("g", fused.inputs, (Value("z", shapes["z"]),), (*fused.nodes, node), fused.constants | constants, shapes)
    out = fold_batchnorm(fuse_bias(g))
    assert out.nodes[1] == fused.nodes[1] and out.nodes[2].op == ("Add" if follower == "Add" else "ScaleShift")


# ------------------------------------------------------------------------------ runtime weights


def _as_runtime(g: Graph, name: str) -> Graph:
    """g with the constant `name` turned into a graph input."""
    constants = {k: v for k, v in g.constants.items() if k != name}
    shape = g.constants[name].shape
    return Graph("g", (*g.inputs, Value(name, shape)), g.outputs, g.nodes, constants, g.shapes | {name: shape})


def test_fold_batchnorm_keeps_runtime_weights_and_runtime_statistics():
    g = conv_bn()
    out = fold_batchnorm(_as_runtime(g, "w"))
    assert [n.op for n in out.nodes] == ["Conv", "ScaleShift"] and out.nodes[0] == g.nodes[0]
    runtime_stats = _as_runtime(g, "v")
    assert fold_batchnorm(runtime_stats) == runtime_stats


def test_fuse_bias_keeps_a_runtime_bias():
    g = conv_bn()
    add = Node("Add", "add", ("c", "k"), ("y",))
    g = Graph("g", g.inputs, g.outputs, (g.nodes[0], add), g.constants | {"k": rand(4, 1, 1)}, g.shapes)
    g = _as_runtime(g, "b")
    assert fuse_bias(g) == g


def test_default_pipeline_fuses_residuals_between_bias_and_activation():
    names = [spec.name for spec in parse_pipeline(default_pipeline(nncg.get_target("ssse3"), "2"))]
    assert names.index("fuse-bias") < names.index("fuse-residual") < names.index("fuse-activation")


def test_manager_hands_passes_the_target_and_finishes_pipelines():
    with pytest.raises(NncgError, match="passes vectorize need a target"):
        PassManager("lower,vectorize")
    manager = PassManager("fold-batchnorm,lower,unroll{level=0}")
    assert manager.pipeline == "fold-batchnorm,lower,unroll{level=0},plan-memory"
    assert manager.run(conv_bn()).arena is not None
    assert PassManager("fold-batchnorm,lower", finish=False).pipeline == "fold-batchnorm,lower"
    assert PassManager("fold-batchnorm").pipeline == "fold-batchnorm"  # no lowering: nothing to finish


def test_errors_inside_a_pass_name_it():
    with pytest.raises(NncgError, match="^pass register-block: .*no layer named conv9"):
        PassManager("lower,register-block{layers=conv9:2x2}", target(4)).run(conv_bn())
