"""The malformed-model corpus: broken files and broken graphs are refused with one clear line, never a
traceback. Each goes through the CLI (exit status 2, exactly one line on stderr, nothing written) and
the Python API (NncgError). Odd models that are valid (pool windows wider than the unpadded input)
compile to C that builds with the strict flags and matches onnxruntime."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import check_against_onnxruntime, nncg_onnx, onnx_model
from onnx import TensorProto, helper, numpy_helper

import nncg
from nncg.errors import NncgError
from nncg.frontend.folding import MAX_FOLDED_ELEMENTS

F = TensorProto.FLOAT
F_NP = np.float32


def relu(shape=(1, 4)) -> onnx.ModelProto:
    return onnx_model([helper.make_node("Relu", ["x"], ["y"])], inputs={"x": list(shape)})


def data(proto: onnx.ModelProto) -> bytes:
    return proto.SerializeToString()


# --- the corpus: name -> (file contents, extra CLI arguments, fragments the message must contain) -----


def broken_files() -> dict:
    good = data(relu())
    newer_ir = relu()
    newer_ir.ir_version = onnx.IR_VERSION + 1
    return {
        "empty": (b"", [], ["empty"]),
        "truncated": (good[: len(good) * 2 // 3], [], ["truncated"]),
        "not_protobuf": (b"this is a text file, not a model\n", [], ["not a valid ONNX model"]),
        "text_proto": (str(relu()).encode(), [], ["ONNX"]),
        "ir_version_too_new": (data(newer_ir), [], [f"IR version {onnx.IR_VERSION + 1}", "upgrade onnx"]),
    }


def broken_graphs() -> dict:
    cases = {}
    cycle = [helper.make_node("Add", ["x", "b"], ["a"], name="n1"), helper.make_node("Relu", ["a"], ["b"], name="n2")]
    cases["cycle"] = (
        onnx_model(cycle, inputs={"x": [1, 2]}, outputs={"a": None}),
        ["cycle", "'n1'", "'n2'", "acyclic"],
    )
    untyped = onnx_model(
        [helper.make_node("Relu", ["x"], ["y"])], inputs={"x": [1, 2]}, outputs={"y": onnx.ValueInfoProto(name="y")}
    )
    cases["output_without_type"] = (untyped, ["graph output 'y' has no type", "float32"])
    undefined = onnx_model([helper.make_node("Add", ["x", "ghost"], ["y"], name="add")], inputs={"x": [1, 2]})
    cases["undefined_input"] = (undefined, ["'add'", "'ghost'", "no node, graph input or initializer"])
    twice = [helper.make_node("Relu", ["x"], ["y"], name="a"), helper.make_node("Neg", ["x"], ["y"], name="b")]
    cases["two_producers"] = (onnx_model(twice, inputs={"x": [1, 2]}), ["'y'", "node 'a'", "node 'b'", "one source"])
    big_kernel = [helper.make_node("Conv", ["x", "w"], ["y"], name="conv")]
    cases["negative_dims"] = (
        onnx_model(big_kernel, inputs={"x": [1, 1, 3, 3]}, initializers={"w": np.ones((1, 1, 5, 5), np.float32)}),
        ["Conv node 'conv'", "[1, 1, -1, -1]", "negative", "--input-shape"],
    )
    strided = [helper.make_node("Conv", ["x", "w"], ["y"], strides=[2, 2], name="conv")]
    cases["conv_window_past_padding"] = (
        onnx_model(strided, inputs={"x": [1, 1, 2, 2]}, initializers={"w": np.ones((1, 1, 3, 3), np.float32)}),
        ["Conv 'conv'", "window of 3", "padded input (2 + pads 0 + 0)"],
    )
    cases["empty_pool_output"] = (
        onnx_model([helper.make_node("MaxPool", ["x"], ["y"], kernel_shape=[3], name="pool")], inputs={"x": [1, 1, 2]}),
        ["'pool'", "[1, 1, 0]", "empty tensors"],
    )
    cases["pool_window_past_padding"] = (
        onnx_model(
            [helper.make_node("MaxPool", ["x"], ["y"], kernel_shape=[3], strides=[2], name="p")],
            inputs={"x": [1, 1, 2]},
        ),
        ["MaxPool 'p'", "window of 3", "padded input", "ceil_mode=1"],
    )
    cases["huge_input"] = (relu((1, 3, 100000, 100000)), ["input 'x'", "30,000,000,000 elements", "--input-shape"])
    bomb = [
        helper.make_node(
            "ConstantOfShape", ["s"], ["c"], name="bomb", value=numpy_helper.from_array(np.ones(1, np.float32))
        ),
        helper.make_node("ReduceSum", ["c"], ["r"], keepdims=0),
        helper.make_node("Add", ["x", "r"], ["y"]),
    ]
    cases["constant_of_shape_bomb"] = (
        onnx_model(bomb, inputs={"x": [1]}, initializers={"s": np.array([28000, 28000], np.int64)}),
        ["ConstantOfShape node 'bomb'", "[28000, 28000]", "784,000,000 elements", "MAX_FOLDED_ELEMENTS"],
    )
    nan = np.array([[1.0, np.nan, 2.0]], np.float32)
    cases["nan_weights"] = (
        onnx_model([helper.make_node("Add", ["x", "w"], ["y"])], inputs={"x": [1, 3]}, initializers={"w": nan}),
        ["initializer 'w'", "NaN", "[0, 1]", "nan_to_num"],
    )
    folded_nan = [helper.make_node("Log", ["minus"], ["w"], name="log"), helper.make_node("Mul", ["x", "w"], ["y"])]
    cases["nan_folded"] = (
        onnx_model(folded_nan, inputs={"x": [1, 2]}, initializers={"minus": np.array([-1.0, 1.0], np.float32)}),
        ["constant 'w' (computed at compile time by node 'log')", "NaN"],
    )
    reshape = [helper.make_node("Reshape", ["x", "s"], ["y"], name="r")]
    cases["reshape_mismatch"] = (
        onnx_model(reshape, inputs={"x": [1, 12]}, initializers={"s": np.array([5, 5], np.int64)}),
        ["Reshape 'r'", "12 elements", "25 elements", "shape input"],
    )
    cases["unsupported_op"] = (
        onnx_model([helper.make_node("Sin", ["x"], ["y"], name="sin")], inputs={"x": [1, 2]}),
        ["unsupported operators", "Sin (node 'sin')"],
    )
    cases["unknown_op"] = (
        onnx_model([helper.make_node("Frobnicate", ["x"], ["y"])], inputs={"x": [1, 2]}),
        ["opset 13 does not have", "Frobnicate"],
    )
    cases["bad_node_arity"] = (
        onnx_model([helper.make_node("Relu", ["x", "x"], ["y"], name="r")], inputs={"x": [1, 2]}),
        ["Relu node 'r'", "Relu-13", "input size 2"],
    )
    cases["dynamic_shape"] = (relu((4, "N")), ["dynamic shape", "--input-shape x=4x1"])
    int_input = onnx_model(
        [helper.make_node("Cast", ["ids"], ["y"], to=F)],
        inputs={"ids": helper.make_tensor_value_info("ids", TensorProto.INT64, [1, 4])},
    )
    cases["non_float_input"] = (int_input, ["input 'ids' is int64", "float32"])
    return {name: (data(proto), [], fragments) for name, (proto, fragments) in cases.items()}


def with_cli_arguments() -> dict:
    huge = relu(("N", 3, "H", "W"))
    return {"huge_input_shape": (data(huge), ["--input-shape", "x=1x3x100000x100000"], ["30,000,000,000"])}


CORPUS = {**broken_files(), **broken_graphs(), **with_cli_arguments()}


@pytest.mark.parametrize("case", CORPUS)
def test_cli_refuses_in_one_line_and_writes_nothing(case, tmp_path):
    contents, arguments, fragments = CORPUS[case]
    path = tmp_path / f"{case}.onnx"
    path.write_bytes(contents)
    out = tmp_path / "out"
    result = nncg_onnx(path, "-o", out, *arguments)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("nncg-onnx: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("case", CORPUS)
def test_api_raises_nncg_error(case):
    contents, arguments, fragments = CORPUS[case]
    shapes = {"x": (1, 3, 100000, 100000)} if arguments else None
    with pytest.raises(NncgError) as info:
        nncg.compile(contents, input_shapes=shapes)
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message


def test_fold_cap_is_checked_before_evaluating(monkeypatch):
    """The bomb is refused from its inferred shape: the evaluator never runs."""
    import nncg.frontend.folding as folding

    def evaluate(*args):
        raise AssertionError("the node was evaluated")

    monkeypatch.setattr(folding, "_evaluate", evaluate)
    contents = CORPUS["constant_of_shape_bomb"][0]
    with pytest.raises(NncgError, match="MAX_FOLDED_ELEMENTS"):
        nncg.compile(contents)
    assert 28000 * 28000 > MAX_FOLDED_ELEMENTS


def test_unsorted_acyclic_graph_is_sorted_and_keeps_its_node_names():
    nodes = [helper.make_node("Relu", ["a"], ["y"]), helper.make_node("Sigmoid", ["x"], ["a"], name="sig")]
    proto = onnx_model(nodes, inputs={"x": [1, 4]})
    graph = nncg.import_onnx(proto)
    assert [(n.op, n.name) for n in graph.nodes] == [("Sigmoid", "sig"), ("Relu", "Relu_0")]
    check_against_onnxruntime(proto, nncg.compile(proto))


# --- accepted odd inputs: pool windows wider than the unpadded input ------------------------------

ODD_POOLS = {
    "max_window_fills_padding": ("MaxPool", 19, (1, 3, 3, 3), dict(kernel_shape=[5, 5], pads=[1, 1, 1, 1])),
    "max_ceil_window_wider_than_input": (
        "MaxPool",
        11,
        (1, 3, 3, 4),
        dict(kernel_shape=[4, 4], pads=[1, 1, 1, 1], strides=[2, 2], ceil_mode=1),
    ),
    "max_ceil_window_past_padding": (
        "MaxPool",
        19,
        (1, 2, 2, 5),
        dict(kernel_shape=[3, 2], strides=[2, 1], ceil_mode=1),
    ),
    "average_ceil_exclude_pad": (
        "AveragePool",
        19,
        (1, 3, 2, 5),
        dict(kernel_shape=[3, 3], pads=[1, 1, 1, 1], strides=[3, 3], ceil_mode=1),
    ),
    "average_ceil_include_pad": (
        "AveragePool",
        11,
        (1, 3, 2, 5),
        dict(kernel_shape=[3, 3], pads=[0, 1, 2, 1], strides=[2, 2], ceil_mode=1, count_include_pad=1),
    ),
    "average_include_pad_asymmetric": (
        "AveragePool",
        19,
        (1, 3, 3, 3),
        dict(kernel_shape=[4, 4], pads=[2, 2, 1, 1], count_include_pad=1),
    ),
    "average_dilated_exclude_pad": (
        "AveragePool",
        19,
        (1, 2, 3, 3),
        dict(kernel_shape=[3, 2], dilations=[2, 1], pads=[1, 0, 1, 0], ceil_mode=1),
    ),
    "average_opset_22": (
        "AveragePool",
        22,
        (1, 3, 2, 5),
        dict(kernel_shape=[3, 3], pads=[1, 1, 1, 1], strides=[3, 3], ceil_mode=1, count_include_pad=1),
    ),
}


@pytest.mark.parametrize("target", ["ansi-c", "ssse3"])
@pytest.mark.parametrize("case", ODD_POOLS)
def test_pool_window_wider_than_the_input_matches_onnxruntime(case, target):
    op, opset, shape, attrs = ODD_POOLS[case]
    proto = onnx_model([helper.make_node(op, ["x"], ["y"], **attrs)], inputs={"x": list(shape)}, opset=opset)
    for unroll in (None, "auto"):
        check_against_onnxruntime(proto, nncg.compile(proto, target=target, unroll=unroll, verify_ir=True))
