"""Graph pass `fuse-activation`: a pointwise activation node (Relu, LeakyRelu, Clip, Sigmoid, Tanh,
HardSigmoid, HardSwish, Elu: every node whose attributes are an Activation) is applied by its
producer at the store, so the activation costs no extra pass over memory."""

from __future__ import annotations

from dataclasses import replace

from ..ir.graph import Activation, Graph
from .rewrite import merge_into_producer, sole_consumer

PRODUCERS = ("Conv", "Dense", "ScaleShift")


def fuse_activation(graph: Graph) -> Graph:
    for act in graph.nodes:
        if not isinstance(act.attrs, Activation):
            continue
        producer = graph.producer(act.inputs[0])
        if (
            producer is not None
            and producer.op in PRODUCERS
            and producer.attrs.activation is None
            and sole_consumer(graph, act.inputs[0]) is act
        ):
            fused = replace(producer, attrs=replace(producer.attrs, activation=act.attrs))
            return fuse_activation(merge_into_producer(graph, producer, act, fused))
    return graph
