"""ONNX front end (ONNX -> graph IR): the driver. Loads and validates the model, folds constants,
converts every remaining node and assembles the graph IR with static shapes and float32 constants.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np
import onnx
from onnx.helper import tensor_dtype_to_np_dtype

from nncg.errors import NncgError, UnsupportedOpsError
from nncg.frontend.checks import check_attributes, check_computed_shapes, check_constants, constant_origins
from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.folding import Folded, NamedNode, fold_constants
from nncg.frontend.load import ModelSource, load_with_shapes, opset_version, real_inputs
from nncg.frontend.names import node_reads, value_names
from nncg.frontend.ops import CONVERTERS, FOLDED_OPS, SUPPORTED_OPS
from nncg.frontend.ops_integer import INT32_RESULT
from nncg.frontend.qdq import NNCG_DOMAIN, QdqNotes, fuse_qdq
from nncg.ir.c_names import Namespace, layer_name
from nncg.ir.graph import Graph, Node, Value
from nncg.ir.graph_dtypes import (
    INTEGER_PRODUCTS,
    QUANTIZED_INPUTS,
    TYPE_PRESERVING,
    float_ops_reading_integers,
    output_dtype,
)
from nncg.ir.kinds import DType
from nncg.safe_text import shown


def import_onnx(model: ModelSource, input_shapes: Mapping[str, tuple[int, ...]] | None = None) -> Graph:
    """The graph IR of an ONNX model (path, bytes, ModelProto or load_model's result)."""
    proto, shapes = load_with_shapes(model, input_shapes)
    folded = fold_constants(proto, shapes)
    nodes, notes = fuse_qdq(folded, [v.name for v in proto.graph.output])
    folded = replace(folded, nodes=nodes)
    check_supported(folded.nodes)
    ctx = _context(proto, folded, notes)
    computed = [(name, node.op_type, node.output) for node, name in folded.nodes]
    check_computed_shapes(computed, ctx.shapes, ctx.is_used)  # before converters size anything by them
    nodes = tuple(ir_node for node, name in folded.nodes for ir_node in _converted(OnnxOp.of(node, name), ctx))
    graph = _assemble(proto.graph, nodes, ctx)
    check_computed_shapes([(n.name, n.op, n.outputs) for n in graph.nodes], graph.shapes)  # converters' own too
    check_constants(graph, constant_origins(proto.graph, folded))
    check_integer_reads(graph)
    check_attributes(graph)
    return graph


DYNAMIC_QUANTIZATION = "DynamicQuantizeLinear"


def check_supported(nodes: list[NamedNode]) -> None:
    """One error listing every node left after folding that has no converter."""
    bad = [f"{_op_type(node)} (node {shown(name)})" for node, name in nodes if node.op_type not in CONVERTERS]
    types = {node.op_type for node, _ in nodes}
    if DYNAMIC_QUANTIZATION in types:
        raise UnsupportedOpsError(
            "the model is dynamically quantised (DynamicQuantizeLinear computes scales at run time), which "
            "NNCG does not compile: compile the float model instead"
        )
    # an int32 result that qdq.py left unfused may be a graph output, but not in memory for a reader
    read = {i for node, _ in nodes for i in node.input}
    int32_read = [
        (node, name)
        for node, name in nodes
        if node.op_type in INTEGER_PRODUCTS and node.domain != NNCG_DOMAIN and node.output[0] in read
    ]
    if int32_read:
        node, name = int32_read[0]
        raise UnsupportedOpsError(f"{node.op_type} (node {shown(name)}) {INT32_RESULT}")
    if bad:
        raise UnsupportedOpsError(
            f"unsupported operators: {', '.join(bad)}; NNCG supports {', '.join(SUPPORTED_OPS)} "
            f"(plus {FOLDED_OPS}, which are folded at compile time)"
        )


def check_integer_reads(graph: Graph) -> None:
    """A float op that reads an int8 tensor directly (a QOperator model's Transpose of uint8, say) is
    refused: NNCG computes only its int8 ops on integers, and nothing quantized in float."""
    found = float_ops_reading_integers(graph)
    if found:
        node, value = found[0]
        raise UnsupportedOpsError(
            f"{node.op} node {shown(node.name)} reads the {graph.dtype(value)} tensor {shown(value)}; NNCG computes "
            "that op in float only: dequantize its input (DequantizeLinear) or compile the float model"
        )


def _op_type(node: onnx.NodeProto) -> str:
    return node.op_type if node.op_type.isidentifier() and node.op_type.isascii() else shown(node.op_type)


def _converted(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    """The IR nodes of one ONNX op (a converter yields one, or a few computing it in steps)."""
    converted = CONVERTERS[op.type](op, ctx)
    return converted if isinstance(converted, tuple) else (converted,)


def _context(model: onnx.ModelProto, folded: Folded, notes: QdqNotes) -> Context:
    used = {i for node, _ in folded.nodes for i in node_reads(node)}
    used |= {v.name for v in model.graph.output}
    return Context(
        opset=opset_version(model),
        constants=dict(folded.constants),
        shapes=dict(folded.shapes),
        used=used,
        taken=value_names(model.graph) | set(folded.constants),
        output_ranges=notes.output_ranges,
        uint8_pools=notes.uint8_pools,
    )


def _assemble(graph: onnx.GraphProto, nodes: tuple[Node, ...], ctx: Context) -> Graph:
    inputs = tuple(Value(v.name, _static_shape(ctx, v.name, "input")) for v in real_inputs(graph))
    outputs = tuple(Value(v.name, _static_shape(ctx, v.name, "output")) for v in graph.output)
    shapes = {v.name: v.shape for v in (*inputs, *outputs)}
    for node in nodes:
        for output in node.outputs:
            shapes[output] = _static_shape(ctx, output, f"output of {node.op} node {shown(node.name)}")
    constants = {}
    for node in nodes:
        for name in node.inputs:
            if name in ctx.constants:
                array = ctx.constants[name]
                moved = node.op in TYPE_PRESERVING and array.dtype in (np.int8, np.uint8)  # a QLinearConcat's
                constants[name] = (
                    np.ascontiguousarray(array) if node.op in QUANTIZED_INPUTS or moved else _float32(node, name, array)
                )
    dtypes = _dtypes(graph, nodes, constants)
    return Graph(graph.name or "model", inputs, outputs, _layer_named(nodes), constants, shapes, dtypes)


def _dtypes(graph: onnx.GraphProto, nodes: tuple[Node, ...], constants: dict[str, np.ndarray]) -> dict:
    """The dtype of every graph input and computed value that is not float32: an input's as
    declared, a computed value's from its producer."""
    declared = {v.name: tensor_dtype_to_np_dtype(v.type.tensor_type.elem_type).name for v in real_inputs(graph)}
    dtypes = {name: DType(dtype) for name, dtype in declared.items() if dtype != "float32"}

    def dtype_of(name: str) -> DType:
        return DType(constants[name].dtype.name) if name in constants else dtypes.get(name, DType.FLOAT32)

    for node in nodes:
        dtype = output_dtype(node, dtype_of)
        dtypes.update(dict.fromkeys(node.outputs, dtype) if dtype != DType.FLOAT32 else {})
    return dtypes


def _layer_named(nodes: tuple[Node, ...]) -> tuple[Node, ...]:
    """Nodes renamed to their layers' C names (unique, ignoring case): the one identity a layer has
    from here on, in pass parameters (`layers=`), kernels, the profile and --tune's choices."""
    names = Namespace(layer_name)
    return tuple(replace(node, name=names.claim(node.name)) for node in nodes)


def _static_shape(ctx: Context, value: str, role: str) -> tuple[int, ...]:
    if value not in ctx.shapes:
        raise NncgError(
            f"no static shape could be inferred for {shown(value)} ({role}); fix the input shapes "
            "or simplify the model (e.g. with onnxsim)"
        )
    return ctx.shapes[value]


def _float32(node: Node, name: str, array: np.ndarray) -> np.ndarray:
    """Weights fed to IR ops as float32; other float types (e.g. fp16 BN statistics) are widened."""
    if array.dtype == np.float32:
        return np.ascontiguousarray(array)
    if "float" not in array.dtype.name:
        raise NncgError(
            f"{node.op} node {shown(node.name)} reads constant {shown(name)} of type {array.dtype.name}; "
            "NNCG needs float32 weights: re-export the model in float32"
        )
    return np.ascontiguousarray(array.astype(np.float32))
