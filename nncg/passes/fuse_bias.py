"""Graph pass `fuse-bias`: MatMul + Add (bias) becomes one Dense with a bias, and a Conv followed by
a per-channel constant Add takes it as its bias, as exporters split them. A producer whose bias is
computed at runtime, or that adds a fused residual, is left alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir.graph import Graph, Node
from .rewrite import fresh_name, fuse_adds, merge_into_producer, sole_consumer


def fuse_bias(graph: Graph) -> Graph:
    return fuse_adds(graph, _try_fuse)


def _try_fuse(graph: Graph, add: Node, data: str, other: str) -> Graph | None:
    producer = graph.producer(data)
    if (
        producer is None
        or producer.op not in ("Conv", "Dense")
        or not graph.is_constant(other)
        or producer.attrs.activation is not None
        or not all(graph.is_constant(name) for name in producer.inputs[2:])
        or sole_consumer(graph, data) is not add
        or graph.shape(add.outputs[0]) != graph.shape(data)
    ):
        return None
    bias = _per_channel(graph.constants[other], graph.shape(data), channel_axis=1 if producer.op == "Conv" else -1)
    if bias is None:
        return None
    constants = dict(graph.constants)
    if len(producer.inputs) > 2:
        bias = bias + constants[producer.inputs[2]]
    name = fresh_name(graph, f"{producer.name}_bias", constants)
    constants[name] = bias.astype(np.float32)
    fused = replace(producer, inputs=(*producer.inputs[:2], name))
    return merge_into_producer(graph, producer, add, fused, constants)


def _per_channel(const: np.ndarray, shape: tuple[int, ...], channel_axis: int) -> np.ndarray | None:
    """The constant as a [C] vector when it varies only along the channel axis, else None."""
    axis = channel_axis % len(shape)
    if const.ndim > len(shape):
        return None
    try:
        if np.broadcast_shapes(const.shape, shape) != shape:
            return None
    except ValueError:
        return None
    full = np.broadcast_to(const, shape)
    moved = np.moveaxis(full, axis, -1).reshape(-1, shape[axis])
    if not np.all(moved == moved[0]):
        return None
    return moved[0].astype(np.float32)
