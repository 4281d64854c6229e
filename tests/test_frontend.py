"""Tests of the ONNX front end (ONNX -> graph IR): loading, validation, constant folding, op conversion."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from helpers import compile_and_check, onnx_model
from onnx import TensorProto, helper, numpy_helper

from nncg.errors import NncgError, NncgWarning, UnsupportedOpsError
from nncg.frontend import import_onnx, load_model
from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_nn import convert_maxpool
from nncg.frontend.ops_shape import convert_dropout
from nncg.ir.graph import (
    Activation,
    BatchNormAttrs,
    ConvAttrs,
    DenseAttrs,
    Graph,
    Node,
    PoolAttrs,
    ReshapeAttrs,
    SoftmaxAttrs,
)
from nncg.ir.names import fresh_name
from nncg.ir.ops import IR_OPS

F = TensorProto.FLOAT
RNG = np.random.default_rng(0)


# --- helpers -------------------------------------------------------------------------------------


def value(name, shape, dtype=F):
    return helper.make_tensor_value_info(name, dtype, shape)


def const(name, array):
    return numpy_helper.from_array(np.asarray(array), name)


def rand(*shape):
    return RNG.standard_normal(shape).astype(np.float32)


def one_op(op, in_shape, out_shape=None, inits=None, extra_inputs=(), opset=13, outputs=("y",), **attrs):
    """A model with a single node reading x (and constants by name), writing y."""
    node = helper.make_node(op, ["x", *extra_inputs], list(outputs), **attrs)
    return onnx_model([node], inputs={"x": in_shape}, outputs={"y": out_shape}, initializers=inits, opset=opset)


def run_ort(proto, feeds):
    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, feeds)


def ort_shape(proto, name="x"):
    """Output shape onnxruntime actually produces on the model NNCG compiled."""
    loaded = load_model(proto)
    shape = [d.dim_value for d in loaded.graph.input[0].type.tensor_type.shape.dim]
    return tuple(run_ort(loaded, {name: rand(*shape)})[0].shape)


def only(graph: Graph) -> Node:
    assert len(graph.nodes) == 1, graph.nodes
    return graph.nodes[0]


def fails(source, *fragments, error=NncgError, **kwargs) -> str:
    """import_onnx raises `error` with a one-line message containing every fragment."""
    with pytest.raises(error) as info:
        import_onnx(source, **kwargs)
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message
    return message


def conv_model(x_shape=(1, 2, 7, 7), w_shape=(3, 2, 3, 3), bias=True, opset=13, **attrs):
    inputs = ["x", "w", "b"] if bias else ["x", "w"]
    inits = {"w": rand(*w_shape), **({"b": rand(w_shape[0])} if bias else {})}
    node = helper.make_node("Conv", inputs, ["y"], name="conv", **attrs)
    return onnx_model([node], inputs={"x": x_shape}, initializers=inits, opset=opset)


# --- loading -------------------------------------------------------------------------------------


def test_loads_path_bytes_proto_and_load_model_result(tmp_path):
    proto = one_op("Relu", [1, 4])
    path = tmp_path / "m.onnx"
    onnx.save(proto, path)
    graphs = [import_onnx(src) for src in (str(path), path, proto.SerializeToString(), proto, load_model(proto))]
    assert all(g == graphs[0] for g in graphs)
    assert graphs[0].nodes == (Node("Relu", "Relu_0", ("x",), ("y",), Activation("relu")),)


def test_load_model_does_not_modify_the_callers_proto():
    proto = one_op("Relu", ["N", 4])
    load_model(proto, {"x": (2, 4)})
    assert proto.graph.input[0].type.tensor_type.shape.dim[0].dim_param == "N"


def test_missing_file(tmp_path):
    fails(tmp_path / "nope.onnx", "nope.onnx", "does not exist")


def test_text_file_is_not_onnx(tmp_path):
    path = tmp_path / "notes.onnx"
    path.write_text("this is a text file, not a model\n")
    fails(path, "notes.onnx", "not", "ONNX")


def test_empty_file(tmp_path):
    path = tmp_path / "empty.onnx"
    path.write_bytes(b"")
    fails(path, "empty.onnx", "empty")


def test_directory_is_not_a_model(tmp_path):
    fails(tmp_path, "not a file")


def test_wrong_argument_type():
    fails(42, "int", "file path")


def test_every_truncation_of_a_real_model_is_detected(tmp_path):
    data = conv_model(opset=13).SerializeToString()
    for cut in range(len(data)):
        with pytest.raises(NncgError):
            import_onnx(data[:cut])
    path = tmp_path / "cut.onnx"
    path.write_bytes(data[: len(data) * 2 // 3])
    fails(path, "cut.onnx", "truncated")


def test_cut_before_opset_import_parses_but_is_detected():
    data = conv_model().SerializeToString()
    opset = helper.make_model(helper.make_graph([], "g", [], []), opset_imports=[helper.make_opsetid("", 13)])
    tail = len(opset.opset_import[0].SerializeToString()) + 2  # field tag and length byte
    cut = data[:-tail]
    assert onnx.load_model_from_string(cut).graph.node  # protobuf accepts it silently
    fails(cut, "opset_import")


def test_model_failing_the_checker():
    node = helper.make_node("Relu", ["x", "x"], ["y"])  # Relu takes one input
    fails(
        onnx_model([node], inputs={"x": [1, 2]}, outputs={"y": [1, 2]}),
        "Relu node 'Relu_0'",
        "Relu-13 schema",
        "input size 2",
    )


def test_non_default_domain_is_refused():
    node = helper.make_node("FusedConv", ["x"], ["y"], name="fc", domain="com.microsoft")
    proto = onnx_model([node], inputs={"x": [1, 2]}, outputs={"y": [1, 2]})
    proto.opset_import.append(helper.make_opsetid("com.microsoft", 1))
    fails(proto, "com.microsoft.FusedConv (node 'fc')", "non-default domain", error=UnsupportedOpsError)


def test_too_old_opset():
    fails(one_op("Relu", [1, 2], opset=6), "opset 6", "7 to")


def test_external_data_is_read_from_a_path_but_not_from_bytes(tmp_path):
    proto = conv_model()
    weight = numpy_helper.to_array(proto.graph.initializer[0])
    path = tmp_path / "ext.onnx"
    onnx.save(proto, path, save_as_external_data=True, all_tensors_to_one_file=True, size_threshold=0)
    assert len(list(tmp_path.iterdir())) == 2  # the model and its data file
    np.testing.assert_array_equal(import_onnx(path).constants["w"], weight)
    fails(path.read_bytes(), "'w'", "external", "file path")


def test_declared_output_shape_must_match():
    fails(one_op("Relu", [1, 4], out_shape=[1, 5]), "output 'y'", "[1, 5]", "[1, 4]")


def test_shape_inference_errors_are_wrapped():
    node = helper.make_node("Add", ["x", "c"], ["y"])
    proto = onnx_model([node], inputs={"x": [1, 3]}, initializers={"c": rand(1, 4)})
    fails(proto, "shape inference")


# --- graph inputs and outputs --------------------------------------------------------------------


def test_inputs_with_initializers_are_constants():
    # Old exporters (IR 3) list every initializer among the graph inputs.
    node = helper.make_node("Add", ["x", "c"], ["y"])
    proto = onnx_model(
        [node],
        inputs={"x": [1, 3], "c": [1, 3]},
        outputs={"y": [1, 3]},
        initializers={"c": rand(1, 3)},
        opset=7,
        ir_version=3,
    )
    graph = import_onnx(proto)
    assert [v.name for v in graph.inputs] == ["x"]
    assert graph.is_constant("c") and graph.constants["c"].dtype == np.float32


def test_non_float32_input():
    node = helper.make_node("Cast", ["ids"], ["y"], to=F)
    proto = onnx_model([node], inputs={"ids": value("ids", [1, 4], TensorProto.INT64)}, outputs={"y": [1, 4]})
    fails(proto, "input 'ids' is int64; NNCG compiles models whose inputs are float32, int8, uint8")


def test_non_float32_output():
    node = helper.make_node("Cast", ["x"], ["y"], to=TensorProto.INT64)
    proto = onnx_model([node], inputs={"x": [1, 4]}, outputs={"y": value("y", [1, 4], TensorProto.INT64)})
    fails(proto, "output 'y' is int64")


def local_functions_model(function_opset: int = 13) -> onnx.ModelProto:
    """x -> Block(x) -> y, where the model-local function Block calls ConvLeaky twice and ConvLeaky
    (Conv then LeakyRelu with the caller's alpha attribute) is a model-local function too."""
    leaky = helper.make_node("LeakyRelu", ["c"], ["Y"])
    leaky.attribute.append(helper.make_attribute_ref("alpha", onnx.AttributeProto.FLOAT))
    conv_leaky = helper.make_function(
        "my.fns", "ConvLeaky", ["X", "W"], ["Y"],
        [helper.make_node("Conv", ["X", "W"], ["c"], pads=[1, 1, 1, 1]), leaky],
        [helper.make_opsetid("", function_opset)], attributes=["alpha"],
    )  # fmt: skip
    block = helper.make_function(
        "my.fns", "Block", ["X", "W1", "W2"], ["Y"],
        [helper.make_node("ConvLeaky", ["X", "W1"], ["h"], domain="my.fns", alpha=0.1),
         helper.make_node("ConvLeaky", ["h", "W2"], ["Y"], domain="my.fns", alpha=0.3)],
        [helper.make_opsetid("", function_opset), helper.make_opsetid("my.fns", 1)],
    )  # fmt: skip
    proto = onnx_model(
        [helper.make_node("Block", ["x", "w1", "w2"], ["y"], domain="my.fns")],
        inputs={"x": [1, 2, 6, 6]}, outputs={"y": [1, 4, 6, 6]},
        initializers={"w1": rand(3, 2, 3, 3), "w2": rand(4, 3, 3, 3)},
    )  # fmt: skip
    proto.opset_import.append(helper.make_opsetid("my.fns", 1))
    proto.functions.extend([conv_leaky, block])
    return proto


def test_local_functions_are_inlined():
    proto = local_functions_model()
    graph = import_onnx(proto)
    assert [n.op for n in graph.nodes].count("Conv") == 2 and not load_model(proto).functions
    compile_and_check(proto, "ansi-c")


def test_local_functions_onnx_cannot_convert_to_the_models_opset_are_refused():
    fails(local_functions_model(function_opset=11), "cannot inline the model's local functions", "Type unknown")


def test_dynamic_dim_param():
    fails(one_op("Relu", ["N", 3, "H", 8]), "input 'x'", "x[N,3,H,8]", "--input-shape x=1x3x1x8")


def test_missing_dim_value():
    proto = one_op("Relu", [3, None])
    fails(proto, "x[3,?]", "--input-shape x=3x1")


@pytest.mark.parametrize("batch", ["N", None])
def test_dynamic_batch_defaults_to_1_with_a_warning(batch):
    with pytest.warns(NncgWarning, match=r"input 'x' has a dynamic batch dimension .*--input-shape x=Bx3x8x8"):
        graph = import_onnx(one_op("Relu", [batch, 3, 8, 8]))
    assert graph.inputs[0].shape == (1, 3, 8, 8) and graph.shapes["y"] == (1, 3, 8, 8)


def test_a_dynamic_vector_length_is_no_batch():
    fails(one_op("Relu", ["N"]), "x[N]", "--input-shape x=1")


def test_unknown_rank():
    proto = one_op("Relu", [1, 3])
    proto.graph.input[0].type.tensor_type.ClearField("shape")
    fails(proto, "input 'x'", "x[unknown rank]", "--input-shape")


def test_input_shapes_fix_dynamic_dims():
    graph = import_onnx(one_op("Relu", ["N", 3, "H", 8]), {"x": (2, 3, 5, 8)})
    assert graph.inputs[0].shape == (2, 3, 5, 8)
    assert graph.outputs[0].shape == (2, 3, 5, 8)
    assert graph.shapes["y"] == (2, 3, 5, 8)


def test_input_shapes_give_unknown_rank():
    proto = one_op("Relu", [1, 3])
    proto.graph.input[0].type.tensor_type.ClearField("shape")
    assert import_onnx(proto, {"x": (4, 5)}).shapes["y"] == (4, 5)


@pytest.mark.parametrize(
    ("shapes", "fragments"),
    [
        ({"z": (1, 3)}, ["'z'", "not an input", "'x'"]),
        ({"c": (1, 3)}, ["'c'", "constant"]),
        ({"x": (1, 3, 8)}, ["input 'x'", "3 dims", "x[N,3]"]),
        ({"x": (1, 4)}, ["input 'x'", "dim 1 = 4", "fixes it at 3"]),
        ({"x": (1, -3)}, ["input_shapes['x']", "positive ints"]),
    ],
)
def test_bad_input_shapes(shapes, fragments):
    node = helper.make_node("Add", ["x", "c"], ["y"])
    proto = onnx_model([node], inputs={"x": ["N", 3], "c": [1, 3]}, initializers={"c": rand(1, 3)})
    fails(proto, *fragments, input_shapes=shapes)


def test_inputs_outputs_keep_onnx_order_and_all_shapes_are_recorded():
    nodes = [helper.make_node("Relu", ["b"], ["r"]), helper.make_node("Add", ["r", "a"], ["s"])]
    proto = onnx_model(nodes, inputs={"b": [1, 2], "a": [1, 2]}, outputs={"s": None, "r": None})
    graph = import_onnx(proto)
    assert [v.name for v in graph.inputs] == ["b", "a"]
    assert [v.name for v in graph.outputs] == ["s", "r"]
    assert graph.shapes == {"a": (1, 2), "b": (1, 2), "r": (1, 2), "s": (1, 2)}


def test_node_names_default_to_op_and_index_and_are_unique():
    nodes = [
        helper.make_node("Relu", ["x"], ["a"], name="act"),
        helper.make_node("Relu", ["a"], ["b"], name="act"),
        helper.make_node("Relu", ["b"], ["y"]),
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 2]}))
    assert [n.name for n in graph.nodes] == ["act", "act_1", "Relu_2"]


