"""Graph IR: the ONNX model after import, with static shapes, folded constants and typed attributes.

Stage 1 of the pipeline (ONNX -> graph IR -> graph passes -> loop-nest IR -> loop passes -> backend).
Every value has a static shape and a dtype (float32 unless Graph.dtypes says otherwise: the int8
path); every constant is a numpy array, float32 but for the integer weights of the quantized ops;
every node carries one
frozen attribute record with ONNX defaults already filled in, so passes and lowerings never look
at raw ONNX attributes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TypeVar, Union

import numpy as np

from .arrays import same_arrays
from .kinds import ActivationKind, ConvAlgorithm, DType, GeluApproximation, VectorAxis, coerce

Shape = tuple[int, ...]


@dataclass(frozen=True)
class Activation:
    """A pointwise activation that a producer applies at its store: relu, leaky_relu with slope
    alpha, clip to [low, high] (ReLU6 is clip(0, 6)), sigmoid, tanh, hard_sigmoid
    max(0, min(1, alpha*x + beta)), hard_swish x * hard_sigmoid(x) (ONNX's has alpha 1/6 and beta 0.5),
    elu with scale alpha, silu x * sigmoid(x) (SiLU, Swish), erf, gelu x * Phi(x), exact or with
    the tanh approximation (`approximate`), abs, neg, sqrt, exp, log, reciprocal, pow x^alpha (a
    constant exponent), softplus log(1 + exp(x)), softsign x / (1 + |x|), mish x tanh(softplus(x)),
    selu gamma * elu(alpha), celu max(0, x) + min(0, alpha (exp(x / alpha) - 1)) and
    thresholded_relu x > alpha ? x : 0."""

    kind: ActivationKind
    alpha: float = 0.0
    low: float = float("-inf")
    high: float = float("inf")
    beta: float = 0.0
    approximate: GeluApproximation = GeluApproximation.NONE
    gamma: float = 0.0

    def __post_init__(self) -> None:
        coerce(self, kind=ActivationKind, approximate=GeluApproximation)

    def __str__(self) -> str:
        if self.kind == "clip":
            return f"clip({self.low:g}, {self.high:g})"
        if self.kind == "hard_sigmoid" or (self.kind == "hard_swish" and (self.alpha, self.beta) != (1 / 6, 0.5)):
            return f"{self.kind}(alpha={self.alpha:g}, beta={self.beta:g})"
        if self.kind in ("leaky_relu", "elu", "pow", "celu", "thresholded_relu"):
            return f"{self.kind}(alpha={self.alpha:g})"
        if self.kind == "selu":
            return f"selu(alpha={self.alpha:g}, gamma={self.gamma:g})"
        if self.kind == "gelu" and self.approximate != "none":
            return f"gelu(approximate={self.approximate})"
        return str(self.kind)


@dataclass(frozen=True)
class ConvAttrs:
    """Conv over len(kernel) spatial dims; pads already resolved from auto_pad, begin and end apart.

    Inputs x, w [C_out, C_in/group, k...], optionally b [C_out], then with `residual` a tensor of
    the output's shape added at the store before the activation (a fused ResNet shortcut). w and b
    are constant or computed at runtime."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    group: int = 1
    activation: Activation | None = None
    residual: bool = False
    algorithm: ConvAlgorithm = ConvAlgorithm.DIRECT  # set by the winograd pass
    gemm_channels: int = 0  # Winograd: output channels padded to this many in its GEMMs (0: not padded)
    vector_axis: VectorAxis = VectorAxis.CHANNELS  # set by the vectorize-pixels pass, read by the lowering
    # Set by the vectorize-pixels pass for a planar input: the reduction loops over the input channels
    # (planes) outside the taps along a row instead of inside them.
    planes_outside_row: bool = False
    # Set by the cache-block pass: weights packed in panels of `panel` output channels, the reduction
    # done `ci_block` input channels at a time (0: not blocked / all input channels at once).
    panel: int = 0
    ci_block: int = 0
    # Set by the cache-block pass for a depthwise Conv: computed this many channels at a time outside its
    # pixel loops, each block's weights packed together (0: channels innermost).
    channel_block: int = 0

    def __post_init__(self) -> None:
        coerce(self, algorithm=ConvAlgorithm, vector_axis=VectorAxis)


@dataclass(frozen=True)
class ConvTransposeAttrs:
    """ConvTranspose: inputs x, w [C_in, C_out/group, k...] and optionally b [C_out], constant or
    runtime. Output o reads input i where o = i*stride + k*dilation - pad_begin; output_padding and
    output_shape are resolved into the pads and the output shape in Graph.shapes."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    group: int = 1


@dataclass(frozen=True)
class PoolAttrs:
    """MaxPool and AveragePool (also their Global forms); the output shape (ceil_mode included) is
    recorded in Graph.shapes. count_include_pad: AveragePool divides by the padded window size."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    ceil_mode: bool = False
    count_include_pad: bool = False


@dataclass(frozen=True)
class BatchNormAttrs:
    """Inference BatchNormalization: inputs are x, scale, bias, mean, var; statistics that are
    computed at runtime keep the node to the lowering, constant ones are folded."""

    epsilon: float = 1e-5


@dataclass(frozen=True)
class ScaleShiftAttrs:
    """y = x * scale[c] + shift[c] over axis 1 (a BatchNorm that had no producer to fold into)."""

    activation: Activation | None = None


@dataclass(frozen=True)
class DenseAttrs:
    """y[m, n] = alpha * sum_k x[m, k] * w[k, n] + beta * b[m, n]; inputs x, w and optionally b.

    x may have rank > 2: all leading dims are rows. trans_x reads x as [K, M] (Gemm transA=1).
    w is [K, N] ([N, K] with trans_w) or batched [..., K, N] (MatMul), its batch dims broadcast
    against x's leading dims. b broadcasts to the output (NumPy rules). The front end folds
    alpha, beta and transB into constant operands, so they differ from their defaults only when
    the operand they apply to is computed at runtime.
    """

    trans_x: bool = False
    activation: Activation | None = None
    trans_w: bool = False
    alpha: float = 1.0
    beta: float = 1.0
    panel: int = 0  # set by the cache-block pass: w packed in panels of this many columns (0: not packed)
    streams: int = 1  # set by the cache-block pass: segments of the reduction a panel reads side by side


@dataclass(frozen=True)
class SoftmaxAttrs:
    """Softmax along `axis`; coerce_2d is the opset < 13 meaning (flatten to 2-D at axis)."""

    axis: int
    coerce_2d: bool = False


@dataclass(frozen=True)
class LrnAttrs:
    """Local response normalisation across channels (axis 1):
    y = x / (bias + alpha / size * sum of x^2 over the `size` channels around c) ** beta."""

    size: int
    alpha: float = 1e-4
    beta: float = 0.75
    bias: float = 1.0


@dataclass(frozen=True)
class ReduceAttrs:
    """A reduction (ReduceSum, ReduceMean, ReduceMax, ...: the op says which) over `axes` (sorted,
    non-negative; none: each element alone, ReduceL2's |x|); keepdims keeps them as size 1."""

    axes: Shape
    keepdims: bool = True


@dataclass(frozen=True)
class ArgMaxAttrs:
    """ArgMax / ArgMin along `axis` (non-negative): the index of the first extreme element (the last
    with select_last_index), written as int32."""

    axis: int
    keepdims: bool = True
    select_last_index: bool = False


@dataclass(frozen=True)
class NormAttrs:
    """InstanceNormalization, GroupNormalization, LayerNormalization (inference):
    y = (x - mean) / sqrt(var + epsilon) * scale + bias, with the mean and biased variance of each
    set of elements normalised together. Layer: per index of the dims before `axis`, over the dims
    from `axis` on; scale and bias broadcast to those dims, bias optional. Group and Instance: per
    (n, group of channels), over its channels and the spatial dims (`groups` groups; Instance has
    one per channel); scale and bias per channel. Inputs x, scale[, bias]; outputs y, then
    LayerNormalization's mean and 1 / sqrt(var + epsilon) per group where `mean_output` and
    `inv_std_output` say they are used. `activation` is applied to y at its store (fuse-activation)."""

    epsilon: float = 1e-5
    axis: int = 1
    groups: int = 1
    mean_output: bool = False
    inv_std_output: bool = False
    activation: Activation | None = None


@dataclass(frozen=True)
class ReshapeAttrs:
    """Reshape, Flatten, Squeeze, Unsqueeze: the row-major element order is kept, shape changes."""

    shape: Shape


@dataclass(frozen=True)
class ConcatAttrs:
    """Concat along `axis` (non-negative); any input may be a constant."""

    axis: int


@dataclass(frozen=True)
class SliceAttrs:
    """y[i] = x[starts + steps * i] per dim, every dim listed (steps may be negative); the output
    shape in Graph.shapes gives the count per dim, so starts are already clamped."""

    starts: Shape
    steps: Shape


@dataclass(frozen=True)
class SplitAttrs:
    """Split along `axis`: output k (only the used outputs are listed) is x[starts[k]:] on that axis,
    as long as its shape in Graph.shapes says."""

    axis: int
    starts: Shape


@dataclass(frozen=True)
class TransposeAttrs:
    """y's dim k is x's dim perm[k]."""

    perm: Shape


@dataclass(frozen=True)
class TileAttrs:
    """Tile and Expand: y[i] = x[i mod x's extent] per dim, the output `repeats` times x's extent
    (x has the output's rank; Expand's broadcasting is a repeat of its size-1 dims)."""

    repeats: Shape


@dataclass(frozen=True)
class GatherAttrs:
    """Gather along `axis` at constant indices (non-negative, inside the axis): y[..., j, ...] =
    x[..., indices[j], ...]; the indices' own shape is a Reshape after this node."""

    axis: int
    indices: Shape


@dataclass(frozen=True)
class PadAttrs:
    """Pad each dim by pads_begin/pads_end (negative: crop). mode: constant (with `value`, or the
    one element of the node's second input when the value comes at run time), reflect (mirror
    without repeating the border), edge (repeat the border) or wrap (periodic)."""

    pads_begin: Shape
    pads_end: Shape
    mode: str = "constant"
    value: float = 0.0


@dataclass(frozen=True)
class ResizeAttrs:
    """Resize and Upsample: output coordinate o of dim d maps to input coordinate
    transform(o, scales[d]) (coordinate_transformation_mode as in ONNX Resize); mode nearest picks one
    input by nearest_mode ("simple" is Resize-10/Upsample: floor when enlarging, ceil when shrinking),
    linear interpolates between the two neighbours, cubic between four (Keys' kernel with
    cubic_coeff_a). With antialias, linear and cubic stretch their kernel by 1/scale when shrinking;
    exclude_outside drops taps outside the input and renormalises. tf_crop_and_resize maps the output
    onto roi (start, end) of each dim, in input-length units, and writes extrapolation_value where
    that reaches outside the input. Output shape in Graph.shapes."""

    scales: tuple[float, ...]
    mode: str = "nearest"
    coordinate_transformation_mode: str = "half_pixel"
    nearest_mode: str = "round_prefer_floor"
    cubic_coeff_a: float = -0.75
    exclude_outside: bool = False
    antialias: bool = False
    roi: tuple[tuple[float, float], ...] = ()
    extrapolation_value: float = 0.0


@dataclass(frozen=True)
class QuantAttrs:
    """QuantizeLinear (float -> dtype) and DequantizeLinear (dtype -> float) of one tensor:
    real = (q - zero_point) * scale, per tensor."""

    scale: float
    zero_point: int
    dtype: DType

    def __post_init__(self) -> None:
        coerce(self, dtype=DType)


@dataclass(frozen=True)
class Requantization:
    """How an integer op writes its output: the int32 result, scaled (per output channel where the
    op has a multipliers input), rounded and offset by zero_point, clamped to [low, high] (the
    type's range, or narrower where a Relu or Clip was folded into it), as dtype."""

    zero_point: int
    low: int
    high: int
    dtype: DType

    def __post_init__(self) -> None:
        coerce(self, dtype=DType)

    def __str__(self) -> str:
        return f"{self.dtype}(zero_point={self.zero_point}, {self.low}..{self.high})"


_Window = TypeVar("_Window", bound="IntegerWindow")


@dataclass(frozen=True)
class IntegerWindow:
    """The window of an integer convolution and its input's zero point: what QLinearConv
    (QConvAttrs) and a dequantised ConvInteger (IntegerConvAttrs) share."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    group: int
    x_zero_point: int

    @classmethod
    def of(cls: type[_Window], geometry: ConvAttrs, x_zero_point: int, *rest: object) -> _Window:
        """The record of `geometry`'s window (a Conv's, from the front end) and the input zero
        point, then the subclass's own fields `rest` in order."""
        g = geometry
        return cls(g.kernel, g.strides, g.dilations, g.pads_begin, g.pads_end, g.group, x_zero_point, *rest)


