"""Graph pass `drop-identity`: Dropout (inference) and Identity disappear; readers read the input."""

from __future__ import annotations

from dataclasses import replace

from ..ir.graph import Graph
from .rewrite import rename_input


def drop_identity(graph: Graph) -> Graph:
    for node in graph.nodes:
        if node.op != "Identity":
            continue
        src, dst = node.inputs[0], node.outputs[0]
        if not graph.is_graph_output(dst):
            nodes = [rename_input(n, dst, src) for n in graph.nodes if n is not node]
            return drop_identity(graph.with_nodes(nodes))
        producer = graph.producer(src)
        if producer is not None and not graph.is_graph_output(src):
            # The graph output keeps its name: the producer writes it directly.
            nodes = [
                replace(n, outputs=tuple(dst if o == src else o for o in n.outputs))
                if n is producer
                else rename_input(n, src, dst)
                for n in graph.nodes
                if n is not node
            ]
            return drop_identity(graph.with_nodes(nodes))
    return graph  # what is left copies an input or constant to an output: lowering copies it