def test_fresh_name_counts_up_past_every_taken_collection():
    assert fresh_name("w", set()) == "w"
    assert fresh_name("w", {"w", "w_1"}, {"w_2": 0}) == "w_3"
    assert fresh_name("w", {"w_1"}) == "w"


def test_every_ir_node_uses_a_canonical_op_and_its_attr_record():
    graph = import_onnx(conv_model())
    for node in graph.nodes:
        expected = IR_OPS[node.op].attrs
        assert node.attrs is None if expected is None else isinstance(node.attrs, expected)


# --- constant folding ----------------------------------------------------------------------------


def test_shape_gather_concat_reshape_chain_folds_away():
    nodes = [
        helper.make_node("Shape", ["x"], ["s"]),
        helper.make_node("Gather", ["s", "zero"], ["n"], axis=0),
        helper.make_node("Unsqueeze", ["n", "axes"], ["n1"]),
        helper.make_node("Concat", ["n1", "minus1"], ["target"], axis=0),
        helper.make_node("Cast", ["target"], ["target64"], to=TensorProto.INT64),
        helper.make_node("Reshape", ["x", "target64"], ["y"], name="flat"),
    ]
    inits = {"zero": np.array(0, np.int64), "axes": [0], "minus1": [-1]}
    proto = onnx_model(nodes, inputs={"x": ["N", 3, 4, 4]}, outputs={"y": ["N", "K"]}, initializers=inits)
    graph = import_onnx(proto, {"x": (2, 3, 4, 4)})
    assert only(graph) == Node("Reshape", "flat", ("x",), ("y",), ReshapeAttrs((2, 48)))
    assert graph.constants == {}
    assert graph.outputs[0].shape == (2, 48)


