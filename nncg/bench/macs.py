"""Multiply-accumulates per layer, counted from the graph IR: the work behind GFLOP/s and % of peak."""

from __future__ import annotations

from ..ir.graph import Graph, Node
from ..ir.ops import IR_OPS


def node_macs(graph: Graph, node: Node) -> int:
    """The MAC rule of the node's op (nncg/ir/ops.py): Conv, ConvTranspose and Dense count their
    multiply-accumulates, other ops none."""
    return IR_OPS[node.op].macs(graph, node)


def total_macs(graph: Graph) -> int:
    return sum(node_macs(graph, node) for node in graph.nodes)


def macs_by_layer(graph: Graph) -> dict[str, int]:
    """MACs keyed by layer: a node's name, which its kernel keeps."""
    return {node.name: node_macs(graph, node) for node in graph.nodes}
