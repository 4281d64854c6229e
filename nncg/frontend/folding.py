"""ONNX front end (ONNX -> graph IR), step 2: constant folding. Evaluates every node computable at
compile time (Constant, Shape/Size of static shapes, any node with only constant inputs).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import onnx
from onnx import helper, numpy_helper
from onnx.reference import ReferenceEvaluator

from nncg.errors import NncgError
from nncg.frontend.load import opset_version, real_inputs
from nncg.frontend.names import node_names, node_reads
from nncg.frontend.shapes import inferred_shapes, one_line, static_shapes
from nncg.ir.graph import Shape
from nncg.safe_text import shown

# Folding evaluates constant subgraphs with numpy at compile time, so it could be made to allocate
# any amount of memory: a 231-byte model with ConstantOfShape([28000, 28000]) asks for 3 GB. No real
# CNN folds anything near this many elements (VGG's largest weight, 103M floats, fits); a node whose
# result would be larger is refused before it is evaluated.
MAX_FOLDED_ELEMENTS = 2**27
FOLD_CAP = f"{MAX_FOLDED_ELEMENTS:,} elements (nncg.frontend.folding.MAX_FOLDED_ELEMENTS)"
SMALL_CONSTANT = 16  # constant inputs up to this many elements are quoted in messages, and their
# values fed to ONNX shape inference when it has to find a node's output shape alone

# Folding these would freeze one random draw into the compiled model.
NONDETERMINISTIC = {
    "RandomNormal",
    "RandomUniform",
    "RandomNormalLike",
    "RandomUniformLike",
    "Multinomial",
    "Bernoulli",
}

# onnx's reference evaluator implements these ops only from the opset given; the earlier versions
# are subsets of it (opset 19 added the float8 types, and 21 blocked scales, to (De)QuantizeLinear of 10
# and 13), so a node of an earlier opset folds as that one. tf2onnx writes opset-13 DequantizeLinear
# on the weights of models converted from TFLite, float models included.
REFERENCE_OPSET = {"DequantizeLinear": 19, "QuantizeLinear": 19}

NamedNode = tuple[onnx.NodeProto, str]


@dataclass
class Folded:
    """The live nodes left after folding (with their stable names), all constants, static shapes,
    for each folded constant the name of the node it was folded from, and for each constant folded
    from a DequantizeLinear that node (the int8 path reads the quantized weights from it)."""

    nodes: list[NamedNode]
    constants: dict[str, np.ndarray]
    shapes: dict[str, Shape]
    folded_by: dict[str, str]
    dequantized: dict[str, onnx.NodeProto] = field(default_factory=dict)


def fold_constants(model: onnx.ModelProto, shapes: dict[str, Shape]) -> Folded:
    """Fold until nothing changes; re-infer shapes in between since folding can make them static.

    `shapes` are the static shapes of the model as given (load_with_shapes).
    """
    opset = opset_version(model)
    outputs = [v.name for v in model.graph.output]
    constants = initializer_arrays(model.graph)
    nodes = live_nodes(list(zip(model.graph.node, node_names(model.graph), strict=True)), outputs)
    folded_by: dict[str, str] = {}
    dequantized: dict[str, onnx.NodeProto] = {}
    while True:
        remaining = [n for n in nodes if not _fold_node(n, constants, shapes, opset, folded_by)]
        dequantized.update(
            {n.output[0]: n for n, _ in nodes if n.op_type == "DequantizeLinear" and n.output[0] in constants}
        )
        _check_outputs_computed(outputs, constants)
        if len(remaining) == len(nodes):
            break
        nodes = live_nodes(remaining, outputs)
        shapes = inferred_shapes(_rebuild(model, nodes, constants))
    return Folded(nodes, constants, shapes, folded_by, dequantized)


def live_nodes(nodes: list[NamedNode], outputs: list[str]) -> list[NamedNode]:
    """Nodes the graph outputs depend on; dead branches need not be compiled (or supported)."""
    needed = set(outputs)
    live = []
    for node, name in reversed(nodes):
        if needed.intersection(node.output):
            live.append((node, name))
            needed |= node_reads(node)
    return live[::-1]


def initializer_arrays(graph: onnx.GraphProto) -> dict[str, np.ndarray]:
    arrays = {t.name: tensor_array(t) for t in graph.initializer}
    arrays.update({t.values.name: sparse_array(t) for t in graph.sparse_initializer})
    return arrays


def tensor_array(tensor: onnx.TensorProto) -> np.ndarray:
    try:
        return numpy_helper.to_array(tensor)
    except Exception as exc:  # e.g. raw_data shorter than dims say
        raise _corrupt(tensor.name, exc) from None


def sparse_array(sparse: onnx.SparseTensorProto) -> np.ndarray:
    """Dense copy of a sparse tensor; indices are either linear [NNZ] or coordinates [NNZ, rank]."""
    values, indices = tensor_array(sparse.values), tensor_array(sparse.indices)
    dims = tuple(int(d) for d in sparse.dims)
    elements = math.prod(dims)
    if min(dims, default=0) < 0 or elements > MAX_FOLDED_ELEMENTS:
        raise NncgError(
            f"sparse tensor {shown(sparse.values.name)} has dims {list(dims)}: made dense it would have "
            f"{elements:,} elements, more than the {FOLD_CAP} NNCG materialises; the model is damaged or "
            "not a CNN NNCG can compile: fix its dims"
        )
    try:
        dense = np.zeros(elements, dtype=values.dtype)
        flat = indices if indices.ndim == 1 else np.ravel_multi_index(tuple(indices.T), dims)
        dense[flat] = values
    except (IndexError, ValueError) as exc:  # indices outside the dims, or not matching the values
        raise _corrupt(sparse.values.name, exc) from None
    return dense.reshape(dims)


def _corrupt(name: str, exc: BaseException) -> NncgError:
    return NncgError(f"tensor {shown(name)} is corrupt ({one_line(exc, 120)}); the model file is damaged: re-export it")


def constant_value(node: onnx.NodeProto) -> np.ndarray:
    """The value of a Constant node, whichever of its value_* attributes holds it."""
    attr = node.attribute[0]  # the checker guarantees exactly one
    if attr.name == "value":
        return tensor_array(attr.t)
    if attr.name == "sparse_value":
        return sparse_array(attr.sparse_tensor)
    simple = {
        "value_float": lambda: np.array(attr.f, dtype=np.float32),
        "value_floats": lambda: np.array(list(attr.floats), dtype=np.float32),
        "value_int": lambda: np.array(attr.i, dtype=np.int64),
        "value_ints": lambda: np.array(list(attr.ints), dtype=np.int64),
        "value_string": lambda: np.array(attr.s.decode(), dtype=object),
        "value_strings": lambda: np.array([s.decode() for s in attr.strings], dtype=object),
    }
    if attr.name not in simple:
        raise NncgError(
            f"Constant node {shown(node.name)} has unknown attribute {shown(attr.name)}; give it one of value, "
            "value_float(s), value_int(s), value_string(s) or sparse_value, or re-export the model"
        )
    return simple[attr.name]()


# --- one node ------------------------------------------------------------------------------------


def _fold_node(named: NamedNode, constants: dict, shapes: dict[str, Shape], opset: int, folded_by: dict) -> bool:
    """Store the node's outputs in `constants` if they are computable now; says whether it folded."""
    node, name = named
    values = _node_values(node, name, constants, shapes, opset)
    if values is None:
        return False
    for output, value in zip(node.output, values, strict=True):
        if output:
            constants[output] = value
            folded_by[output] = name
    return True


