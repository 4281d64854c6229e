"""Reductions over an empty axis. ONNX defines them (ReduceSum over a 0-sized axis is 0, ReduceMax
-inf, ...): the result is a constant, and the empty input it reduces is never read. A graph input
may have a 0-sized dimension only when every node reading it is such a reduction over that axis;
any other empty tensor is refused (nncg/frontend/checks.py)."""

from __future__ import annotations

import math

import onnx
from onnx import numpy_helper

# The value of each reduction over no elements (ONNX's reference: the reduction's identity).
EMPTY_VALUES: dict[str, float] = {
    "ReduceSum": 0.0,
    "ReduceSumSquare": 0.0,
    "ReduceL1": 0.0,
    "ReduceL2": 0.0,
    "ReduceMax": -math.inf,
    "ReduceMin": math.inf,
    "ReduceLogSum": -math.inf,
    "ReduceLogSumExp": -math.inf,
}


def reduced_empty_inputs(graph: onnx.GraphProto) -> set[str]:
    """The graph inputs with a 0-sized dimension that only reductions over their 0-sized axes read
    (axes as an attribute or an initializer)."""
    found = set()
    for value in graph.input:
        dims = value.type.tensor_type.shape.dim if value.type.HasField("tensor_type") else ()
        empty = {i for i, d in enumerate(dims) if d.HasField("dim_value") and d.dim_value == 0}
        readers = [node for node in graph.node if value.name in node.input]
        if empty and readers and all(_reduces(node, value.name, empty, len(dims), graph) for node in readers):
            found.add(value.name)
    return found


def _reduces(node: onnx.NodeProto, name: str, empty: set[int], rank: int, graph: onnx.GraphProto) -> bool:
    if node.op_type not in EMPTY_VALUES or node.domain not in ("", "ai.onnx") or node.input[0] != name:
        return False
    axes = _axes(node, graph)
    if axes is None:
        return False
    return empty <= ({a % rank for a in axes} if axes else set(range(rank)))


def _axes(node: onnx.NodeProto, graph: onnx.GraphProto) -> list[int] | None:
    """The node's axes ([] for all), or None when they are not known before import."""
    attr = next((a for a in node.attribute if a.name == "axes"), None)
    if attr is not None:
        return list(attr.ints)
    if len(node.input) < 2 or not node.input[1]:
        noop = next((a.i for a in node.attribute if a.name == "noop_with_empty_axes"), 0)
        return None if noop else []
    tensor = next((t for t in graph.initializer if t.name == node.input[1]), None)
    return None if tensor is None else numpy_helper.to_array(tensor).tolist()