def test_shape_start_end_folds():
    # Shape with start (opset 15): keep the last two dims, merge the rest.
    nodes = [
        helper.make_node("Shape", ["x"], ["tail"], start=-2),
        helper.make_node("Concat", ["minus1", "tail"], ["target"], axis=0),
        helper.make_node("Reshape", ["x", "target"], ["y"]),
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [2, 3, 4, 5]}, initializers={"minus1": [-1]}, opset=15))
    assert only(graph).attrs == ReshapeAttrs((6, 4, 5))


def test_constant_of_shape_and_size_fold():
    nodes = [
        helper.make_node("ConstantOfShape", ["shape"], ["twos"], value=const("v", np.array([2.0], np.float32))),
        helper.make_node("Size", ["x"], ["n"]),
        helper.make_node("Cast", ["n"], ["nf"], to=F),
        helper.make_node("Mul", ["x", "twos"], ["m"]),
        helper.make_node("Div", ["m", "nf"], ["y"]),
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 3]}, initializers={"shape": [1, 3]}))
    assert [n.op for n in graph.nodes] == ["Mul", "Div"]
    np.testing.assert_array_equal(graph.constants["twos"], np.full((1, 3), 2.0, np.float32))
    assert graph.constants["nf"] == np.float32(3)


@pytest.mark.parametrize(
    ("attrs", "expected"),
    [
        ({"value": const("t", np.array([1.5, 2.5, 3.5], np.float32))}, [1.5, 2.5, 3.5]),
        ({"value_float": 4.0}, 4.0),
        ({"value_floats": [1.0, 2.0, 3.0]}, [1.0, 2.0, 3.0]),
        ({"value_int": 7}, 7.0),
        ({"value_ints": [1, 2, 3]}, [1.0, 2.0, 3.0]),
        (
            {
                "sparse_value": helper.make_sparse_tensor(
                    const("sv", np.array([5.0], np.float32)), const("si", [1]), [3]
                )
            },
            [0.0, 5.0, 0.0],
        ),
    ],
)
def test_constant_value_forms_fold(attrs, expected):
    nodes = [
        helper.make_node("Constant", [], ["c"], **attrs),
        helper.make_node("Cast", ["c"], ["cf"], to=F),  # value_int(s) are int64
        helper.make_node("Add", ["x", "cf"], ["y"], name="add"),
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 3]}))
    assert only(graph) == Node("Add", "add", ("x", "cf"), ("y",))
    assert graph.constants["cf"].dtype == np.float32
    np.testing.assert_array_equal(graph.constants["cf"], np.asarray(expected, np.float32))