def _node_values(node, name, constants, shapes, opset) -> list[np.ndarray] | None:
    if node.op_type == "Constant":
        return [constant_value(node)]
    inputs = [i for i in node.input if i]
    if node.op_type in ("Shape", "Size") and inputs[0] not in constants and inputs[0] in shapes:
        return [_shape_value(node, shapes[inputs[0]])]
    if any(i not in constants for i in inputs) or node.op_type in NONDETERMINISTIC:
        return None
    if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS) for a in node.attribute):
        return None  # subgraphs may read outer values that a one-node model would not have
    for output, shape in _output_shapes(node, constants, shapes, opset).items():
        if shape is not None:
            _check_fold_size(node, name, output, shape, constants)
    values = _evaluate(node, name, constants, opset)
    for output, value in zip(node.output, values or (), strict=False):
        if value is not None:  # inference did not know the shape: too late not to allocate, still refused
            _check_fold_size(node, name, output, value.shape, constants)
    return values


def _output_shapes(node, constants: dict, shapes: dict[str, Shape], opset: int) -> dict[str, Shape | None]:
    """The shapes of the node's outputs: from the whole model's inference, else from inferring the
    node alone with its small constant inputs' values known (None where ONNX cannot tell)."""
    outputs = [o for o in node.output if o]
    if all(o in shapes for o in outputs):
        return {o: shapes[o] for o in outputs}
    feeds = {i: constants[i] for i in dict.fromkeys(node.input) if i}
    small = [numpy_helper.from_array(a, i) for i, a in feeds.items() if a.size <= SMALL_CONSTANT and a.dtype != object]
    graph = helper.make_graph(
        [node],
        "fold_shapes",
        [helper.make_tensor_value_info(i, _elem_type(a), a.shape) for i, a in feeds.items()],
        [onnx.ValueInfoProto(name=o) for o in outputs],
        initializer=small,
    )
    try:
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
        inferred = onnx.shape_inference.infer_shapes(model, data_prop=True)
    except Exception:  # evaluating the node will report what is wrong with it
        return dict.fromkeys(outputs)
    found = static_shapes(inferred)
    return {o: found.get(o) for o in outputs}


