"""DepthToSpace, SpaceToDepth, Tile, Expand, Gather, Where and MatMul with 1-D operands: one small ONNX
model per attribute combination, compiled for every target (NEON under qemu-user) and compared with
onnxruntime; odd sizes, negative axes and indices; the graph IR they become and the copies they cost;
one-line errors for the forms NNCG refuses."""

from __future__ import annotations

import numpy as np
import pytest
from cross_helpers import NEON_TOOLCHAINS, check_on_neon
from helpers import compile_and_check, kernel_ops, onnx_model
from onnx import helper

import nncg
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops import CONVERTERS
from nncg.ir.graph import GatherAttrs, SliceAttrs, TileAttrs
from nncg.lowering.gather import index_runs

RNG = np.random.default_rng(17)
TARGETS = ("ansi-c", "ssse3", "avx2", "avx512")


def ints(*values):
    return np.array(values, dtype=np.int64)


def floats(shape):
    return RNG.standard_normal(shape).astype(np.float32)


def conv(x, y, c_in, c_out, name):
    """A 3x3 'same' Conv node and its weight: its output is a channels-last internal buffer."""
    w = (RNG.standard_normal((c_out, c_in, 3, 3)) / 3).astype(np.float32)
    return helper.make_node("Conv", [x, f"w_{name}"], [y], pads=[1, 1, 1, 1], name=name), {f"w_{name}": w}


def one_op(op, x_shape, extra=(), inits=None, opset=13, with_conv=False, c_out=None, **attrs):
    """op(x, *extra) -> y; with_conv makes it Conv -> op -> Relu, so that the op reads and writes
    internal (channels-last) buffers instead of the row-major graph input and output."""
    inits = dict(inits or {})
    ir_version = 11 if opset > 21 else 8
    if not with_conv:
        node = helper.make_node(op, ["x", *extra], ["y"], **attrs)
        return onnx_model([node], inputs={"x": x_shape}, initializers=inits, opset=opset, ir_version=ir_version)
    c_out = c_out or x_shape[1]
    node, weight = conv("x", "c", x_shape[1], c_out, "conv")
    nodes = [node, helper.make_node(op, ["c", *extra], ["t"], **attrs), helper.make_node("Relu", ["t"], ["y"])]
    return onnx_model(nodes, inputs={"x": x_shape}, initializers=inits | weight, opset=opset, ir_version=ir_version)


# --- DepthToSpace, SpaceToDepth ------------------------------------------------------------------

# x shape, blocksize, mode (None: the default, DCR)
DEPTH_TO_SPACE = {
    "dcr_default": ((1, 8, 3, 5), 2, None),
    "dcr": ((2, 12, 1, 3), 2, "DCR"),
    "crd": ((1, 12, 3, 5), 2, "CRD"),
    "blocksize_3_crd": ((1, 18, 2, 3), 3, "CRD"),
    "blocksize_3_dcr": ((1, 9, 3, 2), 3, "DCR"),
    "blocksize_1": ((1, 3, 2, 5), 1, "DCR"),
}
# x shape, blocksize, mode (CRD needs opset 28)
SPACE_TO_DEPTH = {
    "default": ((1, 3, 6, 4), 2, None),
    "blocksize_3": ((2, 2, 9, 3), 3, None),
    "dcr": ((1, 5, 4, 6), 2, "DCR"),
    "crd": ((1, 3, 4, 10), 2, "CRD"),
}


def _block_attrs(blocksize, mode):
    return {"blocksize": blocksize, **({"mode": mode} if mode else {})}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("with_conv", [False, True])
