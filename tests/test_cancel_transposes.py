"""Graph pass cancel-transposes: tf2onnx's NHWC <-> NCHW Transposes pushed through the ops between convs
until inverse pairs cancel. Graph-level Before/Expected pairs, then models against onnxruntime."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import check_against_onnxruntime, compile_and_check, kernel_ops, onnx_model, weights
from onnx import helper
from test_x86_targets import TARGETS as X86_TARGETS

import nncg
from benchmarks.nhwc_model import keras_mobilenet_nhwc
from nncg.ir.graph import (
    Activation,
    ConcatAttrs,
    ConvAttrs,
    Graph,
    Node,
    PadAttrs,
    ReduceAttrs,
    ReshapeAttrs,
    SliceAttrs,
    TransposeAttrs,
    Value,
)
from nncg.ir.verify import verify_ir
from nncg.passes import PassManager, default_pipeline
from nncg.passes.cancel_transposes import cancel_transposes

RNG = np.random.default_rng(11)
CONV = ConvAttrs((1, 1), (1, 1), (1, 1), (0, 0), (0, 0))
TO_NCHW, TO_NHWC = TransposeAttrs((0, 3, 1, 2)), TransposeAttrs((0, 2, 3, 1))
NCHW, NHWC = (1, 4, 3, 5), (1, 3, 5, 4)  # the same tensor in both layouts
TARGETS = ["ansi-c", "ssse3", *X86_TARGETS]


def rand(*shape):
    return RNG.standard_normal(shape).astype(np.float32)


def graph(nodes, constants, shapes, inputs=("x",), outputs=("y",)):
    return Graph(
        "g",
        tuple(Value(n, shapes[n]) for n in inputs),
        tuple(Value(n, shapes[n]) for n in outputs),
        tuple(nodes),
        constants,
        shapes,
    )


def conv(x, y, name="conv"):
    return Node("Conv", name, (x, "w"), (y,), CONV)


def transpose(x, y, attrs, name=None):
    return Node("Transpose", name or f"t_{y}", (x,), (y,), attrs)


def relu(x, y, name="relu"):
    return Node("Relu", name, (x,), (y,), Activation("relu"))


def check(before: Graph, expected: Graph):
    after = cancel_transposes(before)
    assert verify_ir(after) == []
    assert after == expected, "\n".join(f"{n.op} {n.name} {n.inputs} -> {n.outputs} {n.attrs}" for n in after.nodes)


# ------------------------------------------------------------------------------------------ graph level


def test_inverse_pair_cancels():
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NCHW, "a": NCHW, "h": NHWC, "b": NCHW, "y": NCHW}
    before = graph(
        [conv("x", "a", "c1"), transpose("a", "h", TO_NHWC), transpose("h", "b", TO_NCHW), conv("b", "y", "c2")],
        w,
        shapes,
    )
    expected = graph([conv("x", "a", "c1"), conv("a", "y", "c2")], w, {k: shapes[k] for k in ("x", "a", "y")})
    check(before, expected)


def test_transpose_moves_past_activations_and_per_channel_constants():
    """Conv -> NHWC -> Mul(scale[C]) -> Add(shift[C]) -> Clip -> NCHW -> Conv: the folded BatchNorm and
    the ReLU6 run in NCHW, the constants reshaped to [1, C, 1, 1]."""
    scale, shift = rand(4), rand(4)
    consts = {"w": rand(4, 4, 1, 1), "scale": scale, "shift": shift}
    clip = Activation("clip", low=0.0, high=6.0)
    shapes = {"x": NCHW, "a": NCHW, "h": NHWC, "m": NHWC, "s": NHWC, "r": NHWC, "b": NCHW, "y": NCHW}
    before = graph(
        [
            conv("x", "a", "c1"),
            transpose("a", "h", TO_NHWC),
            Node("Mul", "mul", ("h", "scale"), ("m",)),
            Node("Add", "add", ("shift", "m"), ("s",)),
            Node("Clip", "clip", ("s",), ("r",), clip),
            transpose("r", "b", TO_NCHW),
            conv("b", "y", "c2"),
        ],
        consts,
        shapes,
    )
    expected_consts = {"w": consts["w"], "scale_t0312": scale.reshape(1, 4, 1, 1)}
    expected_consts["shift_t0312"] = shift.reshape(1, 4, 1, 1)
    expected = graph(
        [
            conv("x", "a", "c1"),
            Node("Mul", "mul", ("a", "scale_t0312"), ("m_t0312",)),
            Node("Add", "add", ("shift_t0312", "m_t0312"), ("s_t0312",)),
            Node("Clip", "clip", ("s_t0312",), ("r_t0312",), clip),
            conv("r_t0312", "y", "c2"),
        ],
        expected_consts,
        {"x": NCHW, "a": NCHW, "m_t0312": NCHW, "s_t0312": NCHW, "r_t0312": NCHW, "y": NCHW},
    )
    check(before, expected)


def test_residual_add_of_two_transposed_tensors():
    """x -> T -> Conv -> T = h (read by the next conv's T and the Add); Add(h, T(conv(h))): both Adds'
    operands carry the same permutation, so the Add runs in NCHW and the Transposes cancel. The Relu
    writing the graph output keeps its Transpose in front (behind it, the Transpose would be a copy)."""
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NHWC, "i": NCHW, "a": NCHW, "h": NHWC, "j": NCHW, "b": NCHW, "k": NHWC, "s": NHWC, "y": NHWC}
    before = graph(
        [
            transpose("x", "i", TO_NCHW),
            conv("i", "a", "c1"),
            transpose("a", "h", TO_NHWC),
            transpose("h", "j", TO_NCHW),
            conv("j", "b", "c2"),
            transpose("b", "k", TO_NHWC),
            Node("Add", "add", ("h", "k"), ("s",)),
            relu("s", "y"),
        ],
        w,
        shapes,
    )
    expected = graph(
        [
            transpose("x", "i", TO_NCHW),  # the graph input's layout stays
            conv("i", "a", "c1"),
            conv("a", "b", "c2"),
            Node("Add", "add", ("a", "b"), ("s_t0312",)),
            transpose("s_t0312", "s", TO_NHWC, "add_transpose"),  # so does the graph output's
            relu("s", "y"),
        ],
        w,
        {"x": NHWC, "i": NCHW, "a": NCHW, "b": NCHW, "s": NHWC, "y": NHWC, "s_t0312": NCHW},
    )
    check(before, expected)


def test_concat_and_pad_attributes_follow_the_permutation():
    w = {"w": rand(4, 4, 1, 1)}
    cat_nhwc, cat_nchw = (1, 3, 5, 8), (1, 8, 3, 5)
    pad_nhwc, pad_nchw = (1, 4, 7, 8), (1, 8, 4, 7)
    shapes = {"x": NCHW, "a": NCHW, "b": NCHW, "ha": NHWC, "hb": NHWC, "c": cat_nhwc, "p": pad_nhwc, "y": pad_nchw}
    pads = PadAttrs((0, 1, 0, 0), (0, 0, 2, 0))  # NHWC: H by (1, 0), W by (0, 2)
    before = graph(
        [
            conv("x", "a", "c1"),
            conv("x", "b", "c2"),
            transpose("a", "ha", TO_NHWC),
            transpose("b", "hb", TO_NHWC),
            Node("Concat", "cat", ("ha", "hb"), ("c",), ConcatAttrs(3)),
            Node("Pad", "pad", ("c",), ("p",), pads),
            transpose("p", "y", TO_NCHW),
        ],
        w,
        shapes,
    )
    expected = graph(
        [
            conv("x", "a", "c1"),
            conv("x", "b", "c2"),
            Node("Concat", "cat", ("a", "b"), ("c_t0312",), ConcatAttrs(1)),
            # the Transposes around the graph output cancel: the Pad writes it
            Node("Pad", "pad", ("c_t0312",), ("y",), PadAttrs((0, 0, 1, 0), (0, 0, 0, 2))),
        ],
        w,
        {"x": NCHW, "a": NCHW, "b": NCHW, "c_t0312": cat_nchw, "y": pad_nchw},
    )
    check(before, expected)


@pytest.mark.parametrize("op", ["ReduceMean", "ReduceMax", "ReduceL2"])
def test_global_pool_over_nhwc_needs_no_transpose(op):
    """A reduction over H and W of NHWC without keepdims: over dims 2, 3 of NCHW, and [N, C] is left."""
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NCHW, "a": NCHW, "h": NHWC, "y": (1, 4)}
    before = graph(
        [
            conv("x", "a"),
            transpose("a", "h", TO_NHWC),
            Node(op, "gap", ("h",), ("y",), ReduceAttrs((1, 2), False)),
        ],
        w,
        shapes,
    )
    expected = graph(
        [conv("x", "a"), Node(op, "gap", ("a",), ("y",), ReduceAttrs((2, 3), False))],
        w,
        {"x": NCHW, "a": NCHW, "y": (1, 4)},
    )
    check(before, expected)


def test_slice_attributes_follow_the_permutation():
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NCHW, "a": NCHW, "h": NHWC, "s": (1, 2, 5, 2), "y": (1, 2, 5, 2)}
    before = graph(
        [
            conv("x", "a"),
            transpose("a", "h", TO_NHWC),
            Node("Slice", "s", ("h",), ("s",), SliceAttrs((0, 1, 0, 3), (1, 1, 1, -2))),
            relu("s", "y"),
        ],
        w,
        shapes,
    )
    expected = graph(
        [
            conv("x", "a"),
            Node("Slice", "s", ("a",), ("s_t0312",), SliceAttrs((0, 3, 1, 0), (1, -2, 1, 1))),
            transpose("s_t0312", "s", TO_NHWC, "s_transpose"),
            relu("s", "y"),
        ],
        w,
        {"x": NCHW, "a": NCHW, "s_t0312": (1, 2, 2, 5), "s": (1, 2, 5, 2), "y": (1, 2, 5, 2)},
    )
    check(before, expected)


def test_transpose_shared_with_a_reader_that_cannot_take_it_is_not_pushed():
    """h is also read by a Reshape (row-major NHWC order): pushing into the Relu would add a Transpose."""
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NCHW, "a": NCHW, "h": NHWC, "y": NHWC, "z": (1, 60)}
    before = graph(
        [
            conv("x", "a"),
            transpose("a", "h", TO_NHWC),
            relu("h", "y"),
            Node("Reshape", "flat", ("h",), ("z",), ReshapeAttrs((1, 60))),
        ],
        w,
        shapes,
        outputs=("y", "z"),
    )
    assert cancel_transposes(before) == before


def test_input_and_output_transposes_stay():
    """Graph input NHWC -> Conv -> graph output NHWC: nothing to cancel, the C API keeps its layout."""
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NHWC, "i": NCHW, "a": NCHW, "y": NHWC}
    before = graph([transpose("x", "i", TO_NCHW), conv("i", "a"), transpose("a", "y", TO_NHWC)], w, shapes)
    assert cancel_transposes(before) == before


def test_runtime_operand_without_the_permutation_blocks_the_push():
    """Add(T(a), x): x is NHWC at runtime, so the Add stays in NHWC."""
    w = {"w": rand(4, 4, 1, 1)}
    shapes = {"x": NHWC, "i": NCHW, "a": NCHW, "h": NHWC, "y": NHWC}
    before = graph(
        [
            transpose("x", "i", TO_NCHW),
            conv("i", "a"),
            transpose("a", "h", TO_NHWC),
            Node("Add", "add", ("h", "x"), ("y",)),
        ],
        w,
        shapes,
    )
    assert cancel_transposes(before) == before


def test_pass_is_in_the_default_pipeline_before_the_fusions():
    pipeline = default_pipeline(nncg.get_target("ssse3"))
    names = [p.split("{")[0] for p in pipeline.split(",")]
    assert names.index("drop-identity") < names.index("cancel-transposes") < names.index("fuse-activation")
    assert PassManager("cancel-transposes").pipeline == "cancel-transposes"


# ------------------------------------------------------------------------------------- against onnxruntime


def tf2onnx_model():
    """A tf2onnx-style NHWC model: a BatchNorm as Mul/Add on the last axis, ReLU6, a Pad, a Slice, a
    residual Add, a Concat on axis 3, a Sigmoid, and a Flatten before a Dense (whose Transpose stays: the
    Dense weights are in NHWC order) next to an NHWC graph output."""
    h, w, c = 6, 5, 4
    init = {"w1": weights(8, c, 3, 3), "b1": weights(8), "w2": weights(8, 8, 1, 1), "w3": weights(6, 8, 1, 1)}
    init |= {"scale": weights(8) + 1.0, "shift": weights(8), "lo": np.float32(0), "hi": np.float32(6)}
    init |= {"pads": np.array([0, 1, 1, 0, 0, 1, 1, 0], np.int64), "fc": weights(h * w * 14, 3)}
    init |= {"starts": np.array([1, 1], np.int64), "ends": np.array([h + 1, w + 1], np.int64)}
    init |= {"axes": np.array([1, 2], np.int64), "flat": np.array([1, -1], np.int64)}
    nchw, nhwc = [0, 3, 1, 2], [0, 2, 3, 1]
    nodes = [
        helper.make_node("Transpose", ["x"], ["x_t"], perm=nchw),
        helper.make_node("Conv", ["x_t", "w1", "b1"], ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Transpose", ["c1"], ["c1_t"], perm=nhwc),
        helper.make_node("Mul", ["c1_t", "scale"], ["bn_m"]),
        helper.make_node("Add", ["bn_m", "shift"], ["bn"]),
        helper.make_node("Clip", ["bn", "lo", "hi"], ["r1"]),
        helper.make_node("Pad", ["r1", "pads"], ["p1"]),  # NHWC: H and W by 1 on each side
        helper.make_node("Transpose", ["p1"], ["p1_t"], perm=nchw),
        helper.make_node("Conv", ["p1_t", "w2"], ["c2"]),
        helper.make_node("Transpose", ["c2"], ["c2_t"], perm=nhwc),
        helper.make_node("Slice", ["c2_t", "starts", "ends", "axes"], ["c2_s"]),  # the border cropped off
        helper.make_node("Add", ["c2_s", "c1_t"], ["res"]),  # c1_t is read twice
        helper.make_node("Transpose", ["r1"], ["r1_t"], perm=nchw),
        helper.make_node("Conv", ["r1_t", "w3"], ["c3"]),
        helper.make_node("Transpose", ["c3"], ["c3_t"], perm=nhwc),
        helper.make_node("Relu", ["c3_t"], ["r3"]),
        helper.make_node("Concat", ["res", "r3"], ["cat"], axis=3),  # 8 + 6 channels
        helper.make_node("Sigmoid", ["cat"], ["act"]),
        helper.make_node("Reshape", ["act", "flat"], ["f"]),
        helper.make_node("MatMul", ["f", "fc"], ["y"]),
        helper.make_node("Identity", ["cat"], ["z"]),
    ]
    return onnx_model(nodes, inputs={"x": (1, h, w, c)}, outputs={"y": (1, 3), "z": (1, h, w, 14)}, initializers=init)


@pytest.mark.parametrize("target", TARGETS)
def test_tf2onnx_style_model_matches_onnxruntime(target):
    model = tf2onnx_model()
    graph = PassManager("drop-identity,cancel-transposes").run(nncg.import_onnx(model))
    transposes = [n for n in graph.nodes if n.op == "Transpose"]
    # left: after the graph input, and the two in front of the Concat, which writes graph output z (and the
    # Flatten reads z in NHWC order, as the Dense weights expect); the 3 others are gone
    concat = graph.producer("z")
    assert concat.op == "Concat" and concat.attrs.axis == 3
    assert [t.inputs[0] for t in transposes] == ["x", "res_t0312", "r3_t0312"]
    assert [t.outputs[0] for t in transposes[1:]] == list(concat.inputs)
    compile_and_check(model, target)


@pytest.mark.parametrize("target", TARGETS)
def test_nhwc_benchmark_model_keeps_only_the_input_transpose(target):
    model = keras_mobilenet_nhwc(size=32)
    before = nncg.import_onnx(model)
    after = cancel_transposes(before)
    assert sum(n.op == "Transpose" for n in before.nodes) == 104
    assert [n.inputs for n in after.nodes if n.op == "Transpose"] == [("input_1",)]
    compiled = nncg.compile(model, target=target, verify_ir=True)
    check_against_onnxruntime(model, compiled)
    # every ReLU6 and residual Add fuses into its Conv once the Transposes are gone
    assert sorted(set(kernel_ops(compiled))) == ["Conv", "Dense", "ReduceMean", "Softmax"]
    assert "Transpose" not in kernel_ops(compiled)
