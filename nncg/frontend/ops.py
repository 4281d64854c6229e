"""ONNX front end (ONNX -> graph IR), step 3: one record per ONNX op NNCG converts (converter, graph IR
ops it yields, parameter inputs); the converter table and the parameter inputs derive from them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_conv import convert_conv_transpose
from nncg.frontend.ops_data import (
    convert_concat,
    convert_pad,
    convert_resize,
    convert_slice,
    convert_split,
    convert_transpose,
    convert_upsample,
)
from nncg.frontend.ops_elementwise import (
    convert_activation,
    convert_log_softmax,
    convert_lrn,
    convert_pow,
    convert_prelu,
    convert_variadic,
    convert_where,
)
from nncg.frontend.ops_integer import convert_conv_integer, convert_matmul_integer
from nncg.frontend.ops_linear import convert_binary, convert_gemm, convert_matmul
from nncg.frontend.ops_nn import (
    convert_averagepool,
    convert_batchnorm,
    convert_clip,
    convert_conv,
    convert_global_pool,
    convert_leaky_relu,
    convert_maxpool,
    convert_relu,
    convert_softmax,
)
from nncg.frontend.ops_norm import convert_group_norm, convert_instance_norm, convert_layer_norm
from nncg.frontend.ops_qbinary import convert_qlinear_add, convert_qlinear_mul
from nncg.frontend.ops_qconcat import convert_qlinear_concat
from nncg.frontend.ops_qlookup import (
    convert_qlinear_hard_swish,
    convert_qlinear_leaky_relu,
    convert_qlinear_sigmoid,
    convert_qlinear_tanh,
)
from nncg.frontend.ops_qsoftmax import convert_qlinear_softmax
from nncg.frontend.ops_quantized import (
    convert_dequantize_linear,
    convert_qgemm,
    convert_qlinear_average_pool,
    convert_qlinear_conv,
    convert_qlinear_global_average_pool,
    convert_qlinear_matmul,
    convert_quantize_linear,
)
from nncg.frontend.ops_rearrange import (
    convert_depth_to_space,
    convert_expand,
    convert_gather,
    convert_space_to_depth,
    convert_tile,
)
from nncg.frontend.ops_reduce import convert_arg_extreme, convert_reduce
from nncg.frontend.ops_shape import (
    convert_dropout,
    convert_flatten,
    convert_identity,
    convert_reshape,
    convert_squeeze,
    convert_unsqueeze,
)
from nncg.ir.graph import Node
from nncg.ir.ops import REDUCE_OPS

# One IR node, or several computing the op's output in steps (the last writes it).
Converter = Callable[[OnnxOp, Context], Node | tuple[Node, ...]]
# The unary math ops beside the activations: pointwise, each its own graph IR op
UNARY_ACTIVATIONS = (
    "Abs", "Neg", "Sqrt", "Exp", "Log", "Reciprocal", "Softplus", "Softsign", "Mish", "Selu", "Celu", "ThresholdedRelu",
)  # fmt: skip


@dataclass(frozen=True)
class RepeatedSlots:
    """The parameter slots of a variadic op's repeated inputs: from slot `start` on, the inputs come
    in groups of `period`, and the ones at `offsets` within each group are parameters."""

    start: int
    period: int
    offsets: tuple[int, ...]

    def __contains__(self, slot: int) -> bool:
        return slot >= self.start and (slot - self.start) % self.period in self.offsets


@dataclass(frozen=True)
class ConvertedOp:
    """An ONNX op the front end converts: its converter, the graph IR ops (nncg/ir/ops.py) that
    converter can yield, and the input slots it reads as compile-time constants (operator
    parameters such as shapes, axes and pads; not weights, which may be runtime values): the fixed
    ones, and those among a variadic op's repeated inputs."""

    convert: Converter
    ir_ops: tuple[str, ...]
    parameter_inputs: tuple[int, ...] = ()
    repeated_parameters: RepeatedSlots | None = None

    def is_parameter(self, slot: int) -> bool:
        return slot in self.parameter_inputs or (
            self.repeated_parameters is not None and slot in self.repeated_parameters
        )


