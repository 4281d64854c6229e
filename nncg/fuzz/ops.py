"""The generator's op table: for each step kind, how to propose it on a value (random, valid
parameters) and how to build it into ONNX nodes, with the opsets it exists in."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

from . import ops_activation, ops_conv, ops_math, ops_rearrange, ops_reduce, ops_resize, ops_shape
from .build import StepContext
from .draw import Draw, Proposal
from .recipe import Shape


@dataclass(frozen=True)
class OpSpec:
    build: Callable[[StepContext], list[Shape]]
    propose: Callable[[Draw, str], Proposal | None]
    weight: float = 1.0  # how often the generator proposes it
    min_opset: int = 7
    max_opset: int = 99


REDUCTIONS = (
    "ReduceSum", "ReduceMax", "ReduceMin", "ReduceL1", "ReduceL2", "ReduceSumSquare", "ReduceLogSum", "ReduceLogSumExp",
)  # fmt: skip

OPS: dict[str, OpSpec] = {
    "Conv": OpSpec(ops_conv.build_conv, ops_conv.propose_conv, 5.0),
    "ConvTranspose": OpSpec(ops_conv.build_conv_transpose, ops_conv.propose_conv_transpose, 1.0),
    "MaxPool": OpSpec(partial(ops_conv.build_pool, op="MaxPool"), partial(ops_conv.propose_pool, op="MaxPool"), 1.5),
    "AveragePool": OpSpec(
        partial(ops_conv.build_pool, op="AveragePool"), partial(ops_conv.propose_pool, op="AveragePool"), 1.5
    ),
    "GlobalAveragePool": OpSpec(
        partial(ops_conv.build_global_pool, op="GlobalAveragePool"), ops_conv.propose_global_pool, 0.5
    ),
    "GlobalMaxPool": OpSpec(partial(ops_conv.build_global_pool, op="GlobalMaxPool"), ops_conv.propose_global_pool, 0.4),
    "Unary": OpSpec(ops_math.build_unary, ops_math.propose_unary, 3.0),
    "PRelu": OpSpec(ops_math.build_prelu, ops_math.propose_prelu, 0.6),
    "Binary": OpSpec(ops_math.build_binary, ops_math.propose_binary, 2.5),
    "Variadic": OpSpec(ops_math.build_variadic, ops_math.propose_variadic, 0.8),
    "Softmax": OpSpec(ops_math.build_softmax, ops_math.propose_softmax, 0.8),
    "ReduceMean": OpSpec(ops_math.build_reduce_mean, ops_math.propose_reduce_mean, 0.6),
    "BatchNormalization": OpSpec(ops_math.build_batchnorm, ops_math.propose_batchnorm, 1.0),
    "LRN": OpSpec(ops_math.build_lrn, ops_math.propose_lrn, 0.5),
    "Gemm": OpSpec(ops_math.build_gemm, ops_math.propose_gemm, 3.0),
    "MatMul": OpSpec(ops_math.build_matmul, ops_math.propose_matmul, 0.8),
    "Flatten": OpSpec(ops_shape.build_flatten, ops_shape.propose_flatten, 1.0),
    "Reshape": OpSpec(ops_shape.build_reshape, ops_shape.propose_reshape, 0.8),
    "Squeeze": OpSpec(ops_shape.build_squeeze, ops_shape.propose_squeeze, 0.5),
    "Unsqueeze": OpSpec(ops_shape.build_unsqueeze, ops_shape.propose_unsqueeze, 0.4),
    "Transpose": OpSpec(ops_shape.build_transpose, ops_shape.propose_transpose, 0.7),
    "Slice": OpSpec(ops_shape.build_slice, ops_shape.propose_slice, 0.8),
    "Pad": OpSpec(ops_shape.build_pad, ops_shape.propose_pad, 0.8),
    "Split": OpSpec(ops_shape.build_split, ops_shape.propose_split, 0.6),
    "Concat": OpSpec(ops_shape.build_concat, ops_shape.propose_concat, 1.2),
    "Resize": OpSpec(ops_resize.build_resize, ops_resize.propose_resize, 2.0, min_opset=10),
    "Upsample": OpSpec(ops_resize.build_upsample, ops_resize.propose_upsample, 1.5, max_opset=9),
    "DepthToSpace": OpSpec(ops_rearrange.build_depth_to_space, ops_rearrange.propose_depth_to_space, 0.8),
    "SpaceToDepth": OpSpec(ops_rearrange.build_space_to_depth, ops_rearrange.propose_space_to_depth, 0.4),
    "Tile": OpSpec(ops_rearrange.build_tile, ops_rearrange.propose_tile, 0.4),
    "Expand": OpSpec(ops_rearrange.build_expand, ops_rearrange.propose_expand, 0.4, min_opset=8),
    "Gather": OpSpec(ops_rearrange.build_gather, ops_rearrange.propose_gather, 0.5),
    "Where": OpSpec(ops_rearrange.build_where, ops_rearrange.propose_where, 0.4, min_opset=9),
    **{
        op: OpSpec(
            partial(ops_activation.build_activation, op=op),
            partial(ops_activation.propose_activation, op=op),
            ops_activation.WEIGHTS.get(op, 0.15),
            min_opset=ops_activation.MIN_OPSET.get(op, 7),
        )
        for op in ops_activation.ACTIVATIONS
    },
    "Pow": OpSpec(ops_activation.build_pow, ops_activation.propose_pow, 0.4),
    **{
        op: OpSpec(partial(ops_reduce.build_reduce, op=op), partial(ops_reduce.propose_reduce, op=op), 0.15)
        for op in REDUCTIONS
    },
    **{
        op: OpSpec(partial(ops_reduce.build_arg_extreme, op=op), ops_reduce.propose_arg_extreme, 0.2)
        for op in ("ArgMax", "ArgMin")
    },
    "InstanceNormalization": OpSpec(ops_reduce.build_instance_norm, ops_reduce.propose_instance_norm, 0.3),
    # opset 21's GroupNormalization (scale and bias per channel; opsets 18-20 had them per group)
    "GroupNormalization": OpSpec(ops_reduce.build_group_norm, ops_reduce.propose_group_norm, 1.2, min_opset=21),
    "LayerNormalization": OpSpec(ops_reduce.build_layer_norm, ops_reduce.propose_layer_norm, 0.4, min_opset=17),
    "Dropout": OpSpec(ops_shape.build_dropout, ops_shape.propose_dropout, 0.3),
    "Identity": OpSpec(ops_shape.build_identity, ops_shape.propose_identity, 0.2),
}
