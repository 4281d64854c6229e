"""Which graph-IR nodes an algorithm applies to: asked by the pass that chooses it, the lowering that
carries it out and the tuner that times it, so each reads the same rule from one place."""

from __future__ import annotations

import math
from collections.abc import Iterable

from .graph import ConvAttrs, DenseAttrs, Graph, Node
from .kinds import ConvAlgorithm, VectorAxis
from .target import Target

# onnxruntime computes QLinearAdd in float fused multiply-adds (lowering/quantized_add.py), which vectors
# of a target with FMA do too, or, without, in double (Target.fma_in_double); QLinearMul's float32 sum
# is an Fma by 1 (passes/vectorize.py _product_then_sum)
FUSED_OPS = ("QLinearAdd", "QLinearMul")


def fused_ops_vectorise(target: Target) -> bool:
    """Whether FUSED_OPS vectorise on `target`, run whole or as an int8 band kernel's stages: the vectorize
    pass's rule, and what the band planner prices them by (lowering/band_plan.py)."""
    return target.integer_vectors and (target.fma or target.fma_in_double)


# The ops whose kernels requantise their int32 results in the form lower's `requantize` chooses
# (lowering/requantize.py Scales); the other int8 ops requantise in float whatever the form (QLinearAdd's
# fused multiply-adds, QuantizeLinear's quotient)
SCALED_OPS = ("QLinearConv", "QLinearDense", "QLinearGlobalAveragePool")


def integer_kernel_vectorises(target: Target, fixed_point: bool) -> bool:
    """Whether an int8 kernel vectorises on `target`: with integer vectors, unless it requantises in the
    fixed-point form (`fixed_point`: a band kernel if any of its stages does), which no backend has in
    vectors. The vectorize pass's rule (it finds a RequantizeFixed in the kernel), and what the band
    planner prices int8 layers and band kernels by (requantises_fixed; lowering/band_plan.py)."""
    return target.integer_vectors and not fixed_point


def requantises_fixed(ops: Iterable[str], requantize: str) -> bool:
    """Whether the kernel computing `ops` (a layer's op, or a band group's) requantises in the fixed-point
    form, under lower's `requantize`."""
    return requantize == "fixed" and any(op in SCALED_OPS for op in ops)


def winograd_applies(graph: Graph, node: Node) -> bool:
    """A 2-D 3x3 Conv, stride 1, no dilation, no groups, with constant weights."""
    return (
        node.op == "Conv"
        and isinstance(node.attrs, ConvAttrs)
        and _winograd_window(node.attrs)
        and graph.is_constant(node.inputs[1])
    )


def integer_winograd_shaped(node: Node) -> bool:
    """A QLinearConv (its weights are constant) of winograd_applies's window; whether its arithmetic
    fits the integer transforms is lowering/winograd_integer.py's integer_winograd_fits."""
    return node.op == "QLinearConv" and _winograd_window(node.attrs)


def _winograd_window(attrs) -> bool:
    return attrs.kernel == (3, 3) and attrs.strides == (1, 1) and attrs.dilations == (1, 1) and attrs.group == 1


def _direct_channel_conv(graph: Graph, node: Node) -> bool:
    """A direct Conv vectorised over its output channels, with constant weights."""
    attrs = node.attrs
    return (
        node.op == "Conv"
        and isinstance(attrs, ConvAttrs)
        and attrs.algorithm == ConvAlgorithm.DIRECT
        and attrs.vector_axis == VectorAxis.CHANNELS
        and graph.is_constant(node.inputs[1])
    )


def cache_block_applies(graph: Graph, node: Node) -> bool:
    """A direct, ungrouped Conv vectorised over its output channels, with constant weights."""
    return _direct_channel_conv(graph, node) and node.attrs.group == 1


def group_panels_apply(graph: Graph, node: Node) -> bool:
    """A direct, grouped (not depthwise) Conv vectorised over its output channels, with constant weights:
    computed one group at a time, a group being one panel."""
    return (
        _direct_channel_conv(graph, node) and node.attrs.group > 1 and graph.shape(node.inputs[1])[0] > node.attrs.group
    )


def depthwise_blocks_apply(graph: Graph, node: Node) -> bool:
    """A direct depthwise Conv (one input and one output channel a group) vectorised over its channels,
    with constant weights: computed a block of channels at a time outside its pixel loops."""
    if not _direct_channel_conv(graph, node):
        return False
    c_out, c_in_g = graph.shape(node.inputs[1])[:2]
    return c_in_g == 1 and node.attrs.group == c_out > 1


def panel_packing_applies(graph: Graph, node: Node) -> bool:
    """A Gemm/MatMul whose w is one constant [K, N] matrix (x's rows may be any)."""
    attrs = node.attrs
    return (
        isinstance(attrs, DenseAttrs)
        and not attrs.trans_x
        and graph.is_constant(node.inputs[1])
        and len(graph.shape(node.inputs[1])) == 2
    )


# A packed GEMV's reduction split into up to this many segments, read side by side (4 distant streams of
# a weight panel keep more cache lines in flight than one: a 1280x1000 classifier from memory ran
# 1.15x-1.2x faster on avx512), each of at least MIN_SEGMENT steps.
GEMV_STREAMS = 4
MIN_SEGMENT = 16


def reduction_streams(graph: Graph, node: Node, vectors: int, accumulators: int) -> int:
    """How many segments of its reduction a panel-packed Gemm/MatMul of `vectors` accumulators a
    segment reads at once: for one row of x (batch 1: a GEMV, bound by streaming its weights) as many as
    `accumulators` registers hold, at most GEMV_STREAMS; else 1 (rows reuse the weights). Each segment
    broadcasts its own x value per step, so the panel's width comes first (cache_block.panel_width)."""
    out = graph.shape(node.outputs[0])
    reduction = math.prod(graph.shape(node.inputs[1])) // out[-1]
    if math.prod(out[:-1]) != 1:
        return 1
    return max(1, min(GEMV_STREAMS, accumulators // vectors, reduction // MIN_SEGMENT))
