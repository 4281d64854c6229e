"""Graph pass `fold-batchnorm`: BatchNormalization folded into the preceding Conv or Dense.

bn(conv(x)) = conv'(x) with w' = w * scale[c] and b' = b * scale + shift, where scale and shift
come from the BN statistics (the paper's Sec. II-B). A BatchNorm with no producer to fold into
becomes a per-channel ScaleShift. Only constants fold: a BatchNorm whose statistics are computed at
runtime stays for the lowering, and a producer with runtime weights, bias or a fused residual
(see fuse-residual: the BN would scale the residual too) keeps its BatchNorm as a ScaleShift."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir.batchnorm import scale_shift_of_batchnorm
from ..ir.graph import Graph, Node, ScaleShiftAttrs
from .rewrite import fresh_name, merge_into_producer, sole_consumer


def fold_batchnorm(graph: Graph) -> Graph:
    for bn in graph.nodes:
        if bn.op == "BatchNormalization" and _all_constant(graph, bn.inputs[1:]):
            return fold_batchnorm(_fold_one(graph, bn))
    return graph


def _all_constant(graph: Graph, names) -> bool:
    return all(graph.is_constant(name) for name in names)


def _fold_one(graph: Graph, bn: Node) -> Graph:
    scale, shift = scale_shift_of_batchnorm(graph.constants, bn)
    constants = dict(graph.constants)
    producer = graph.producer(bn.inputs[0])
    foldable = (
        producer is not None
        and producer.op in ("Conv", "Dense")
        and producer.attrs.activation is None
        and _all_constant(graph, producer.inputs[1:])
        and sole_consumer(graph, bn.inputs[0]) is bn
        and (producer.op == "Conv" or len(graph.shape(bn.inputs[0])) == 2)
    )
    if not foldable:
        names = [fresh_name(graph, f"{bn.name}_{what}", constants) for what in ("scale", "shift")]
        constants.update(zip(names, (scale, shift)))
        node = Node("ScaleShift", bn.name, (bn.inputs[0], *names), bn.outputs, ScaleShiftAttrs())
        return graph.with_nodes([node if n is bn else n for n in graph.nodes], constants)
    weight = constants[producer.inputs[1]].astype(np.float64)
    if producer.op == "Conv":  # w [c_out, c_in, k...]
        weight = weight * scale.reshape((-1,) + (1,) * (weight.ndim - 1))
    else:  # Dense w [K, N]
        weight = weight * scale.reshape(1, -1)
    bias = constants[producer.inputs[2]].astype(np.float64) if len(producer.inputs) > 2 else 0.0
    w_name = fresh_name(graph, f"{producer.name}_w_bn", constants)
    constants[w_name] = weight.astype(np.float32)
    b_name = fresh_name(graph, f"{producer.name}_b_bn", constants)
    constants[b_name] = (bias * scale + shift).astype(np.float32)
    folded = replace(producer, inputs=(producer.inputs[0], w_name, b_name))
    return merge_into_producer(graph, producer, bn, folded, constants)
