"""Zero-copy concatenation: a Concat input whose producer can write it straight into its slab of the
Concat's output is lowered as a view of that slab (the Concat output's buffer, with the rest of the
concatenated axis as a halo on either side), and the Concat copies only the other inputs. The
producer writes with its usual strides; squeezenet's fire modules concatenate two convs this way."""

from __future__ import annotations

from ..ir.graph import Graph
from .halo import VIEW_WRITERS


def concat_slices(graph: Graph) -> dict[str, tuple[str, int, int]]:
    """Value -> (the Concat output, axis, offset) for each Concat input its producer may write in
    place: produced by a VIEW_WRITERS node, once among the Concat's inputs, not a graph output,
    into an internal Concat output (other readers read the slab)."""
    producers = {value: node for node in graph.nodes for value in node.outputs}
    slices: dict[str, tuple[str, int, int]] = {}
    for node in graph.nodes:
        if node.op != "Concat" or graph.is_graph_output(node.outputs[0]):
            continue
        offset = 0
        for name in node.inputs:
            producer = producers.get(name)
            if (
                producer is not None
                and producer.op in VIEW_WRITERS
                and node.inputs.count(name) == 1
                and name not in slices
                and not graph.is_graph_output(name)
            ):
                slices[name] = (node.outputs[0], node.attrs.axis, offset)
            offset += graph.shape(name)[node.attrs.axis]
    return slices
