"""Graph IR operators: one record per op, naming the attribute record its nodes carry and how many
multiply-accumulates a node does. The front end's converters and the lowerings are keyed by these
names; tests/test_op_tables.py checks that the three tables agree."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from .graph import (
    Activation,
    ArgMaxAttrs,
    BatchNormAttrs,
    ConcatAttrs,
    ConvAttrs,
    ConvTransposeAttrs,
    DenseAttrs,
    GatherAttrs,
    Graph,
    IntegerConvAttrs,
    IntegerDenseAttrs,
    LrnAttrs,
    Node,
    NormAttrs,
    PadAttrs,
    PoolAttrs,
    QAveragePoolAttrs,
    QBinaryAttrs,
    QConvAttrs,
    QDenseAttrs,
    QLookupAttrs,
    QPoolAttrs,
    QSoftmaxAttrs,
    QuantAttrs,
    ReduceAttrs,
    ReshapeAttrs,
    ResizeAttrs,
    ScaleShiftAttrs,
    SliceAttrs,
    SoftmaxAttrs,
    SplitAttrs,
    TileAttrs,
    TransposeAttrs,
)

# The reductions, named as in ONNX, all with ReduceAttrs.
REDUCE_OPS = (
    "ReduceSum",
    "ReduceMean",
    "ReduceMax",
    "ReduceMin",
    "ReduceL1",
    "ReduceL2",
    "ReduceSumSquare",
    "ReduceLogSum",
    "ReduceLogSumExp",
)

MacRule = Callable[[Graph, Node], int]


def no_macs(graph: Graph, node: Node) -> int:
    """Data movement, pointwise and reduction ops: their cost is memory, not multiply-accumulates."""
    return 0


def conv_macs(graph: Graph, node: Node) -> int:
    """Outputs x c_in/group x kernel taps (w: [c_out, c_in/group, k...])."""
    weight = graph.shape(node.inputs[1])
    return math.prod(graph.shape(node.outputs[0])) * math.prod(weight[1:])


def conv_transpose_macs(graph: Graph, node: Node) -> int:
    """Inputs x c_out/group x kernel taps (w: [c_in, c_out/group, k...])."""
    weight = graph.shape(node.inputs[1])
    return math.prod(graph.shape(node.inputs[0])) * math.prod(weight[1:])


def dense_macs(graph: Graph, node: Node) -> int:
    """Outputs x K (w: [..., K, N], or [..., N, K] with trans_w)."""
    weight = graph.shape(node.inputs[1])
    k = weight[-1] if node.attrs.trans_w else weight[-2]
    return math.prod(graph.shape(node.outputs[0])) * k


def q_dense_macs(graph: Graph, node: Node) -> int:
    """Outputs x K (w: [K, N])."""
    return math.prod(graph.shape(node.outputs[0])) * graph.shape(node.inputs[1])[0]


@dataclass(frozen=True)
class IrOp:
    """attrs: the attribute record type of every node of the op (None: no attributes); macs: the
    node's multiply-accumulates, from shapes alone (weights may be constant or computed at runtime)."""

    attrs: type | None
    macs: MacRule
    # Each output element computed from the same element of its inputs (broadcast ones aside): what
    # plan-memory computes in place when an input of the output's size and type dies there. The band
    # planner counts memory by it; tests/test_memory_plan.py checks the two agree.
    elementwise: bool = False


