"""Which graph-IR nodes an algorithm applies to: asked by the pass that chooses it, the lowering that
carries it out and the tuner that times it, so each reads the same rule from one place."""

from __future__ import annotations

from .graph import ConvAttrs, Graph, Node


def winograd_applies(graph: Graph, node: Node) -> bool:
    """A 2-D 3x3 Conv, stride 1, no dilation, no groups, with constant weights."""
    attrs = node.attrs
    return (
        node.op == "Conv"
        and isinstance(attrs, ConvAttrs)
        and attrs.kernel == (3, 3)
        and attrs.strides == (1, 1)
        and attrs.dilations == (1, 1)
        and attrs.group == 1
        and graph.is_constant(node.inputs[1])
    )
