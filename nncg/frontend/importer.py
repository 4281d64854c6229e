"""ONNX front end (ONNX -> graph IR): the driver. Loads and validates the model, folds constants,
converts every remaining node and assembles the graph IR with static shapes and float32 constants.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np
import onnx

from nncg.errors import NncgError, UnsupportedOpsError
from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.folding import Folded, NamedNode, fold_constants
from nncg.frontend.load import ModelSource, load_with_shapes, opset_version, real_inputs
from nncg.frontend.names import node_reads, value_names
from nncg.frontend.ops import CONVERTERS, FOLDED_OPS, SUPPORTED_OPS
from nncg.ir.graph import Graph, Node, Value
from nncg.limits import check_tensor_size
from nncg.safe_text import shown


def import_onnx(model: ModelSource, input_shapes: Mapping[str, tuple[int, ...]] | None = None) -> Graph:
    """The graph IR of an ONNX model (path, bytes, ModelProto or load_model's result)."""
    proto, shapes = load_with_shapes(model, input_shapes)
    folded = fold_constants(proto, shapes)
    check_supported(folded.nodes)
    ctx = _context(proto, folded)
    computed = [(name, node.op_type, node.output) for node, name in folded.nodes]
    check_computed_shapes(computed, ctx.shapes, ctx.is_used)  # before converters size anything by them
    nodes = tuple(CONVERTERS[node.op_type](OnnxOp.of(node, name), ctx) for node, name in folded.nodes)
    graph = _assemble(proto.graph, nodes, ctx)
    check_computed_shapes([(n.name, n.op, n.outputs) for n in graph.nodes], graph.shapes)  # converters' own too
    check_constants(graph, _constant_origins(proto.graph, folded))
    check_attributes(graph)
    return graph


def check_supported(nodes: list[NamedNode]) -> None:
    """One error listing every node left after folding that has no converter."""
    bad = [f"{node.op_type} (node {shown(name)})" for node, name in nodes if node.op_type not in CONVERTERS]
    if bad:
        raise UnsupportedOpsError(
            f"unsupported operators: {', '.join(bad)}; NNCG supports {', '.join(SUPPORTED_OPS)} "
            f"(plus {FOLDED_OPS}, which are folded at compile time)"
        )


def check_computed_shapes(nodes: list[tuple[str, str, Sequence[str]]], shapes: dict, used=None) -> None:
    """Every tensor the C computes (outputs of the (name, op, outputs) nodes that `used` accepts and
    whose shape is known) has at least one element and fits int indexing (nncg.limits)."""
    for name, op, outputs in nodes:
        for output in outputs:
            if output not in shapes or (used is not None and not used(output)):
                continue
            shape = shapes[output]
            what = f"output {shown(output)} of {op} node {shown(name)}"
            if min(shape, default=1) < 1:
                raise NncgError(
                    f"{what} has the empty shape {list(shape)}; NNCG does not support empty tensors: "
                    "change the node's parameters so that every dimension is at least 1, or remove it"
                )
            check_tensor_size(what, shape)


def check_constants(graph: Graph, origins: dict[str, str]) -> None:
    """The weights the C holds are finite or infinite floats, never NaN (a NaN weight makes every
    output it reaches NaN; no trained model has one), and fit int indexing. `origins` says where
    each came from, for the message."""
    for name, array in graph.constants.items():
        what = origins.get(name, f"constant {shown(name)}")
        check_tensor_size(what, array.shape, "NNCG cannot compile weights this large")
        nan = np.isnan(array)
        if nan.any():
            first = [int(i) for i in np.argwhere(nan)[0]]
            raise NncgError(
                f"{what} holds NaN ({int(nan.sum()):,} of {array.size:,} values, the first at index {first}); "
                "NNCG refuses NaN weights: the model is damaged or its training diverged: replace them "
                "(e.g. numpy.nan_to_num on the tensor) and re-export"
            )


def check_attributes(graph: Graph) -> None:
    """No float attribute the C prints (alpha, clip bounds, pad value, epsilon, scales) is NaN."""
    for node in graph.nodes:
        if not dataclasses.is_dataclass(node.attrs):
            continue
        for field in dataclasses.fields(node.attrs):
            if any(math.isnan(v) for v in _floats(getattr(node.attrs, field.name))):
                raise NncgError(
                    f"{node.op} node {shown(node.name)} has {field.name} NaN; NNCG refuses NaN parameters, which "
                    "make every output they reach NaN: give it a number"
                )


def _floats(value: object):
    """The floats in an attribute value, nested tuples included."""
    if isinstance(value, float):
        yield value
    elif isinstance(value, tuple):
        for item in value:
            yield from _floats(item)


def _constant_origins(graph: onnx.GraphProto, folded: Folded) -> dict[str, str]:
    """How messages name each constant: as an initializer, or as the result of the node folded into it."""
    origins = {t.name: f"initializer {shown(t.name)}" for t in graph.initializer}
    origins |= {t.values.name: f"sparse initializer {shown(t.values.name)}" for t in graph.sparse_initializer}
    origins |= {
        value: f"constant {shown(value)} (computed at compile time by node {shown(node)})"
        for value, node in folded.folded_by.items()
    }
    return origins


def _context(model: onnx.ModelProto, folded: Folded) -> Context:
    used = {i for node, _ in folded.nodes for i in node_reads(node)}
    used |= {v.name for v in model.graph.output}
    return Context(
        opset=opset_version(model),
        constants=dict(folded.constants),
        shapes=dict(folded.shapes),
        used=used,
        taken=value_names(model.graph) | set(folded.constants),
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
                constants[name] = _float32(node, name, ctx.constants[name])
    return Graph(graph.name or "model", inputs, outputs, nodes, constants, shapes)


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