def test_weight_computed_from_constants_folds_to_float32():
    nodes = [
        helper.make_node("Transpose", ["w16"], ["wt"], perm=[1, 0, 2, 3]),
        helper.make_node("Cast", ["wt"], ["w"], to=F),
        helper.make_node("Conv", ["x", "w"], ["y"]),
    ]
    w16 = rand(2, 3, 1, 1).astype(np.float16)
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 2, 4, 4]}, initializers={"w16": w16}))
    node = only(graph)
    assert node.inputs == ("x", "w")
    np.testing.assert_array_equal(graph.constants["w"], w16.transpose(1, 0, 2, 3).astype(np.float32))


def test_constant_graph_output_is_refused():
    nodes = [helper.make_node("Relu", ["x"], ["y"]), helper.make_node("Constant", [], ["k"], value_float=1.0)]
    fails(onnx_model(nodes, inputs={"x": [1, 2]}, outputs={"y": None, "k": value("k", [])}), "output 'k'", "constant")


def test_dead_branches_are_not_compiled():
    nodes = [helper.make_node("Relu", ["x"], ["y"]), helper.make_node("Tanh", ["x"], ["unused"])]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 2]}))
    assert [n.op for n in graph.nodes] == ["Relu"]


# --- unsupported operators -----------------------------------------------------------------------


def test_all_unsupported_ops_are_listed_at_once():
    nodes = [
        helper.make_node("Sin", ["x"], ["t"], name="t1"),
        helper.make_node("Relu", ["t"], ["r"]),
        helper.make_node("Cos", ["r"], ["y"]),
    ]
    message = fails(
        onnx_model(nodes, inputs={"x": [1, 2]}),
        "Sin (node 't1')",
        "Cos (node 'Cos_2')",
        error=UnsupportedOpsError,
    )
    supported = message.split("NNCG supports ")[1]
    assert "Relu (node" not in message
    for op in ("BatchNormalization", "Conv", "Gemm", "MatMul", "Unsqueeze"):
        assert op in supported
    assert "Constant" in supported  # folded-only ops are named too


def test_unsupported_op_with_constant_inputs_is_folded_not_refused():
    nodes = [helper.make_node("Tanh", ["c"], ["t"]), helper.make_node("Add", ["x", "t"], ["y"])]
    c = np.array([[0.5, 1.0]], np.float32)
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 2]}, initializers={"c": c}))
    assert only(graph).inputs == ("x", "t")
    np.testing.assert_allclose(graph.constants["t"], np.tanh(c), rtol=1e-6)


# --- Conv ----------------------------------------------------------------------------------------


def test_conv_explicit_asymmetric_pads_and_defaults():
    proto = conv_model(pads=[0, 1, 2, 3])
    graph = import_onnx(proto)
    node = only(graph)
    assert node == Node(
        "Conv", "conv", ("x", "w", "b"), ("y",), ConvAttrs((3, 3), (1, 1), (1, 1), pads_begin=(0, 1), pads_end=(2, 3))
    )
    assert graph.shapes["y"] == ort_shape(proto) == (1, 3, 7, 9)
    assert graph.constants["w"].dtype == np.float32


@pytest.mark.parametrize(
    ("auto_pad", "begin", "end"),
    [("SAME_UPPER", (1, 1), (2, 2)), ("SAME_LOWER", (2, 2), (1, 1)), ("VALID", (0, 0), (0, 0))],
)
def test_conv_auto_pad(auto_pad, begin, end):
    # in 7, k 4, stride 2: SAME gives ceil(7/2) = 4 outputs, total pad (4-1)*2 + 4 - 7 = 3.
    proto = conv_model(w_shape=(3, 2, 4, 4), auto_pad=auto_pad, strides=[2, 2])
    graph = import_onnx(proto)
    attrs = only(graph).attrs
    assert (attrs.pads_begin, attrs.pads_end, attrs.strides) == (begin, end, (2, 2))
    assert graph.shapes["y"] == ort_shape(proto)


def test_conv_same_pad_uses_dilation():
    # in 8, k 3, dilation 2 (span 5), stride 1: total pad 4.
    graph = import_onnx(conv_model(x_shape=(1, 2, 8, 8), auto_pad="SAME_UPPER", dilations=[2, 2]))
    attrs = only(graph).attrs
    assert (attrs.pads_begin, attrs.pads_end, attrs.dilations) == ((2, 2), (2, 2), (2, 2))
    assert graph.shapes["y"] == (1, 3, 8, 8)


@pytest.mark.parametrize(("x_shape", "w_shape"), [((1, 2, 9), (4, 2, 3)), ((1, 2, 5, 6, 7), (4, 2, 1, 2, 3))])
def test_conv_any_number_of_spatial_dims(x_shape, w_shape):
    proto = conv_model(x_shape, w_shape, bias=False, strides=[2] * (len(x_shape) - 2))
    graph = import_onnx(proto)
    node = only(graph)
    assert node.inputs == ("x", "w")
    assert node.attrs.kernel == w_shape[2:]
    assert node.attrs.pads_begin == node.attrs.pads_end == (0,) * (len(x_shape) - 2)
    assert graph.shapes["y"] == ort_shape(proto)


def test_conv_old_opset_and_kernel_shape_attribute():
    graph = import_onnx(conv_model(opset=7, kernel_shape=[3, 3], pads=[1, 1, 1, 1]))
    assert only(graph).attrs.kernel == (3, 3)
    assert graph.shapes["y"] == (1, 3, 7, 7)


def test_conv_group_is_kept_and_checked():
    proto = conv_model(x_shape=(1, 4, 5, 5), w_shape=(6, 2, 3, 3), group=2)
    assert import_onnx(proto).nodes[0].attrs.group == 2
    bad = conv_model(x_shape=(1, 4, 5, 5), w_shape=(6, 1, 3, 3), group=2)
    fails(bad, "Conv 'conv' has group=2 with 4 input channels and weight [6, 1, 3, 3]")


def test_conv_runtime_weight_is_kept_as_an_input():
    node = helper.make_node("Conv", ["x", "w"], ["y"], name="conv")
    graph = import_onnx(onnx_model([node], inputs={"x": [1, 2, 5, 5], "w": [3, 2, 3, 3]}))
    assert only(graph).inputs == ("x", "w") and not graph.is_constant("w")
    assert only(graph).attrs.kernel == (3, 3) and graph.shapes["y"] == (1, 3, 3, 3)