@dataclass(frozen=True)
class QConvAttrs(IntegerWindow):
    """QLinearConv: inputs x (int8/uint8), w [C_out, C_in/group, k...] (constant, int8, or int16
    when its zero point is not 0 and was subtracted), b [C_out] (int32 constant) and the
    multipliers [C_out] (float32 constant: x_scale * w_scale / y_scale). The accumulator is
    b + sum (x - x_zero_point) * w over the taps inside the image (a padded tap reads the zero
    point: it adds 0)."""

    out: Requantization
    algorithm: ConvAlgorithm = ConvAlgorithm.DIRECT  # set by the winograd pass

    def __post_init__(self) -> None:
        coerce(self, algorithm=ConvAlgorithm)


@dataclass(frozen=True)
class QDenseAttrs:
    """QLinearMatMul and Gemm in QDQ form: inputs x [M, K] (int8/uint8), w [K, N] (constant, as
    QConvAttrs's w), b [N] (int32) and the multipliers [N]."""

    x_zero_point: int
    out: Requantization


@dataclass(frozen=True)
class IntegerConvAttrs(IntegerWindow):
    """ConvInteger: inputs x (int8/uint8), w (as QConvAttrs's), b [C_out] (int32 constant: 0, or
    the zero point folded in). Its int32 result b + sum (x - x_zero_point) * w is the output as it
    is, or, when `dequantized` (frontend/qdq.py fused the Cast, Mul and Add that read it), two more
    float32 constants follow: scale [C_out] and, when `biased`, bias [C_out]; the output is then
    float32(sum) * scale (+ bias), each step rounded to float32 as onnxruntime's Cast, Mul and Add
    round it."""

    biased: bool
    dequantized: bool = True


