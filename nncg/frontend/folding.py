"""ONNX front end (ONNX -> graph IR), step 2: constant folding. Evaluates every node computable at
compile time (Constant, Shape/Size of static shapes, any node with only constant inputs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import helper, numpy_helper
from onnx.reference import ReferenceEvaluator

from nncg.errors import NncgError
from nncg.frontend.load import opset_version, real_inputs
from nncg.frontend.names import node_names, node_reads
from nncg.frontend.shapes import inferred_shapes, one_line
from nncg.ir.graph import Shape

# Folding these would freeze one random draw into the compiled model.
NONDETERMINISTIC = {
    "RandomNormal",
    "RandomUniform",
    "RandomNormalLike",
    "RandomUniformLike",
    "Multinomial",
    "Bernoulli",
}

NamedNode = tuple[onnx.NodeProto, str]


@dataclass
class Folded:
    """The live nodes left after folding (with their stable names), all constants, static shapes."""

    nodes: list[NamedNode]
    constants: dict[str, np.ndarray]
    shapes: dict[str, Shape]


def fold_constants(model: onnx.ModelProto, shapes: dict[str, Shape]) -> Folded:
    """Fold until nothing changes; re-infer shapes in between since folding can make them static.

    `shapes` are the static shapes of the model as given (load_with_shapes).
    """
    opset = opset_version(model)
    outputs = [v.name for v in model.graph.output]
    constants = initializer_arrays(model.graph)
    nodes = live_nodes(list(zip(model.graph.node, node_names(model.graph), strict=True)), outputs)
    while True:
        remaining = [n for n in nodes if not _fold_node(n, constants, shapes, opset)]
        _check_outputs_computed(outputs, constants)
        if len(remaining) == len(nodes):
            break
        nodes = live_nodes(remaining, outputs)
        shapes = inferred_shapes(_rebuild(model, nodes, constants))
    return Folded(nodes, constants, shapes)


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
        raise NncgError(
            f"tensor '{tensor.name}' is corrupt ({one_line(exc, 120)}); the model file is damaged: re-export it"
        ) from None


def sparse_array(sparse: onnx.SparseTensorProto) -> np.ndarray:
    """Dense copy of a sparse tensor; indices are either linear [NNZ] or coordinates [NNZ, rank]."""
    values, indices = tensor_array(sparse.values), tensor_array(sparse.indices)
    dims = tuple(sparse.dims)
    dense = np.zeros(int(np.prod(dims)), dtype=values.dtype)
    flat = indices if indices.ndim == 1 else np.ravel_multi_index(tuple(indices.T), dims)
    dense[flat] = values
    return dense.reshape(dims)


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
        raise NncgError(f"Constant node '{node.name}' has unknown attribute '{attr.name}'; re-export the model")
    return simple[attr.name]()


# --- one node ------------------------------------------------------------------------------------


def _fold_node(named: NamedNode, constants: dict, shapes: dict[str, Shape], opset: int) -> bool:
    """Store the node's outputs in `constants` if they are computable now; says whether it folded."""
    node, name = named
    values = _node_values(node, name, constants, shapes, opset)
    if values is None:
        return False
    for output, value in zip(node.output, values, strict=True):
        if output:
            constants[output] = value
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
    return _evaluate(node, name, constants, opset)


def _shape_value(node: onnx.NodeProto, shape: Shape) -> np.ndarray:
    if node.op_type == "Size":
        return np.array(int(np.prod(shape)), dtype=np.int64)
    attrs = {a.name: a.i for a in node.attribute}
    # Python slicing clamps exactly like Shape's start/end (opset 15).
    return np.array(shape[attrs.get("start", 0) : attrs.get("end", len(shape))], dtype=np.int64)


def _evaluate(node: onnx.NodeProto, name: str, constants: dict, opset: int) -> list[np.ndarray] | None:
    """Run the node alone in onnx's reference evaluator on its constant inputs."""
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
        results = ReferenceEvaluator(model).run(None, feeds)
    except Exception as exc:
        raise NncgError(
            f"cannot fold {node.op_type} node '{name}', whose inputs are all constants: "
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
                f"graph output '{name}' is a constant (it does not depend on any input); "
                "NNCG compiles only outputs computed from the inputs: remove it from the outputs"
            )