@pytest.mark.parametrize("case", DEPTH_TO_SPACE)
def test_depth_to_space(case, with_conv, target):
    shape, blocksize, mode = DEPTH_TO_SPACE[case]
    compile_and_check(one_op("DepthToSpace", shape, with_conv=with_conv, **_block_attrs(blocksize, mode)), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("with_conv", [False, True])
@pytest.mark.parametrize("case", SPACE_TO_DEPTH)
def test_space_to_depth(case, with_conv, target):
    shape, blocksize, mode = SPACE_TO_DEPTH[case]
    opset = 28 if mode else 13
    model = one_op("SpaceToDepth", shape, opset=opset, with_conv=with_conv, **_block_attrs(blocksize, mode))
    compile_and_check(model, target)


def pixel_shuffle(mode="DCR"):
    """Conv (16 channels) -> DepthToSpace(2) -> Conv: the sub-pixel upsampling of super-resolution nets."""
    conv_a, w_a = conv("x", "a", 3, 16, "conv_a")
    conv_b, w_b = conv("d", "y", 4, 5, "conv_b")
    shuffle = helper.make_node("DepthToSpace", ["a"], ["d"], blocksize=2, mode=mode, name="shuffle")
    return onnx_model([conv_a, shuffle, conv_b], inputs={"x": (1, 3, 5, 7)}, initializers=w_a | w_b)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("mode", ["DCR", "CRD"])
def test_pixel_shuffle_is_one_copy(mode, target):
    """Between the convs, the Reshape -> Transpose -> Reshape of DepthToSpace is one copy kernel: the
    first Reshape (a split of the channels-last conv output's channels) and the Transpose are views."""
    compiled = compile_and_check(pixel_shuffle(mode), target, unroll=None)
    ops = kernel_ops(compiled)
    assert ops[:3] == ["Conv", "Reshape", "Conv"] and ops.count("Reshape") == 1 and "Transpose" not in ops


def test_depth_to_space_graph_ir():
    graph = import_onnx(one_op("DepthToSpace", (1, 8, 3, 5), blocksize=2, mode="CRD"))
    assert [n.op for n in graph.nodes] == ["Reshape", "Transpose", "Reshape"]
    assert graph.nodes[0].attrs.shape == (1, 2, 2, 2, 3, 5) and graph.nodes[1].attrs.perm == (0, 1, 4, 2, 5, 3)
    assert graph.nodes[2].attrs.shape == (1, 2, 6, 10) and graph.nodes[2].outputs == ("y",)


# --- Tile, Expand --------------------------------------------------------------------------------

TILE = {
    "rank_4": ((1, 3, 2, 5), (1, 2, 3, 1)),
    "innermost": ((2, 3, 1, 3), (1, 1, 2, 3)),
    "every_dim": ((2, 1, 3, 2), (2, 3, 1, 2)),
    "no_repeat": ((1, 2, 3, 3), (1, 1, 1, 1)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("with_conv", [False, True])
@pytest.mark.parametrize("case", TILE)
def test_tile(case, with_conv, target):
    shape, repeats = TILE[case]
    compile_and_check(one_op("Tile", shape, ["r"], {"r": ints(*repeats)}, with_conv=with_conv), target)


@pytest.mark.parametrize("target", TARGETS)
def test_tile_rank_2(target):
    compile_and_check(one_op("Tile", (3, 5), ["r"], {"r": ints(2, 3)}), target)


EXPAND = {
    "channels_to_image": ((1, 4, 1, 1), (1, 4, 3, 5)),
    "rank_grows": ((3, 1), (2, 1, 6)),
    "shape_of_lower_rank": ((1, 3, 1, 5), (4, 1)),
    "ones_keep_dims": ((2, 3, 1, 5), (1, 1, 1, 1)),
    "innermost": ((1, 3, 4, 1), (1, 3, 4, 7)),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", EXPAND)
def test_expand(case, target):
    shape, target_shape = EXPAND[case]
    compile_and_check(one_op("Expand", shape, ["s"], {"s": ints(*target_shape)}), target)


@pytest.mark.parametrize("target", TARGETS)
def test_expand_of_conv_output(target):
    """A pooled conv output [1, 6, 1, 1] expanded over an image and added to the conv output."""
    node, weight = conv("x", "c", 3, 6, "conv")
    nodes = [
        node,
        helper.make_node("GlobalAveragePool", ["c"], ["p"]),
        helper.make_node("Expand", ["p", "s"], ["e"]),
        helper.make_node("Add", ["c", "e"], ["y"]),
    ]
    inits = weight | {"s": ints(1, 6, 5, 3)}
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 3, 5, 3)}, initializers=inits), target)


def test_tile_and_expand_graph_ir():
    tile = import_onnx(one_op("Tile", (1, 3, 2, 5), ["r"], {"r": ints(1, 2, 3, 1)}))
    assert [(n.op, n.attrs) for n in tile.nodes] == [("Tile", TileAttrs((1, 2, 3, 1)))]
    expand = import_onnx(one_op("Expand", (3, 1), ["s"], {"s": ints(2, 1, 6)}))
    assert [n.op for n in expand.nodes] == ["Reshape", "Tile"]
    assert expand.nodes[0].attrs.shape == (1, 3, 1) and expand.nodes[1].attrs == TileAttrs((2, 1, 6))
    same = import_onnx(one_op("Expand", (2, 3), ["s"], {"s": ints(1)}))
    assert [n.op for n in same.nodes] == ["Reshape"]  # nothing to repeat: a view


