"""Graph pass `fuse-activation`: a pointwise activation node (Relu, LeakyRelu, Clip, Sigmoid, Tanh,
HardSigmoid, HardSwish, Elu, Silu, Erf, Gelu, the unary math ops such as Abs, Sqrt, Softplus, Mish
and Pow by one exponent: every node whose attributes are an Activation) is applied by its producer
at the store, so the activation costs no extra pass over memory.

First, the composite forms torch exports are made one activation: its GELU decompositions become a
Gelu node (fuse_gelu.py); Mul(x, Sigmoid(x)) (SiLU, Swish) becomes a Silu node and
Mul(x, HardSigmoid(x)) a HardSwish, either operand order, when the Mul is the gate's only reader. x
then usually has one reader left, so its producer applies the whole x * gate(x) at its store; with no
producer to take it, the Silu is one pass over memory instead of two (a Gelu instead of five or more)."""

from __future__ import annotations

from dataclasses import replace

from ..ir.graph import Activation, Graph, Node
from .fuse_gelu import fuse_gelu
from .rewrite import merge_into_producer, sole_consumer

PRODUCERS = ("Conv", "Dense", "ScaleShift", "InstanceNormalization", "GroupNormalization", "LayerNormalization")

# A gate g whose Mul(x, g(x)) is one activation: the gate's op -> the fused node's op and activation
# kind (the gate's parameters carry over: HardSigmoid's alpha and beta).
GATED = {"Sigmoid": ("Silu", "silu"), "HardSigmoid": ("HardSwish", "hard_swish")}


def fuse_activation(graph: Graph) -> Graph:
    return _fuse_producers(fuse_gated(fuse_gelu(graph)))


def fuse_gated(graph: Graph) -> Graph:
    """Every Mul(x, gate(x)) whose gate only the Mul reads made one activation node (Silu, HardSwish)."""
    for mul in graph.nodes:
        if mul.op != "Mul" or len(mul.inputs) != 2:
            continue
        for x, gated in (mul.inputs, mul.inputs[::-1]):
            gate = graph.producer(gated)
            if (
                gate is not None
                and gate.op in GATED
                and gate.inputs[0] == x
                and sole_consumer(graph, gated) is mul
                and graph.shape(x) == graph.shape(mul.outputs[0])
            ):
                return fuse_gated(_make_gated(graph, mul, gate, x))
    return graph


def _make_gated(graph: Graph, mul: Node, gate: Node, x: str) -> Graph:
    op, kind = GATED[gate.op]
    fused = Node(op, mul.name, (x,), mul.outputs, replace(gate.attrs, kind=kind))
    # At the Mul's place: x exists before the gate, which is before the Mul.
    return graph.with_nodes([fused if n is mul else n for n in graph.nodes if n is not gate])


def _fuse_producers(graph: Graph) -> Graph:
    for act in graph.nodes:
        if not isinstance(act.attrs, Activation):
            continue
        producer = graph.producer(act.inputs[0])
        if (
            producer is not None
            and producer.op in PRODUCERS
            and producer.attrs.activation is None
            and len(producer.outputs) == 1  # not a LayerNormalization writing its statistics too
            and sole_consumer(graph, act.inputs[0]) is act
        ):
            fused = replace(producer, attrs=replace(producer.attrs, activation=act.attrs))
            return _fuse_producers(merge_into_producer(graph, producer, act, fused))
    return graph