# --- MaxPool -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("size", "attrs"),
    [
        (5, {"kernel_shape": [2, 2], "strides": [2, 2]}),
        (5, {"kernel_shape": [2, 2], "strides": [2, 2], "ceil_mode": 1}),
        (6, {"kernel_shape": [3, 3], "strides": [2, 2], "ceil_mode": 1, "pads": [1, 1, 1, 1]}),
        # ceil would add a window starting in the end padding; the spec drops it: 2 outputs, not 3.
        (4, {"kernel_shape": [2, 2], "strides": [2, 2], "ceil_mode": 1, "pads": [0, 0, 1, 1]}),
        (7, {"kernel_shape": [3, 3], "strides": [2, 2], "dilations": [2, 2], "ceil_mode": 1}),
        (5, {"kernel_shape": [2, 2], "strides": [2, 2], "ceil_mode": 1, "auto_pad": "VALID"}),
        (5, {"kernel_shape": [3, 3], "strides": [2, 2], "auto_pad": "SAME_UPPER"}),
        (6, {"kernel_shape": [2, 2], "strides": [2, 2], "ceil_mode": 1, "auto_pad": "SAME_LOWER"}),
    ],
)
def test_maxpool_output_shape_matches_onnxruntime(size, attrs):
    proto = one_op("MaxPool", [1, 2, size, size], opset=12, **attrs)
    graph = import_onnx(proto)
    node = only(graph)
    assert node.op == "MaxPool" and node.attrs.ceil_mode == bool(attrs.get("ceil_mode", 0))
    assert graph.shapes["y"] == ort_shape(proto)


def test_ceil_maxpool_shape_reaches_downstream_shapes_and_folding_in_old_opsets():
    # ONNX's MaxPool-12 inference says 3x3 here; the spec and onnxruntime say 2x2, and the Shape
    # chain and Gemm after it must see 2x2 too.
    nodes = [
        helper.make_node("MaxPool", ["x"], ["p"], kernel_shape=[2, 2], strides=[2, 2], pads=[0, 0, 1, 1], ceil_mode=1),
        helper.make_node("Shape", ["p"], ["s"]),
        helper.make_node("Gather", ["s", "zero"], ["n"], axis=0),
        helper.make_node("Unsqueeze", ["n"], ["n1"], axes=[0]),
        helper.make_node("Concat", ["n1", "minus1"], ["target"], axis=0),
        helper.make_node("Reshape", ["p", "target"], ["f"]),
        helper.make_node("Gemm", ["f", "B"], ["y"]),
    ]
    inits = {"zero": np.array(0, np.int64), "minus1": [-1], "B": rand(4, 3)}
    proto = onnx_model(nodes, inputs={"x": [1, 1, 4, 4]}, initializers=inits, opset=12)
    graph = import_onnx(proto)
    assert [n.op for n in graph.nodes] == ["MaxPool", "Reshape", "Dense"]
    assert graph.shapes["p"] == (1, 1, 2, 2) and graph.shapes["f"] == (1, 4)
    assert graph.shapes["y"] == ort_shape(proto) == (1, 3)


def test_maxpool_attrs_resolved():
    proto = one_op("MaxPool", [1, 2, 9, 9], kernel_shape=[3, 3], strides=[2, 2], auto_pad="SAME_LOWER", opset=12)
    node = only(import_onnx(proto))
    assert node.attrs == PoolAttrs((3, 3), (2, 2), (1, 1), pads_begin=(1, 1), pads_end=(1, 1), ceil_mode=False)


def test_maxpool_unused_indices_output_is_fine():
    proto = one_op("MaxPool", [1, 1, 4, 4], outputs=("y", "idx"), kernel_shape=[2, 2], opset=12)
    node = only(import_onnx(proto))
    assert node.outputs == ("y",)


def converter_context(shapes, used, opset=13):
    """A Context as the importer builds it, for reaching converter checks no valid float model can."""
    return Context(opset=opset, constants={}, shapes=shapes, used=set(used), taken=set())


def test_maxpool_used_indices_are_refused():
    node = helper.make_node("MaxPool", ["x"], ["y", "idx"], name="pool", kernel_shape=[2, 2])
    # Through import, Indices can only escape as an (int64) graph output, which is refused as such.
    proto = onnx_model(
        [node], inputs={"x": [1, 1, 4, 4]}, outputs={"y": None, "idx": value("idx", None, TensorProto.INT64)}, opset=12
    )
    fails(proto, "output 'idx' is int64")
    ctx = converter_context({"x": (1, 1, 4, 4)}, used={"idx"})
    with pytest.raises(NncgError, match="MaxPool 'pool' has its Indices output 'idx' used"):
        convert_maxpool(OnnxOp.of(node, "pool"), ctx)


def test_maxpool_storage_order_is_refused():
    node = helper.make_node("MaxPool", ["x"], ["y"], name="pool", kernel_shape=[2, 2], storage_order=1)
    fails(onnx_model([node], inputs={"x": [1, 1, 4, 4]}, opset=12), "MaxPool 'pool'", "storage_order")


# --- activations, BatchNormalization, Softmax ----------------------------------------------------


def test_relu_and_leaky_relu():
    nodes = [
        helper.make_node("Relu", ["x"], ["a"]),
        helper.make_node("LeakyRelu", ["a"], ["b"]),
        helper.make_node("LeakyRelu", ["b"], ["y"], alpha=0.25),
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [1, 2]}))
    assert [(n.op, n.attrs) for n in graph.nodes] == [
        ("Relu", Activation("relu")),
        ("LeakyRelu", Activation("leaky_relu", pytest.approx(0.01))),
        ("LeakyRelu", Activation("leaky_relu", 0.25)),
    ]


def bn_model(opset, outputs=("y",), params_dtype=np.float32, **attrs):
    names = ["scale", "bias", "mean", "var"]
    inits = {n: (np.abs(rand(3)) + 0.1).astype(params_dtype) for n in names}
    node = helper.make_node("BatchNormalization", ["x", *names], list(outputs), name="bn", **attrs)
    return onnx_model([node], inputs={"x": [1, 3, 4, 4]}, outputs=outputs, initializers=inits, opset=opset)