# --- Gather --------------------------------------------------------------------------------------

# x shape, indices, axis
GATHER = {
    "axis_0_runs": ((5, 4, 3), ints(0, 1, 3), 0),
    "channels_negative_indices": ((1, 6, 3, 4), ints(-1, 0, -3, 2), 1),
    "negative_axis_repeated": ((2, 3, 5), ints(4, 4, 1, 1, 2), -1),
    "reversed_range": ((2, 7, 3), ints(6, 5, 4, 3, 2, 1, 0), 1),
    "strided_slice": ((1, 8, 3, 3), ints(1, 3, 5, 7), 1),
    "scalar_index": ((1, 5, 3, 4), np.array(-2, dtype=np.int64), 1),
    "matrix_indices": ((2, 5, 3), np.array([[0, 4], [2, 2], [-1, 3]], dtype=np.int32), 1),
    "scalar_index_last_axis": ((3, 4), np.array(3, dtype=np.int64), -1),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", GATHER)
def test_gather(case, target):
    shape, indices, axis = GATHER[case]
    compile_and_check(one_op("Gather", shape, ["i"], {"i": indices}, axis=axis), target)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("indices", [ints(5, 0, 2, 3), np.array(4, dtype=np.int64), ints(1, 3, 5)])
@pytest.mark.parametrize("axis", [1, 3])
def test_gather_of_conv_output(indices, axis, target):
    model = one_op("Gather", (1, 3, 4, 6), ["i"], {"i": indices}, with_conv=True, c_out=6, axis=axis)
    compile_and_check(model, target)


def test_gather_graph_ir():
    """Evenly stepping indices are a Slice, others a Gather; indices other than 1-D add a Reshape."""
    strided = import_onnx(one_op("Gather", (1, 8, 3), ["i"], {"i": ints(-1, 4, 1)}, axis=1))
    assert [(n.op, n.attrs) for n in strided.nodes] == [("Slice", SliceAttrs((0, 7, 0), (1, -3, 1)))]
    scalar = import_onnx(one_op("Gather", (1, 8, 3), ["i"], {"i": np.array(2, dtype=np.int64)}, axis=1))
    assert [(n.op, n.attrs) for n in scalar.nodes[:1]] == [("Slice", SliceAttrs((0, 2, 0), (1, 1, 1)))]
    assert scalar.nodes[1].op == "Reshape" and scalar.shape("y") == (1, 3)
    runs = import_onnx(one_op("Gather", (4, 3), ["i"], {"i": np.array([[0, 1], [3, 3]], dtype=np.int64)}))
    assert [(n.op, n.attrs) for n in runs.nodes[:1]] == [("Gather", GatherAttrs(0, (0, 1, 3, 3)))]
    assert runs.nodes[1].op == "Reshape" and runs.shape("y") == (2, 2, 3)


def test_index_runs_are_maximal_from_the_left():
    assert index_runs((0, 1, 3)) == [(0, 0, 1, 2), (2, 3, 1, 1)]
    assert index_runs((4, 4, 1, 1, 2)) == [(0, 4, 0, 2), (2, 1, 0, 2), (4, 2, 1, 1)]
    assert index_runs((6, 4, 2, 3)) == [(0, 6, -2, 3), (3, 3, 1, 1)]


def test_gather_of_a_constant_folds():
    """An embedding-style Gather of a constant table at constant indices is folded at import."""
    nodes = [helper.make_node("Gather", ["table", "i"], ["g"], axis=0), helper.make_node("Add", ["x", "g"], ["y"])]
    inits = {"table": floats((5, 3)), "i": ints(4, 0)}
    model = onnx_model(nodes, inputs={"x": (2, 3)}, initializers=inits)
    assert [n.op for n in import_onnx(model).nodes] == ["Add"]
    compile_and_check(model, "ansi-c")


# --- Where ---------------------------------------------------------------------------------------


def where_model(condition, x_shape, y_shape=None, y_constant=None, x_constant=None):
    """Where(condition, X, Y): X and Y graph inputs of these shapes, or constants when given."""
    inputs, inits = {}, {"cond": condition}
    for name, shape, constant in (("a", x_shape, x_constant), ("b", y_shape, y_constant)):
        if constant is None:
            inputs[name] = shape
        else:
            inits[name] = constant
    node = helper.make_node("Where", ["cond", "a", "b"], ["y"])
    return onnx_model([node], inputs=inputs, initializers=inits, opset=16)


MASK = RNG.random((1, 3, 4, 5)) > 0.5
WHERE = {
    "same_shapes": lambda: where_model(MASK, (1, 3, 4, 5), (1, 3, 4, 5)),
    "broadcast_condition": lambda: where_model(RNG.random((4, 1)) > 0.5, (1, 3, 4, 5), (3, 1, 5)),
    "constant_scalar_y": lambda: where_model(MASK, (1, 3, 4, 5), y_constant=np.array(-np.inf, np.float32)),
    "constant_x": lambda: where_model(RNG.random((5,)) > 0.5, None, (2, 3, 5), x_constant=floats((3, 1))),
    "condition_widens": lambda: where_model(RNG.random((2, 3, 4)) > 0.5, (4,), (3, 1)),
    "all_true": lambda: where_model(np.ones((2, 1), bool), (3,), (2, 3)),
    "all_false_constant_x": lambda: where_model(np.zeros((1, 3), bool), None, (2, 3), x_constant=floats((1, 3))),
}


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", WHERE)
def test_where(case, target):
    compile_and_check(WHERE[case](), target)


@pytest.mark.parametrize("target", TARGETS)
def test_where_masks_a_conv_output(target):
    """Conv -> Where(mask, c, -inf-like constant) -> Softmax over channels: a masked softmax."""
    node, weight = conv("x", "c", 2, 5, "conv")
    nodes = [
        node,
        helper.make_node("Where", ["m", "c", "k"], ["w"]),
        helper.make_node("Softmax", ["w"], ["y"], axis=1),
    ]
    inits = weight | {"m": RNG.random((5, 1, 4)) > 0.3, "k": np.array(-1e4, np.float32)}
    compile_and_check(onnx_model(nodes, inputs={"x": (1, 2, 3, 4)}, initializers=inits, opset=16), target)


def test_where_graph_ir():
    """The condition becomes a constant of 0s and 1s; one that picks a runtime side everywhere is that
    side broadcast; with X and Y constant too, the node folds."""
    graph = import_onnx(where_model(MASK, (1, 3, 4, 5), (1, 3, 4, 5)))
    (node,) = graph.nodes
    assert node.op == "Where" and np.array_equal(graph.constants[node.inputs[0]], MASK.astype(np.float32))
    assert [n.op for n in import_onnx(WHERE["all_true"]()).nodes] == ["Reshape", "Tile"]
    nodes = [helper.make_node("Where", ["m", "k1", "k2"], ["w"]), helper.make_node("Mul", ["x", "w"], ["y"])]
    inits = {"m": MASK, "k1": floats((1, 3, 4, 5)), "k2": np.array(0.5, np.float32)}
    folded = onnx_model(nodes, inputs={"x": (1, 3, 4, 5)}, initializers=inits, opset=16)
    assert [n.op for n in import_onnx(folded).nodes] == ["Mul"]
    compile_and_check(folded, "ansi-c")


# --- MatMul with 1-D operands ----------------------------------------------------------------------

# A shape, B shape, which of them are constants
MATMUL = {
    "vector_times_matrix": ((5,), (5, 3), "B"),
    "batched_times_vector": ((2, 3, 4), (4,), "B"),
    "vector_times_batched": ((4,), (2, 4, 3), ""),
    "batched_4d_times_vector": ((1, 2, 4, 3), (3,), ""),
    "vector_times_vector": ((7,), (7,), ""),
    "constant_vector_times_matrix": ((6,), (2, 6, 3), "A"),
}


def matmul_model(a_shape, b_shape, constants):
    inputs = {name: shape for name, shape in (("a", a_shape), ("b", b_shape)) if name.upper() not in constants}
    inits = {name: floats(shape) for name, shape in (("a", a_shape), ("b", b_shape)) if name.upper() in constants}
    return onnx_model([helper.make_node("MatMul", ["a", "b"], ["y"])], inputs=inputs, initializers=inits)


@pytest.mark.parametrize("target", TARGETS)
@pytest.mark.parametrize("case", MATMUL)
def test_matmul_1d(case, target):
    compile_and_check(matmul_model(*MATMUL[case]), target)


def test_matmul_1d_graph_ir():
    graph = import_onnx(matmul_model((2, 3, 4), (4,), "B"))
    assert [n.op for n in graph.nodes] == ["Dense", "Reshape"]
    assert graph.shape(graph.nodes[1].inputs[0]) == (2, 3, 1) and graph.shape("y") == (2, 3)
    assert graph.constants[graph.nodes[0].inputs[1]].shape == (4, 1)
    both = import_onnx(matmul_model((7,), (7,), ""))
    assert [n.op for n in both.nodes] == ["Reshape", "Reshape", "Dense", "Reshape"] and both.shape("y") == ()


# --- refusals ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("op", "slot", "role"),
    [("Gather", 1, "indices"), ("Tile", 1, "repeats"), ("Expand", 1, "shape"), ("Where", 0, "condition")],
)
def test_runtime_parameters_are_refused_in_one_line(op, slot, role):
    """A parameter computed at runtime, as the converter sees it (graph inputs of other types than
    float32, and the ops computing integers, are refused before conversion)."""
    inputs = ["x", "x", "x"]
    inputs[slot] = "p"
    node = helper.make_node(op, inputs[: 3 if op == "Where" else 2], ["y"])
    ctx = Context(16, {}, {"x": (1, 2, 3, 4), "p": (4,)}, {"y"}, set())
    with pytest.raises(NncgError) as error:
        CONVERTERS[op](OnnxOp.of(node, "n"), ctx)
    assert str(error.value) == (
        f"{op} 'n' has its {role} 'p' computed at runtime; NNCG needs it constant: give it as an initializer, "
        "or fix the input shapes (--input-shape) so that it folds at compile time"
    )