ONNX_OPS: dict[str, ConvertedOp] = {
    "Conv": ConvertedOp(convert_conv, ("Conv",)),
    "ConvTranspose": ConvertedOp(convert_conv_transpose, ("ConvTranspose",)),
    "MaxPool": ConvertedOp(convert_maxpool, ("MaxPool",)),
    "AveragePool": ConvertedOp(convert_averagepool, ("AveragePool",)),
    "GlobalAveragePool": ConvertedOp(convert_global_pool, ("AveragePool",)),
    "GlobalMaxPool": ConvertedOp(convert_global_pool, ("MaxPool",)),
    "Relu": ConvertedOp(convert_relu, ("Relu",)),
    "Clip": ConvertedOp(convert_clip, ("Clip", "Max", "Min")),  # min, max at run time: Max, Min
    "LeakyRelu": ConvertedOp(convert_leaky_relu, ("LeakyRelu",)),
    "BatchNormalization": ConvertedOp(convert_batchnorm, ("BatchNormalization",)),
    "Softmax": ConvertedOp(convert_softmax, ("Softmax",)),
    "Dropout": ConvertedOp(convert_dropout, ("Identity",), (1, 2)),  # ratio, training_mode (opset 12+)
    "Identity": ConvertedOp(convert_identity, ("Identity",)),
    "Flatten": ConvertedOp(convert_flatten, ("Reshape",)),
    "Reshape": ConvertedOp(convert_reshape, ("Reshape",), (1,)),  # shape
    "Squeeze": ConvertedOp(convert_squeeze, ("Reshape",), (1,)),  # axes (opset 13+)
    "Unsqueeze": ConvertedOp(convert_unsqueeze, ("Reshape",), (1,)),  # axes (opset 13+)
    "Gemm": ConvertedOp(convert_gemm, ("Dense",)),
    # A 1-D operand is a Reshape to a matrix, and the product a Reshape back.
    "MatMul": ConvertedOp(convert_matmul, ("Dense", "Reshape")),
    "Add": ConvertedOp(convert_binary, ("Add",)),
    "Sub": ConvertedOp(convert_binary, ("Sub",)),
    "Mul": ConvertedOp(convert_binary, ("Mul",)),
    "Div": ConvertedOp(convert_binary, ("Div",)),
    "Concat": ConvertedOp(convert_concat, ("Concat",)),
    "Split": ConvertedOp(convert_split, ("Split",), (1,)),  # split (opset 13+)
    "Slice": ConvertedOp(convert_slice, ("Slice",), (1, 2, 3, 4)),  # starts, ends, axes, steps (opset 10+)
    "Transpose": ConvertedOp(convert_transpose, ("Transpose",)),
    "Pad": ConvertedOp(convert_pad, ("Pad",), (1, 3)),  # pads, axes (opset 11+); constant_value may be a runtime input
    "DepthToSpace": ConvertedOp(convert_depth_to_space, ("Reshape", "Transpose")),
    "SpaceToDepth": ConvertedOp(convert_space_to_depth, ("Reshape", "Transpose")),
    # Nothing repeated is a Reshape (a view); Expand's rank grows by a Reshape.
    "Tile": ConvertedOp(convert_tile, ("Tile", "Reshape"), (1,)),  # repeats
    "Expand": ConvertedOp(convert_expand, ("Tile", "Reshape"), (1,)),  # shape
    # Evenly stepping indices are a Slice; their shape (other than 1-D) is a Reshape.
    "Gather": ConvertedOp(convert_gather, ("Gather", "Slice", "Reshape"), (1,)),  # indices
    # A condition picking one runtime side everywhere is that side broadcast (Reshape, Tile).
    "Where": ConvertedOp(convert_where, ("Where", "Reshape", "Tile"), (0,)),  # condition
    # roi, scales, sizes (opset 11+; scales alone in opset 10)
    "Resize": ConvertedOp(convert_resize, ("Resize",), (1, 2, 3)),
    "Upsample": ConvertedOp(convert_upsample, ("Resize",), (1,)),  # scales (opset 9)
    "Sigmoid": ConvertedOp(convert_activation, ("Sigmoid",)),
    "Tanh": ConvertedOp(convert_activation, ("Tanh",)),
    "HardSigmoid": ConvertedOp(convert_activation, ("HardSigmoid",)),
    "HardSwish": ConvertedOp(convert_activation, ("HardSwish",)),
    "Elu": ConvertedOp(convert_activation, ("Elu",)),
    "Erf": ConvertedOp(convert_activation, ("Erf",)),
    "Gelu": ConvertedOp(convert_activation, ("Gelu",)),
    **{name: ConvertedOp(convert_activation, (name,)) for name in UNARY_ACTIVATIONS},
    "Pow": ConvertedOp(convert_pow, ("Pow", "PowPerElement"), (1,)),  # exponent
    "PRelu": ConvertedOp(convert_prelu, ("PRelu",)),
    # One input is an Identity; a scalar constant bound is a Clip.
    "Max": ConvertedOp(convert_variadic, ("Max", "Clip", "Identity")),
    "Min": ConvertedOp(convert_variadic, ("Min", "Clip", "Identity")),
    "Sum": ConvertedOp(convert_variadic, ("Sum", "Identity")),
    "LogSoftmax": ConvertedOp(convert_log_softmax, ("LogSoftmax",)),
    "LRN": ConvertedOp(convert_lrn, ("LRN",)),
    # axes (opset 18+, 13+ for ReduceSum); the spatial mean with keepdims is a global AveragePool,
    # the sum, mean, max or min over no axes with noop_with_empty_axes an Identity; every reduction
    # over an empty axis an Identity of its constant value (empty_reductions.py)
    "ReduceMean": ConvertedOp(convert_reduce, ("ReduceMean", "AveragePool", "Identity"), (1,)),
    **{op: ConvertedOp(convert_reduce, (op, "Identity"), (1,)) for op in REDUCE_OPS if op != "ReduceMean"},
    "ArgMax": ConvertedOp(convert_arg_extreme, ("ArgMax",)),
    "ArgMin": ConvertedOp(convert_arg_extreme, ("ArgMin",)),
    "InstanceNormalization": ConvertedOp(convert_instance_norm, ("InstanceNormalization",)),
    "GroupNormalization": ConvertedOp(convert_group_norm, ("GroupNormalization",)),
    "LayerNormalization": ConvertedOp(convert_layer_norm, ("LayerNormalization",)),
    # The int8 path: scales and zero points are parameters; QGemm, QLinearAdd, the pools, QLinearSoftmax,
    # QLinearLeakyRelu and QLinearSigmoid are onnxruntime's (com.microsoft), and what QDQ groups become (qdq.py).
    "QuantizeLinear": ConvertedOp(convert_quantize_linear, ("QuantizeLinear",), (1, 2)),
    "DequantizeLinear": ConvertedOp(convert_dequantize_linear, ("DequantizeLinear",), (1, 2)),
    # int32 graph outputs, or dequantised by the Cast (Mul, Add) that qdq.py fuses: x_zero_point, w_zero_point
    "ConvInteger": ConvertedOp(convert_conv_integer, ("ConvInteger",), (2, 3)),
    "MatMulInteger": ConvertedOp(convert_matmul_integer, ("MatMulInteger", "Reshape"), (2, 3)),
    "QLinearConv": ConvertedOp(convert_qlinear_conv, ("QLinearConv",), (1, 2, 4, 5, 6, 7)),
    "QLinearMatMul": ConvertedOp(convert_qlinear_matmul, ("QLinearDense", "Reshape"), (1, 2, 4, 5, 6, 7)),
    "QGemm": ConvertedOp(convert_qgemm, ("QLinearDense",), (1, 2, 4, 5, 7, 8)),
    "QLinearAdd": ConvertedOp(convert_qlinear_add, ("QLinearAdd",), (1, 2, 4, 5, 6, 7)),
    "QLinearAveragePool": ConvertedOp(
        convert_qlinear_average_pool, ("QLinearAveragePool", "QLinearGlobalAveragePool"), (1, 2, 3, 4)
    ),  # a window of the whole image is the global pool, as in onnxruntime
    "QLinearGlobalAveragePool": ConvertedOp(
        convert_qlinear_global_average_pool, ("QLinearGlobalAveragePool",), (1, 2, 3, 4)
    ),
    "QLinearSoftmax": ConvertedOp(convert_qlinear_softmax, ("QLinearSoftmax",), (1, 2, 3, 4)),
    # y_scale, y_zero_point, then x, x_scale, x_zero_point per input
    "QLinearConcat": ConvertedOp(
        convert_qlinear_concat, ("QLinearLookup", "Concat"), (0, 1), RepeatedSlots(start=2, period=3, offsets=(1, 2))
    ),
    "QLinearMul": ConvertedOp(convert_qlinear_mul, ("QLinearMul",), (1, 2, 4, 5, 6, 7)),
    "QLinearLeakyRelu": ConvertedOp(convert_qlinear_leaky_relu, ("QLinearLookup",), (1, 2, 3, 4)),
    "QLinearSigmoid": ConvertedOp(convert_qlinear_sigmoid, ("QLinearLookup",), (1, 2, 3, 4)),
    # NNCG's own, written only by qdq.py for a QDQ HardSwish or Tanh (onnxruntime computes those in float)
    "QLinearHardSwish": ConvertedOp(convert_qlinear_hard_swish, ("QLinearLookup",), (1, 2, 3, 4)),
    "QLinearTanh": ConvertedOp(convert_qlinear_tanh, ("QLinearLookup",), (1, 2, 3, 4)),
}

CONVERTERS: dict[str, Converter] = {name: op.convert for name, op in ONNX_OPS.items()}
SUPPORTED_OPS: tuple[str, ...] = tuple(sorted(ONNX_OPS))

# Ops that are accepted only when folded away (Shape/Size need a static input shape).
FOLDED_OPS = "Constant, ConstantOfShape, Shape, Size and any other op whose inputs are all constants"

# Parameter inputs of ops that have no converter and import only when folded: the ONNX backend
# (nncg/onnx_backend.py) binds them too, so that such an op fed by a graph input can fold.
FOLDED_PARAMETER_INPUTS: dict[str, tuple[int, ...]] = {
    "ConstantOfShape": (0,),  # shape
    "ReduceProd": (1,),  # axes (opset 18+)
}

# {op_type: indices of the inputs that are operator parameters}: what NNCG compiles as constants.
PARAMETER_INPUTS: dict[str, tuple[int, ...]] = {
    **{name: op.parameter_inputs for name, op in ONNX_OPS.items() if op.parameter_inputs},
    **FOLDED_PARAMETER_INPUTS,
}