@pytest.mark.parametrize(("opset", "attrs"), [(7, {"spatial": 1}), (9, {}), (15, {"training_mode": 0})])
def test_batchnorm(opset, attrs):
    graph = import_onnx(bn_model(opset, epsilon=1e-3, **attrs))
    node = only(graph)
    assert node.op == "BatchNormalization"
    assert node.inputs == ("x", "scale", "bias", "mean", "var")
    assert node.attrs == BatchNormAttrs(epsilon=pytest.approx(1e-3))
    assert graph.shapes["y"] == (1, 3, 4, 4)


def test_batchnorm_default_epsilon_and_fp16_statistics_become_float32():
    graph = import_onnx(bn_model(15, params_dtype=np.float16))
    assert only(graph).attrs == BatchNormAttrs(1e-5)
    assert all(graph.constants[n].dtype == np.float32 for n in ("scale", "bias", "mean", "var"))


def test_batchnorm_training_mode_is_refused():
    proto = bn_model(15, outputs=("y", "rm", "rv"), training_mode=1)
    del proto.graph.output[1:]
    fails(proto, "BatchNormalization 'bn'", "training_mode=1")


def test_batchnorm_extra_outputs_must_be_unused():
    proto = bn_model(9, outputs=("y", "run_mean", "run_var", "saved_mean", "saved_var"))
    del proto.graph.output[1:]
    proto.graph.output.append(value("run_mean", [3]))
    fails(proto, "BatchNormalization 'bn'", "'run_mean'")


def test_batchnorm_spatial_0_is_refused():
    fails(bn_model(7, spatial=0), "BatchNormalization 'bn'", "spatial=0")


@pytest.mark.parametrize(
    ("opset", "attrs", "expected"),
    [
        (11, {}, SoftmaxAttrs(axis=1, coerce_2d=True)),
        (11, {"axis": -1}, SoftmaxAttrs(axis=2, coerce_2d=True)),
        (13, {}, SoftmaxAttrs(axis=2, coerce_2d=False)),
        (13, {"axis": -2}, SoftmaxAttrs(axis=1, coerce_2d=False)),
        (13, {"axis": 0}, SoftmaxAttrs(axis=0, coerce_2d=False)),
    ],
)
def test_softmax_axis_per_opset(opset, attrs, expected):
    node = only(import_onnx(one_op("Softmax", [2, 3, 4], opset=opset, **attrs)))
    assert (node.op, node.attrs) == ("Softmax", expected)


# --- Dropout, Identity, and the Reshape family ---------------------------------------------------


@pytest.mark.parametrize("opset", [7, 10, 13])
def test_dropout_becomes_identity(opset):
    if opset < 12:
        node = helper.make_node("Dropout", ["x"], ["y"], name="drop", ratio=0.3)
        inits = {}
    else:
        node = helper.make_node("Dropout", ["x", "ratio", "mode"], ["y"], name="drop")
        inits = {"ratio": np.array(0.3, np.float32), "mode": np.array(False)}
    graph = import_onnx(onnx_model([node], inputs={"x": [1, 4]}, initializers=inits, opset=opset))
    assert only(graph) == Node("Identity", "drop", ("x",), ("y",))


def test_dropout_unused_mask_is_fine_but_a_used_one_is_refused():
    node = helper.make_node("Dropout", ["x"], ["y", "mask"], name="drop")
    assert only(import_onnx(onnx_model([node], inputs={"x": [1, 4]}))).outputs == ("y",)
    ctx = converter_context({"x": (1, 4)}, used={"mask"})
    with pytest.raises(NncgError, match="Dropout 'drop' has its mask output 'mask' used"):
        convert_dropout(OnnxOp.of(node, "drop"), ctx)


def test_dropout_training_mode_is_refused():
    node = helper.make_node("Dropout", ["x", "", "mode"], ["y"], name="drop")
    proto = onnx_model([node], inputs={"x": [1, 4]}, initializers={"mode": np.array(True)})
    fails(proto, "Dropout 'drop'", "training_mode")


def test_identity():
    assert only(import_onnx(one_op("Identity", [1, 4]))) == Node("Identity", "Identity_0", ("x",), ("y",))


@pytest.mark.parametrize(
    ("target", "expected", "opset", "attrs"),
    [
        ([0, -1], (2, 12), 13, {}),
        ([-1, 0, 2], (4, 3, 2), 13, {}),
        ([4, 6], (4, 6), 14, {"allowzero": 1}),
        ([0, 0, 4], (2, 3, 4), 7, {}),
    ],
)
def test_reshape_zero_and_minus_one(target, expected, opset, attrs):
    proto = one_op("Reshape", [2, 3, 4], extra_inputs=["t"], inits={"t": target}, opset=opset, **attrs)
    graph = import_onnx(proto)
    assert only(graph) == Node("Reshape", "Reshape_0", ("x",), ("y",), ReshapeAttrs(expected))
    assert graph.shapes["y"] == expected == ort_shape(proto)


@pytest.mark.parametrize(
    ("axis", "expected"), [(None, (2, 12)), (0, (1, 24)), (-1, (6, 4)), (-3, (1, 24)), (3, (24, 1))]
)
def test_flatten_axis(axis, expected):
    attrs = {} if axis is None else {"axis": axis}
    proto = one_op("Flatten", [2, 3, 4], opset=13, **attrs)
    assert only(import_onnx(proto)).attrs == ReshapeAttrs(expected)
    assert ort_shape(proto) == expected


def axes_model(op, in_shape, axes, opset):
    if axes is not None and opset >= 13:
        return one_op(op, in_shape, extra_inputs=["axes"], inits={"axes": axes}, opset=opset)
    attrs = {} if axes is None else {"axes": axes}
    return one_op(op, in_shape, opset=opset, **attrs)


@pytest.mark.parametrize("opset", [11, 13])
@pytest.mark.parametrize(
    ("in_shape", "axes", "expected"),
    [([1, 3, 1, 2], [0, 2], (3, 2)), ([1, 3, 1, 2], [-2], (1, 3, 2)), ([1, 3, 1, 2], None, (3, 2))],
)
def test_squeeze(opset, in_shape, axes, expected):
    proto = axes_model("Squeeze", in_shape, axes, opset)
    graph = import_onnx(proto)
    assert only(graph) == Node("Reshape", "Squeeze_0", ("x",), ("y",), ReshapeAttrs(expected))
    assert ort_shape(proto) == expected