IR_OPS: dict[str, IrOp] = {
    "Conv": IrOp(ConvAttrs, conv_macs),
    "ConvTranspose": IrOp(ConvTransposeAttrs, conv_transpose_macs),
    "MaxPool": IrOp(PoolAttrs, no_macs),
    "AveragePool": IrOp(PoolAttrs, no_macs),
    "Relu": IrOp(Activation, no_macs, elementwise=True),
    "Clip": IrOp(Activation, no_macs, elementwise=True),
    "LeakyRelu": IrOp(Activation, no_macs, elementwise=True),
    "BatchNormalization": IrOp(BatchNormAttrs, no_macs),
    "ScaleShift": IrOp(ScaleShiftAttrs, no_macs, elementwise=True),
    "Dense": IrOp(DenseAttrs, dense_macs),
    "Softmax": IrOp(SoftmaxAttrs, no_macs),
    "Reshape": IrOp(ReshapeAttrs, no_macs),
    "Identity": IrOp(None, no_macs),
    "Add": IrOp(None, no_macs, elementwise=True),
    "Sub": IrOp(None, no_macs, elementwise=True),
    "Mul": IrOp(None, no_macs, elementwise=True),
    "Div": IrOp(None, no_macs, elementwise=True),
    "Concat": IrOp(ConcatAttrs, no_macs),
    "Slice": IrOp(SliceAttrs, no_macs),
    "Split": IrOp(SplitAttrs, no_macs),
    "Transpose": IrOp(TransposeAttrs, no_macs),
    "Tile": IrOp(TileAttrs, no_macs),
    "Gather": IrOp(GatherAttrs, no_macs),
    "Where": IrOp(
        None, no_macs, elementwise=True
    ),  # inputs: condition (a constant of 0s and 1s), x, y; NumPy broadcasting
    "Pad": IrOp(PadAttrs, no_macs),
    "Resize": IrOp(ResizeAttrs, no_macs),
    "Sigmoid": IrOp(Activation, no_macs, elementwise=True),
    "Tanh": IrOp(Activation, no_macs, elementwise=True),
    "HardSigmoid": IrOp(Activation, no_macs, elementwise=True),
    "HardSwish": IrOp(Activation, no_macs, elementwise=True),
    "Elu": IrOp(Activation, no_macs, elementwise=True),
    "Silu": IrOp(Activation, no_macs, elementwise=True),
    "Erf": IrOp(Activation, no_macs, elementwise=True),
    "Gelu": IrOp(Activation, no_macs, elementwise=True),
    "Abs": IrOp(Activation, no_macs, elementwise=True),
    "Neg": IrOp(Activation, no_macs, elementwise=True),
    "Sqrt": IrOp(Activation, no_macs, elementwise=True),
    "Exp": IrOp(Activation, no_macs, elementwise=True),
    "Log": IrOp(Activation, no_macs, elementwise=True),
    "Reciprocal": IrOp(Activation, no_macs, elementwise=True),
    "Pow": IrOp(Activation, no_macs, elementwise=True),
    "Softplus": IrOp(Activation, no_macs, elementwise=True),
    "Softsign": IrOp(Activation, no_macs, elementwise=True),
    "Mish": IrOp(Activation, no_macs, elementwise=True),
    "Selu": IrOp(Activation, no_macs, elementwise=True),
    "Celu": IrOp(Activation, no_macs, elementwise=True),
    "ThresholdedRelu": IrOp(Activation, no_macs, elementwise=True),
    "PRelu": IrOp(None, no_macs, elementwise=True),
    "PowPerElement": IrOp(None, no_macs, elementwise=True),
    "Max": IrOp(None, no_macs, elementwise=True),
    "Min": IrOp(None, no_macs, elementwise=True),
    "Sum": IrOp(None, no_macs, elementwise=True),
    "LogSoftmax": IrOp(SoftmaxAttrs, no_macs),
    "LRN": IrOp(LrnAttrs, no_macs),
    **{op: IrOp(ReduceAttrs, no_macs) for op in REDUCE_OPS},
    "ArgMax": IrOp(ArgMaxAttrs, no_macs),
    "ArgMin": IrOp(ArgMaxAttrs, no_macs),
    "InstanceNormalization": IrOp(NormAttrs, no_macs),
    "GroupNormalization": IrOp(NormAttrs, no_macs),
    "LayerNormalization": IrOp(NormAttrs, no_macs),
    # The int8 path (nncg/ir/graph_dtypes.py says which inputs are integer)
    "QuantizeLinear": IrOp(QuantAttrs, no_macs, elementwise=True),
    "DequantizeLinear": IrOp(QuantAttrs, no_macs, elementwise=True),
    "QLinearConv": IrOp(QConvAttrs, conv_macs),
    "QLinearDense": IrOp(QDenseAttrs, q_dense_macs),
    "QLinearAdd": IrOp(QBinaryAttrs, no_macs, elementwise=True),
    "QLinearGlobalAveragePool": IrOp(QPoolAttrs, no_macs),
    "QLinearAveragePool": IrOp(QAveragePoolAttrs, no_macs),
    "QLinearSoftmax": IrOp(QSoftmaxAttrs, no_macs),
    "QLinearLookup": IrOp(QLookupAttrs, no_macs, elementwise=True),
    "QLinearMul": IrOp(QBinaryAttrs, no_macs, elementwise=True),
    "ConvInteger": IrOp(IntegerConvAttrs, conv_macs),
    "MatMulInteger": IrOp(IntegerDenseAttrs, q_dense_macs),
}
