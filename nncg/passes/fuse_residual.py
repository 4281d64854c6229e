"""Graph pass `fuse-residual`: Add(Conv(x), r), a ResNet shortcut, is done by the Conv, which adds r
at its store, so the sum costs no extra pass over memory; fuse-activation then applies the Relu
that usually follows at the same store."""

from __future__ import annotations

from dataclasses import replace

from ..ir.graph import Graph, Node
from .rewrite import fuse_adds, sole_consumer


def fuse_residual(graph: Graph) -> Graph:
    return fuse_adds(graph, _try_fuse)


def _try_fuse(graph: Graph, add: Node, data: str, other: str) -> Graph | None:
    conv = graph.producer(data)
    if (
        conv is None
        or conv.op != "Conv"
        or conv.attrs.activation is not None  # act(conv) + r is not act(conv + r)
        or conv.attrs.residual
        or other == data
        or graph.is_constant(other)  # a constant per-channel Add is a bias: fuse-bias's case
        or sole_consumer(graph, data) is not add
        or not graph.shape(other) == graph.shape(data) == graph.shape(add.outputs[0])
        # A graph input is row-major while the conv stores channels-last: loading it strided along
        # the output channels would keep the whole conv from vectorising, which costs far more than
        # the separate Add.
        or any(v.name == other for v in graph.inputs)
    ):
        return None
    fused = replace(conv, inputs=(*conv.inputs, other), outputs=add.outputs, attrs=replace(conv.attrs, residual=True))
    # The fused node takes the Add's place: r may be computed after the conv, while the conv's own
    # inputs all exist before the Add.
    return graph.with_nodes([fused if n is add else n for n in graph.nodes if n is not conv])
