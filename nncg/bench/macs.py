"""Multiply-accumulates per layer, counted from the graph IR: the work behind GFLOP/s and % of peak."""

from __future__ import annotations

import numpy as np

from ..ir.graph import Graph, Node


def node_macs(graph: Graph, node: Node) -> int:
    """Conv: outputs x c_in/group x kernel taps; ConvTranspose: inputs x c_out/group x kernel taps;
    Dense: outputs x K; other ops do no MACs. Weights may be constant or runtime: shapes suffice."""
    if node.op == "Conv":
        weight = graph.shape(node.inputs[1])  # [c_out, c_in/group, k...]
        return int(np.prod(graph.shape(node.outputs[0]))) * int(np.prod(weight[1:]))
    if node.op == "ConvTranspose":
        weight = graph.shape(node.inputs[1])  # [c_in, c_out/group, k...]
        return int(np.prod(graph.shape(node.inputs[0]))) * int(np.prod(weight[1:]))
    if node.op == "Dense":
        weight = graph.shape(node.inputs[1])  # [..., K, N], or [..., N, K] with trans_w
        k = weight[-1] if node.attrs.trans_w else weight[-2]
        return int(np.prod(graph.shape(node.outputs[0]))) * k
    return 0


def total_macs(graph: Graph) -> int:
    return sum(node_macs(graph, node) for node in graph.nodes)


def macs_by_layer(graph: Graph) -> dict[str, int]:
    """MACs keyed by layer: a node's name, which its kernel keeps."""
    return {node.name: node_macs(graph, node) for node in graph.nodes}