@pytest.mark.parametrize("opset", [11, 13])
@pytest.mark.parametrize(
    ("in_shape", "axes", "expected"),
    [([3, 2], [0, 3], (1, 3, 2, 1)), ([3, 2], [-1], (3, 2, 1)), ([3, 2], [1, -4], (1, 1, 3, 2))],
)
def test_unsqueeze(opset, in_shape, axes, expected):
    proto = axes_model("Unsqueeze", in_shape, axes, opset)
    graph = import_onnx(proto)
    assert only(graph) == Node("Reshape", "Unsqueeze_0", ("x",), ("y",), ReshapeAttrs(expected))
    assert ort_shape(proto) == expected


# --- Gemm, MatMul, elementwise -------------------------------------------------------------------


def dense_reference(graph: Graph, x: np.ndarray) -> np.ndarray:
    """What the IR Dense node means: rows of x (or x.T) times w plus b."""
    node = only(graph)
    w = graph.constants[node.inputs[1]]
    rows = x.T if node.attrs.trans_x else x
    y = rows @ w
    return y + graph.constants[node.inputs[2]] if len(node.inputs) == 3 else y


@pytest.mark.parametrize(
    ("alpha", "beta", "trans_a", "trans_b", "c_shape"),
    [
        (1.0, 1.0, 0, 0, (5,)),
        (0.5, 2.0, 0, 1, (1, 5)),
        (2.0, 0.5, 1, 0, ()),
        (1.5, 1.0, 1, 1, (3, 5)),  # same row repeated: allowed
        (1.0, 1.0, 0, 1, None),
        (1.0, 0.0, 0, 0, (5,)),  # beta 0 drops C
    ],
)
def test_gemm_folds_alpha_beta_trans_into_w_and_b(alpha, beta, trans_a, trans_b, c_shape):
    m, k, n = 3, 4, 5
    a_shape = [k, m] if trans_a else [m, k]
    b = rand(n, k) if trans_b else rand(k, n)
    inputs, inits = ["x", "B"], {"B": b}
    if c_shape is not None:
        c = np.broadcast_to(rand(n), (m, n)).copy() if c_shape == (m, n) else rand(*c_shape)
        inputs.append("C")
        inits["C"] = c
    attrs = {"alpha": alpha, "beta": beta, "transA": trans_a, "transB": trans_b}
    node = helper.make_node("Gemm", inputs, ["y"], name="fc", **attrs)
    proto = onnx_model([node], inputs={"x": a_shape}, initializers=inits)
    graph = import_onnx(proto)
    dense = only(graph)
    has_bias = c_shape is not None and beta != 0
    assert dense.op == "Dense" and dense.attrs == DenseAttrs(trans_x=bool(trans_a))
    assert dense.inputs[:2] == ("x", "fc_w") and len(dense.inputs) == 2 + has_bias
    assert graph.constants["fc_w"].shape == (k, n) and graph.constants["fc_w"].dtype == np.float32
    if has_bias:
        assert graph.constants[dense.inputs[2]].shape == (n,)
    x = rand(*a_shape)
    expected = alpha * (x.T if trans_a else x) @ (b.T if trans_b else b)
    if c_shape is not None:
        expected = expected + beta * c
    np.testing.assert_allclose(dense_reference(graph, x), expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dense_reference(graph, x), run_ort(proto, {"x": x})[0], rtol=1e-5, atol=1e-5)
    assert graph.shapes["y"] == (m, n)


def test_gemm_opset_7_with_required_c():
    node = helper.make_node("Gemm", ["x", "B", "C"], ["y"], transB=1)
    proto = onnx_model([node], inputs={"x": [2, 3]}, initializers={"B": rand(4, 3), "C": rand(4)}, opset=7)
    x = rand(2, 3)
    np.testing.assert_allclose(dense_reference(import_onnx(proto), x), run_ort(proto, {"x": x})[0], rtol=1e-5)


def test_gemm_c_with_distinct_rows_is_refused():
    node = helper.make_node("Gemm", ["x", "B", "C"], ["y"], name="fc")
    proto = onnx_model([node], inputs={"x": [2, 3]}, initializers={"B": rand(3, 4), "C": rand(2, 4)})
    fails(proto, "Gemm 'fc'", "different rows")


def test_gemm_new_constant_names_do_not_collide():
    node = helper.make_node("Gemm", ["x", "fc_w"], ["y"], name="fc")
    graph = import_onnx(onnx_model([node], inputs={"x": [2, 3]}, initializers={"fc_w": rand(3, 4)}))
    assert only(graph).inputs == ("x", "fc_w_1")


def test_gemm_runtime_b_keeps_trans_b_and_alpha():
    node = helper.make_node("Gemm", ["x", "w"], ["y"], name="fc", transB=1, alpha=0.5)
    graph = import_onnx(onnx_model([node], inputs={"x": [2, 3], "w": [4, 3]}))
    assert only(graph) == Node("Dense", "fc", ("x", "w"), ("y",), DenseAttrs(trans_w=True, alpha=0.5))


def test_matmul_becomes_dense_without_bias():
    node = helper.make_node("MatMul", ["x", "W"], ["y"], name="mm")
    w = rand(4, 5)
    proto = onnx_model([node], inputs={"x": [2, 3, 4]}, initializers={"W": w})
    graph = import_onnx(proto)
    assert only(graph) == Node("Dense", "mm", ("x", "W"), ("y",), DenseAttrs())
    assert graph.shapes["y"] == (2, 3, 5)
    x = rand(2, 3, 4)
    np.testing.assert_allclose(x @ graph.constants["W"], run_ort(proto, {"x": x})[0], rtol=1e-5)


@pytest.mark.parametrize("op", ["Add", "Sub", "Mul", "Div"])
def test_elementwise_ops_keep_both_inputs(op):
    nodes = [
        helper.make_node(op, ["c", "x"], ["t"], name="first"),  # constant on the left
        helper.make_node(op, ["t", "x"], ["y"], name="second"),  # both at runtime
    ]
    graph = import_onnx(onnx_model(nodes, inputs={"x": [2, 3]}, initializers={"c": rand(3)}))
    assert graph.nodes == (Node(op, "first", ("c", "x"), ("t",)), Node(op, "second", ("t", "x"), ("y",)))
    assert graph.shapes["t"] == (2, 3) and graph.constants["c"].shape == (3,)