@dataclass(frozen=True)
class IntegerDenseAttrs:
    """MatMulInteger of x [M, K] and w [K, N], with b [N] (then scale and bias [N] when
    `dequantized`), as IntegerConvAttrs's. The output has M * N elements: [M, N], or the shape of
    a batched MatMulInteger's result (its rows the batches' rows in order, x made [M, K] by a Reshape)."""

    x_zero_point: int
    biased: bool
    dequantized: bool = True


@dataclass(frozen=True)
class QBinaryAttrs:
    """QLinearAdd and QLinearMul of two tensors, NumPy-broadcast: a_scale (a - a_zp) + b_scale (b - b_zp),
    or the product (a - a_zp) (b - b_zp) a_scale b_scale, over y_scale plus y_zp, computed as
    onnxruntime's x86 kernels do (lowering/quantized_add.py, lowering/quantized_mul.py)."""

    a_scale: float
    a_zero_point: int
    b_scale: float
    b_zero_point: int
    y_scale: float
    out: Requantization


@dataclass(frozen=True)
class QPoolAttrs:
    """QLinearGlobalAveragePool: the int32 sum of each channel minus N * x_zero_point, times
    x_scale / (y_scale * N) (N: the pixels of a channel), requantized."""

    x_scale: float
    x_zero_point: int
    y_scale: float
    out: Requantization


