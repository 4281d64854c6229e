"""Helpers for graph passes: find a node's single consumer, splice a node out of the graph."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from ..ir import names
from ..ir.graph import Graph, Node


def sole_consumer(graph: Graph, value: str) -> Node | None:
    """The one node reading `value`, if exactly one does and value is not also a graph output."""
    consumers = graph.consumers(value)
    if len(consumers) != 1 or graph.is_graph_output(value):
        return None
    return consumers[0]


def merge_into_producer(graph: Graph, producer: Node, merged: Node, new_producer: Node, constants=None) -> Graph:
    """Replaces producer by new_producer, which now writes merged's output; merged disappears."""
    new_producer = replace(new_producer, outputs=merged.outputs)
    nodes = [new_producer if n is producer else n for n in graph.nodes if n is not merged]
    return graph.with_nodes(nodes, constants)


def rename_input(node: Node, old: str, new: str) -> Node:
    return replace(node, inputs=tuple(new if name == old else name for name in node.inputs))


def fresh_name(graph: Graph, base: str, taken: dict) -> str:
    """A name for a new constant: `base` or `base_<k>`, neither a value of the graph nor in `taken`."""
    return names.fresh_name(base, graph.constants, graph.shapes, taken)


def fuse_adds(graph: Graph, try_fuse: Callable[[Graph, Node, str, str], Graph | None]) -> Graph:
    """Applies try_fuse(graph, add, data, other) to every Add, both operand orders, until none fuses."""
    for add in graph.nodes:
        if add.op != "Add":
            continue
        for data, other in (add.inputs, add.inputs[::-1]):
            fused = try_fuse(graph, add, data, other)
            if fused is not None:
                return fuse_adds(fused, try_fuse)
    return graph