REFUSED = {
    "gather_index_outside": (
        lambda: one_op("Gather", (2, 3), ["i"], {"i": ints(0, 3)}, axis=1, name="n"),
        "Gather 'n' has index 3 outside axis 1 of size 3 (valid: -3 to 2)",
    ),
    "tile_zero_repeat": (
        lambda: one_op("Tile", (2, 3), ["r"], {"r": ints(1, 0)}, name="n"),
        "output 'y' of Tile node 'n' has the empty shape [2, 0]; NNCG does not support empty tensors: change the "
        "node's parameters so that every dimension is at least 1, or remove it",
    ),
    "depth_to_space_channels": (
        lambda: one_op("DepthToSpace", (1, 6, 2, 2), blocksize=2, name="n"),
        "DepthToSpace 'n' has 6 channels, which do not make blocks of 2x2: give it a multiple of 4",
    ),
    "space_to_depth_size": (
        lambda: one_op("SpaceToDepth", (1, 2, 5, 4), blocksize=2, name="n"),
        "SpaceToDepth 'n' has height 5 and width 4, which blocks of 2x2 do not tile: give it multiples of 2",
    ),
}


@pytest.mark.parametrize("case", REFUSED)
def test_invalid_parameters_are_refused_in_one_line(case):
    model, message = REFUSED[case]
    with pytest.raises(NncgError) as error:
        nncg.compile(model())
    assert str(error.value) == message


# --- NEON ----------------------------------------------------------------------------------------

NEON_MODELS = {
    "pixel_shuffle": lambda: pixel_shuffle("DCR"),
    "space_to_depth_conv": lambda: one_op("SpaceToDepth", (1, 3, 6, 4), with_conv=True, blocksize=2),
    "tile_conv": lambda: one_op("Tile", (1, 3, 2, 5), ["r"], {"r": ints(1, 2, 3, 1)}, with_conv=True),
    "expand": lambda: one_op("Expand", (1, 4, 1, 1), ["s"], {"s": ints(1, 4, 3, 5)}),
    "gather_conv": lambda: one_op(
        "Gather", (1, 3, 4, 6), ["i"], {"i": ints(5, 0, 2, 3)}, with_conv=True, c_out=6, axis=1
    ),
    "where": WHERE["broadcast_condition"],
    "matmul_1d": lambda: matmul_model((2, 3, 4), (4,), "B"),
}


@pytest.mark.parametrize("toolchain", NEON_TOOLCHAINS)
@pytest.mark.parametrize("case", NEON_MODELS)
def test_neon_matches_onnxruntime(case, toolchain):
    check_on_neon(toolchain, NEON_MODELS[case]())