@dataclass(frozen=True)
class QAveragePoolAttrs:
    """QLinearAveragePool as onnxruntime computes it: per window the float32 sum of the dequantized
    taps inside the input, divided by the tap count, then y = sum / y_scale + y_zero_point rounded.
    zero_point_offset: 128 where onnxruntime computes an int8 QDQ pool in uint8 (its QDQ transformer
    adds 128 to int8 tensors and zero points on x86), which changes how y_zero_point + 128 rounds
    in float; the result is 128 less."""

    pool: PoolAttrs
    x_scale: float
    x_zero_point: int
    y_scale: float
    out: Requantization
    zero_point_offset: int = 0


@dataclass(frozen=True)
class QSoftmaxAttrs:
    """onnxruntime's QLinearSoftmax (its second input is the float32 table of exp values, see
    lowering/quantized_softmax.py): along `softmax` (its axis and opset meaning), each element's
    table entry times y_multiplier (floor(1 / y_scale)) over the row's sum, rounded and offset by
    the output zero point, saturated."""

    softmax: SoftmaxAttrs
    y_multiplier: float
    out: Requantization


@dataclass(frozen=True)
class QLookupAttrs:
    """A unary op on an int8/uint8 tensor as a table (its second input: 256 constant entries of the
    output type, indexed by the input value minus the input type's lowest), computed at generation
    time as onnxruntime computes its QLinearLeakyRelu and QLinearSigmoid (frontend/ops_qlookup.py).
    `function` names the op the table computes; `dtype` is the output type."""

    function: str
    dtype: DType

    def __post_init__(self) -> None:
        coerce(self, dtype=DType)