# --- malformed graphs: messages that name what is wrong -------------------------------------------


def test_value_with_two_sources_is_refused():
    nodes = [helper.make_node("Relu", ["x"], ["x"], name="loop")]
    fails(onnx_model(nodes, inputs={"x": [1, 2]}, outputs={"x": None}), "value 'x' is both a graph input and", "'loop'")


def test_three_node_cycle_names_every_node():
    nodes = [
        helper.make_node("Relu", ["x"], ["r"], name="entry"),
        helper.make_node("Add", ["r", "c"], ["a"], name="first"),
        helper.make_node("Sigmoid", ["a"], ["b"], name="second"),
        helper.make_node("Tanh", ["b"], ["c"], name="third"),
    ]
    message = fails(onnx_model(nodes, inputs={"x": [1, 2]}, outputs={"a": None}), "cycle")
    assert "'entry'" not in message  # not on the cycle
    for part in ("Add node 'first' reads 'c' from Tanh node 'third'", "reads 'b' from Sigmoid node 'second'"):
        assert part in message


def test_node_reading_its_own_output_is_a_cycle():
    nodes = [helper.make_node("Add", ["x", "y"], ["y"], name="self")]
    fails(onnx_model(nodes, inputs={"x": [1, 2]}), "cycle", "Add node 'self' reads 'y' from Add node 'self'")


def test_operator_newer_than_the_models_opset_is_named():
    proto = one_op("Gelu", [1, 4], opset=13)
    fails(proto, "opset 13 does not have", "Gelu (node 'Gelu_0')", error=UnsupportedOpsError)
    proto = one_op("Upsample", [1, 1, 2, 2], extra_inputs=["s"], inits={"s": np.ones(4, np.float32)}, opset=10)
    fails(proto, "deprecated", "Upsample (node 'Upsample_0')", "Resize", error=UnsupportedOpsError)


def test_input_without_type_and_negative_declared_dim():
    proto = one_op("Relu", [1, 4])
    proto.graph.input[0].ClearField("type")
    fails(proto, "graph input 'x' has no type")
    proto = one_op("Relu", [1, 4])
    proto.graph.input[0].type.tensor_type.shape.dim[1].dim_value = -4
    fails(proto, "input 'x' has a dimension below 1", "empty tensors")


def test_negative_output_dims_name_the_node_and_its_input_shapes():
    proto = conv_model(x_shape=(1, 2, 4, 4), w_shape=(3, 2, 5, 5), bias=False)
    fails(proto, "Conv node 'conv'", "[1, 3, 0, 0]")  # a 5x5 kernel on 4x4: empty, not negative
    proto = conv_model(x_shape=(1, 2, 4, 4), w_shape=(3, 2, 6, 6), bias=False)
    fails(proto, "Conv node 'conv'", "[1, 3, -1, -1]", "'x' [1, 2, 4, 4], 'w' [3, 2, 6, 6]")


def test_sparse_constant_too_large_to_make_dense_is_refused_before_allocating():
    sparse = helper.make_sparse_tensor(const("sv", np.array([1.0], np.float32)), const("si", [5]), [100000, 100000])
    nodes = [
        helper.make_node("Constant", [], ["c"], sparse_value=sparse),
        helper.make_node("ReduceSum", ["c"], ["r"], keepdims=0),
        helper.make_node("Add", ["x", "r"], ["y"]),
    ]
    proto = onnx_model(nodes, inputs={"x": [1]})
    fails(proto, "sparse tensor 'sv'", "10,000,000,000 elements", "MAX_FOLDED_ELEMENTS")


def test_fold_cap_uses_the_nodes_own_shape_inference_when_the_model_has_none(monkeypatch):
    from nncg.frontend import folding

    monkeypatch.setattr(folding, "_evaluate", lambda *args: pytest.fail("the node was evaluated"))
    node = helper.make_node("ConstantOfShape", ["s"], ["c"], name="big")
    add = helper.make_node("Add", ["x", "c"], ["y"])
    proto = onnx_model([node, add], inputs={"x": [1]}, initializers={"s": np.array([20000, 20000], np.int64)})
    with pytest.raises(NncgError, match=r"ConstantOfShape node 'big' would fold to a constant 'c' of shape \[20000"):
        folding.fold_constants(proto, shapes={})  # no whole-model shapes: the node's own inference


def test_infinite_weights_are_kept():
    w = np.array([np.inf, -np.inf], np.float32)
    proto = onnx_model([helper.make_node("Add", ["x", "w"], ["y"])], inputs={"x": [1, 2]}, initializers={"w": w})
    np.testing.assert_array_equal(import_onnx(proto).constants["w"], np.array([np.inf, -np.inf], np.float32))


def test_outside_names_are_escaped_and_capped_in_messages():
    name = "evil\n\x1b[31mred" + "x" * 200
    nodes = [helper.make_node("Reshape", ["x", "s"], ["y"], name=name)]
    proto = onnx_model(nodes, inputs={"x": [1, 12]}, initializers={"s": np.array([5, 5], np.int64)})
    message = fails(proto, "Reshape 'evil\\n\\x1b[31mred", "12 elements", "25 elements")
    assert "\x1b" not in message and "x" * 100 not in message


@pytest.mark.parametrize("import_domain", ["ai.onnx", ""])
def test_ai_onnx_is_the_default_domain(import_domain):
    """onnx's checker knows ONNX's operators only under "": the alias is normalised."""
    proto = one_op("Relu", [1, 2])
    proto.graph.node[0].domain = "ai.onnx"
    proto.opset_import[0].domain = import_domain
    assert only(import_onnx(proto)).op == "Relu"


@pytest.mark.parametrize(
    ("op", "attrs", "field"),
    [("LeakyRelu", {"alpha": float("nan")}, "alpha"), ("Clip", {"min": float("nan")}, "low")],
)
def test_nan_parameters_are_refused_naming_the_node(op, attrs, field):
    fails(one_op(op, [1, 4], opset=10, **attrs), f"{op} node '{op}_0' has {field} NaN")