def _check_fold_size(node, name: str, output: str, shape: Shape, constants: dict) -> None:
    elements = math.prod(shape)
    if elements <= MAX_FOLDED_ELEMENTS:
        return
    inputs = [
        f"{shown(i)} = {np.asarray(constants[i]).tolist()}"
        for i in node.input
        if i in constants and constants[i].size <= SMALL_CONSTANT and constants[i].dtype != object
    ]
    given = f" (from {', '.join(inputs)})" if inputs else ""
    raise NncgError(
        f"{node.op_type} node {shown(name)} would fold to a constant {shown(output)} of shape {list(shape)}{given}: "
        f"{elements:,} elements, more than the {FOLD_CAP} NNCG computes at compile time; no CNN needs a constant "
        "this large: check the node's inputs (a shape or size far too big?) and fix the model"
    )


def _shape_value(node: onnx.NodeProto, shape: Shape) -> np.ndarray:
    if node.op_type == "Size":
        return np.array(int(np.prod(shape)), dtype=np.int64)
    attrs = {a.name: a.i for a in node.attribute}
    # Python slicing clamps exactly like Shape's start/end (opset 15).
    return np.array(shape[attrs.get("start", 0) : attrs.get("end", len(shape))], dtype=np.int64)


def _evaluate(node: onnx.NodeProto, name: str, constants: dict, opset: int) -> list[np.ndarray] | None:
    """Run the node alone in onnx's reference evaluator on its constant inputs."""
    opset = max(opset, REFERENCE_OPSET.get(node.op_type, opset))
    feeds = {i: constants[i] for i in dict.fromkeys(node.input) if i}
    outputs = [o for o in node.output if o]
    try:
        graph = helper.make_graph(
            [node],
            f"fold_{name}",
            [helper.make_tensor_value_info(i, _elem_type(a), a.shape) for i, a in feeds.items()],
            [onnx.ValueInfoProto(name=o) for o in outputs],
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the result is checked (e.g. for NaN) where it is used
            results = ReferenceEvaluator(model).run(None, feeds)
    except Exception as exc:
        raise NncgError(
            f"cannot fold {node.op_type} node {shown(name)}, whose inputs are all constants: "
            f"{one_line(exc, 200)}; simplify the model (e.g. with onnxsim) and retry"
        ) from None
    if not all(isinstance(r, (np.ndarray, np.generic)) for r in results):
        return None  # sequences and optionals are not tensors the IR could hold
    by_name = dict(zip(outputs, (np.asarray(r) for r in results), strict=False))
    return [by_name.get(o) for o in node.output]


def _elem_type(array: np.ndarray) -> int:
    if array.dtype == object:
        return onnx.TensorProto.STRING
    return helper.np_dtype_to_tensor_dtype(array.dtype)


# --- whole graph ---------------------------------------------------------------------------------


def _rebuild(model: onnx.ModelProto, nodes: list[NamedNode], constants: dict) -> onnx.ModelProto:
    """The model with folded values as initializers, for another round of shape inference."""
    graph = model.graph
    read = dict.fromkeys(i for node, _ in nodes for i in sorted(node_reads(node)) if i in constants)
    read.update(dict.fromkeys(v.name for v in graph.output if v.name in constants))
    inputs = real_inputs(graph)
    new_graph = helper.make_graph(
        [node for node, _ in nodes],
        graph.name,
        inputs,
        list(graph.output),
        initializer=[numpy_helper.from_array(constants[n], n) for n in read],
    )
    # IR < 4 wants every initializer listed as an input too; a newer IR version avoids that.
    return helper.make_model(new_graph, opset_imports=list(model.opset_import), ir_version=max(model.ir_version, 4))


def _check_outputs_computed(outputs: list[str], constants: dict) -> None:
    for name in outputs:
        if name in constants:
            raise NncgError(
                f"graph output {shown(name)} is a constant (it does not depend on any input); "
                "NNCG compiles only outputs computed from the inputs: remove it from the outputs"
            )
