"""ONNX front end (ONNX -> graph IR), step 3: the table of ONNX ops NNCG converts and to what."""

from __future__ import annotations

from collections.abc import Callable

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
    convert_prelu,
    convert_reduce_mean,
    convert_variadic,
)
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
from nncg.frontend.ops_shape import (
    convert_dropout,
    convert_flatten,
    convert_identity,
    convert_reshape,
    convert_squeeze,
    convert_unsqueeze,
)
from nncg.ir.graph import Node

Converter = Callable[[OnnxOp, Context], Node]

CONVERTERS: dict[str, Converter] = {
    "Conv": convert_conv,
    "ConvTranspose": convert_conv_transpose,
    "MaxPool": convert_maxpool,
    "AveragePool": convert_averagepool,
    "GlobalAveragePool": convert_global_pool,
    "GlobalMaxPool": convert_global_pool,
    "Relu": convert_relu,
    "Clip": convert_clip,
    "LeakyRelu": convert_leaky_relu,
    "BatchNormalization": convert_batchnorm,
    "Softmax": convert_softmax,
    "Dropout": convert_dropout,
    "Identity": convert_identity,
    "Flatten": convert_flatten,
    "Reshape": convert_reshape,
    "Squeeze": convert_squeeze,
    "Unsqueeze": convert_unsqueeze,
    "Gemm": convert_gemm,
    "MatMul": convert_matmul,
    "Add": convert_binary,
    "Sub": convert_binary,
    "Mul": convert_binary,
    "Div": convert_binary,
    "Concat": convert_concat,
    "Split": convert_split,
    "Slice": convert_slice,
    "Transpose": convert_transpose,
    "Pad": convert_pad,
    "Resize": convert_resize,
    "Upsample": convert_upsample,
    "Sigmoid": convert_activation,
    "Tanh": convert_activation,
    "HardSigmoid": convert_activation,
    "HardSwish": convert_activation,
    "Elu": convert_activation,
    "PRelu": convert_prelu,
    "Max": convert_variadic,
    "Min": convert_variadic,
    "Sum": convert_variadic,
    "LogSoftmax": convert_log_softmax,
    "LRN": convert_lrn,
    "ReduceMean": convert_reduce_mean,
}

SUPPORTED_OPS: tuple[str, ...] = tuple(sorted(CONVERTERS))

# Ops that are accepted only when folded away (Shape/Size need a static input shape).
FOLDED_OPS = "Constant, ConstantOfShape, Shape, Size and any other op whose inputs are all constants"