# Every attribute record a node may carry.
AttrRecord = Union[
    Activation, ConvAttrs, ConvTransposeAttrs, PoolAttrs, BatchNormAttrs, ScaleShiftAttrs, DenseAttrs,
    SoftmaxAttrs, LrnAttrs, ReduceAttrs, ArgMaxAttrs, NormAttrs, ReshapeAttrs, ConcatAttrs, SliceAttrs,
    SplitAttrs, TransposeAttrs, TileAttrs, GatherAttrs, PadAttrs, ResizeAttrs, QuantAttrs, QConvAttrs,
    QDenseAttrs, QBinaryAttrs, QPoolAttrs, QAveragePoolAttrs, QSoftmaxAttrs, QLookupAttrs, IntegerConvAttrs,
    IntegerDenseAttrs,
]  # fmt: skip


@dataclass(frozen=True)
class Value:
    """A graph input or output: a float32 tensor with a static shape."""

    name: str
    shape: Shape


@dataclass(frozen=True)
class Node:
    op: str
    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    attrs: AttrRecord | None = None  # the record nncg.ir.ops.IR_OPS names for `op` (the verifier checks)

    # The graph passes' choices for a float Conv (ConvAttrs), read by planners that see every op.
    @property
    def runs_winograd(self) -> bool:
        """A Conv, or a QLinearConv (integer Winograd), the winograd pass made Winograd."""
        return isinstance(self.attrs, ConvAttrs | QConvAttrs) and self.attrs.algorithm == ConvAlgorithm.WINOGRAD

    @property
    def vectorises_pixels(self) -> bool:
        """Written planar (channels first), not channels last: the vectorize-pixels pass's choice."""
        return isinstance(self.attrs, ConvAttrs) and self.attrs.vector_axis == VectorAxis.PIXELS

    @property
    def cache_blocked(self) -> bool:
        return isinstance(self.attrs, ConvAttrs) and self.attrs.panel > 0


@dataclass(frozen=True)
class Graph:
    """Nodes in topological order. `shapes` holds the shape of every non-constant value, `dtypes`
    the dtype of every non-constant value that is not float32 (a constant's is its array's)."""

    name: str
    inputs: tuple[Value, ...]
    outputs: tuple[Value, ...]
    nodes: tuple[Node, ...]
    constants: dict[str, np.ndarray] = field(default_factory=dict)
    shapes: dict[str, Shape] = field(default_factory=dict)
    dtypes: dict[str, DType] = field(default_factory=dict)

    def __eq__(self, other: object) -> bool:
        """Structural equality, constants included (same names, dtypes, shapes and values)."""
        if not isinstance(other, Graph):
            return NotImplemented
        same = (self.name, self.inputs, self.outputs, self.nodes, self.shapes, self.dtypes)
        return same == (
            other.name, other.inputs, other.outputs, other.nodes, other.shapes, other.dtypes
        ) and same_arrays(self.constants, other.constants)  # fmt: skip

    def is_constant(self, name: str) -> bool:
        return name in self.constants

    def dtype(self, name: str) -> DType:
        if name in self.constants:
            return DType(self.constants[name].dtype.name)
        return self.dtypes.get(name, DType.FLOAT32)

    def shape(self, name: str) -> Shape:
        if name in self.constants:
            return tuple(self.constants[name].shape)
        return self.shapes[name]

    def producer(self, name: str) -> Node | None:
        for node in self.nodes:
            if name in node.outputs:
                return node
        return None

    def consumers(self, name: str) -> list[Node]:
        return [node for node in self.nodes if name in node.inputs]

    def is_graph_output(self, name: str) -> bool:
        return any(v.name == name for v in self.outputs)

    def with_nodes(self, nodes, constants: dict[str, np.ndarray] | None = None) -> Graph:
        """A copy with new nodes (and constants), dropping constants and shapes no node uses."""
        nodes = tuple(nodes)
        constants = dict(self.constants if constants is None else constants)
        used = {name for node in nodes for name in (*node.inputs, *node.outputs)}
        used |= {v.name for v in (*self.inputs, *self.outputs)}
        return replace(
            self,
            nodes=nodes,
            constants={k: v for k, v in constants.items() if k in used},
            shapes={k: v for k, v in self.shapes.items() if k in used},
            dtypes={k: v for k, v in self.dtypes.items() if k in used},
        )
