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


IR_OPS: dict[str, IrOp] = {
    "Conv": IrOp(ConvAttrs, conv_macs),
    "ConvTranspose": IrOp(ConvTransposeAttrs, conv_transpose_macs),
    "MaxPool": IrOp(PoolAttrs, no_macs),
    "AveragePool": IrOp(PoolAttrs, no_macs),
    "Relu": IrOp(Activation, no_macs),
    "Clip": IrOp(Activation, no_macs),
    "LeakyRelu": IrOp(Activation, no_macs),
    "BatchNormalization": IrOp(BatchNormAttrs, no_macs),
    "ScaleShift": IrOp(ScaleShiftAttrs, no_macs),
    "Dense": IrOp(DenseAttrs, dense_macs),
    "Softmax": IrOp(SoftmaxAttrs, no_macs),
    "Reshape": IrOp(ReshapeAttrs, no_macs),
    "Identity": IrOp(None, no_macs),
    "Add": IrOp(None, no_macs),
    "Sub": IrOp(None, no_macs),
    "Mul": IrOp(None, no_macs),
    "Div": IrOp(None, no_macs),
    "Concat": IrOp(ConcatAttrs, no_macs),
    "Slice": IrOp(SliceAttrs, no_macs),
    "Split": IrOp(SplitAttrs, no_macs),
    "Transpose": IrOp(TransposeAttrs, no_macs),
    "Tile": IrOp(TileAttrs, no_macs),
    "Gather": IrOp(GatherAttrs, no_macs),
    "Where": IrOp(None, no_macs),  # inputs: condition (a constant of 0s and 1s), x, y; NumPy broadcasting
    "Pad": IrOp(PadAttrs, no_macs),
    "Resize": IrOp(ResizeAttrs, no_macs),
    "Sigmoid": IrOp(Activation, no_macs),
    "Tanh": IrOp(Activation, no_macs),
    "HardSigmoid": IrOp(Activation, no_macs),
    "HardSwish": IrOp(Activation, no_macs),
    "Elu": IrOp(Activation, no_macs),
    "Silu": IrOp(Activation, no_macs),
    "Erf": IrOp(Activation, no_macs),
    "Gelu": IrOp(Activation, no_macs),
    "Abs": IrOp(Activation, no_macs),
    "Neg": IrOp(Activation, no_macs),
    "Sqrt": IrOp(Activation, no_macs),
    "Exp": IrOp(Activation, no_macs),
    "Log": IrOp(Activation, no_macs),
    "Reciprocal": IrOp(Activation, no_macs),
    "Pow": IrOp(Activation, no_macs),
    "Softplus": IrOp(Activation, no_macs),
    "Softsign": IrOp(Activation, no_macs),
    "Mish": IrOp(Activation, no_macs),
    "Selu": IrOp(Activation, no_macs),
    "Celu": IrOp(Activation, no_macs),
    "ThresholdedRelu": IrOp(Activation, no_macs),
    "PRelu": IrOp(None, no_macs),
    "PowPerElement": IrOp(None, no_macs),
    "Max": IrOp(None, no_macs),
    "Min": IrOp(None, no_macs),
    "Sum": IrOp(None, no_macs),
    "LogSoftmax": IrOp(SoftmaxAttrs, no_macs),
    "LRN": IrOp(LrnAttrs, no_macs),
    **{op: IrOp(ReduceAttrs, no_macs) for op in REDUCE_OPS},
    "ArgMax": IrOp(ArgMaxAttrs, no_macs),
    "ArgMin": IrOp(ArgMaxAttrs, no_macs),
    "InstanceNormalization": IrOp(NormAttrs, no_macs),
    "GroupNormalization": IrOp(NormAttrs, no_macs),
    "LayerNormalization": IrOp(NormAttrs, no_macs),
    # The int8 path (nncg/ir/graph_dtypes.py says which inputs are integer)
    "QuantizeLinear": IrOp(QuantAttrs, no_macs),
    "DequantizeLinear": IrOp(QuantAttrs, no_macs),
    "QLinearConv": IrOp(QConvAttrs, conv_macs),
    "QLinearDense": IrOp(QDenseAttrs, q_dense_macs),
    "QLinearAdd": IrOp(QBinaryAttrs, no_macs),
    "QLinearGlobalAveragePool": IrOp(QPoolAttrs, no_macs),
    "QLinearAveragePool": IrOp(QAveragePoolAttrs, no_macs),
    "QLinearSoftmax": IrOp(QSoftmaxAttrs, no_macs),
    "QLinearLookup": IrOp(QLookupAttrs, no_macs),
    "QLinearMul": IrOp(QBinaryAttrs, no_macs),
    "ConvInteger": IrOp(IntegerConvAttrs, conv_macs),
    "MatMulInteger": IrOp(IntegerDenseAttrs, q_dense_macs),
}
