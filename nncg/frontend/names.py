"""ONNX front end (ONNX -> graph IR): stable node names and fresh value names.

Node names are fixed once per ONNX graph so error messages and the graph IR agree on them.
"""

from __future__ import annotations

import onnx

from nncg.ir.names import fresh_name


def node_names(graph: onnx.GraphProto) -> list[str]:
    """One unique name per node: its ONNX name, or `<OpType>_<index>` when it has none."""
    taken: set[str] = set()
    names = []
    for index, node in enumerate(graph.node):
        name = fresh_name(node.name or f"{node.op_type}_{index}", taken)
        taken.add(name)
        names.append(name)
    return names


def value_names(graph: onnx.GraphProto) -> set[str]:
    """Every tensor name the graph mentions, so new constants never collide with one."""
    names = {v.name for v in (*graph.input, *graph.output, *graph.value_info)}
    names |= {t.name for t in graph.initializer}
    names |= {t.values.name for t in graph.sparse_initializer}
    for node in graph.node:
        names.update(node.input)
        names.update(node.output)
    names.discard("")
    return names


def node_reads(node: onnx.NodeProto) -> set[str]:
    """Values a node reads: its inputs plus, for If/Loop/Scan, every name its subgraphs read
    (a superset of the outer values they capture, which is all liveness needs)."""
    reads = {i for i in node.input if i}
    for attr in node.attribute:
        for graph in (attr.g,) if attr.type == onnx.AttributeProto.GRAPH else attr.graphs:
            for inner in graph.node:
                reads |= node_reads(inner)
    return reads
