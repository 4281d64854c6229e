"""Lowering: graph IR -> loop-nest IR. One module per op family; this driver assigns buffers.

Graph inputs and outputs are row-major (ONNX NCHW) buffers passed by the caller; internal
activations get the layout their producer prefers (channels-last for Conv and MaxPool)."""

from __future__ import annotations

from ..errors import NncgError
from ..ir.c_names import program_name
from ..ir.graph import Graph, Node
from ..ir.kinds import ConvAlgorithm
from ..ir.loops import Program, StoredValue
from ..ir.ops import REDUCE_OPS
from ..ir.target import Target
from .band_plan import plan_layers
from .bands import BandGroup
from .concat import lower_concat
from .context import LoweringContext, TensorRef, row_major
from .conv import lower_conv
from .conv_blocked import lower_blocked_conv
from .conv_transpose import lower_conv_transpose
from .dense import lower_dense
from .elementwise import (
    lower_activation,
    lower_batchnorm,
    lower_binary,
    lower_pow_per_element,
    lower_prelu,
    lower_scale_shift,
    lower_where,
)
from .gather import lower_gather
from .in_place import lower_in_place_depthwise
from .integer_products import lower_conv_integer, lower_matmul_integer
from .lrn import lower_lrn
from .normalization import lower_normalization
from .pad import lower_pad
from .pool import lower_averagepool
from .quantized import (
    lower_any_maxpool,
    lower_dequantize_linear,
    lower_qlinear_average_pool,
    lower_qlinear_conv,
    lower_qlinear_dense,
    lower_qlinear_global_average_pool,
    lower_quantize_linear,
)
from .quantized_add import lower_qlinear_add
from .quantized_lookup import lower_qlinear_lookup
from .quantized_mul import lower_qlinear_mul
from .quantized_softmax import lower_qlinear_softmax
from .reduce import lower_arg_extreme, lower_reduce
from .reshape import copy_nest, lower_reshape
from .resize import lower_resize
from .slice import lower_slice, lower_split
from .softmax import lower_log_softmax, lower_softmax
from .stream import band_values, lower_band_group
from .tile import lower_tile
from .transpose import lower_transpose
from .winograd import lower_winograd
from .winograd_integer import lower_integer_winograd


def lower_any_conv(ctx: LoweringContext, node: Node) -> None:
    """Direct convolution (cache-blocked where the cache-block pass chose it), or Winograd where the
    winograd pass chose it."""
    if node.attrs.algorithm == ConvAlgorithm.WINOGRAD:
        lower_winograd(ctx, node)
    elif node.attrs.panel:
        lower_blocked_conv(ctx, node)
    else:
        lower_conv(ctx, node)


def lower_any_qlinear_conv(ctx: LoweringContext, node: Node) -> None:
    """Direct integer convolution, or integer Winograd where the winograd pass chose it."""
    if node.attrs.algorithm == ConvAlgorithm.WINOGRAD:
        lower_integer_winograd(ctx, node)
    else:
        lower_qlinear_conv(ctx, node)


LOWERINGS = {
    "Conv": lower_any_conv,
    "ConvTranspose": lower_conv_transpose,
    "MaxPool": lower_any_maxpool,
    "AveragePool": lower_averagepool,
    "Relu": lower_activation,
    "Clip": lower_activation,
    "LeakyRelu": lower_activation,
    "BatchNormalization": lower_batchnorm,
    "ScaleShift": lower_scale_shift,
    "Dense": lower_dense,
    "Softmax": lower_softmax,
    "Reshape": lower_reshape,
    "Identity": lower_reshape,
    "Add": lower_binary,
    "Sub": lower_binary,
    "Mul": lower_binary,
    "Div": lower_binary,
    "Concat": lower_concat,
    "Slice": lower_slice,
    "Split": lower_split,
    "Transpose": lower_transpose,
    "Tile": lower_tile,
    "Gather": lower_gather,
    "Where": lower_where,
    "Pad": lower_pad,
    "Resize": lower_resize,
    "Sigmoid": lower_activation,
    "Tanh": lower_activation,
    "HardSigmoid": lower_activation,
    "HardSwish": lower_activation,
    "Elu": lower_activation,
    "Silu": lower_activation,
    "Erf": lower_activation,
    "Gelu": lower_activation,
    "Abs": lower_activation,
    "Neg": lower_activation,
    "Sqrt": lower_activation,
    "Exp": lower_activation,
    "Log": lower_activation,
    "Reciprocal": lower_activation,
    "Pow": lower_activation,
    "Softplus": lower_activation,
    "Softsign": lower_activation,
    "Mish": lower_activation,
    "Selu": lower_activation,
    "Celu": lower_activation,
    "ThresholdedRelu": lower_activation,
    "PRelu": lower_prelu,
    "PowPerElement": lower_pow_per_element,
    "Max": lower_binary,
    "Min": lower_binary,
    "Sum": lower_binary,
    "LogSoftmax": lower_log_softmax,
    "LRN": lower_lrn,
    **dict.fromkeys(REDUCE_OPS, lower_reduce),
    "ArgMax": lower_arg_extreme,
    "ArgMin": lower_arg_extreme,
    "InstanceNormalization": lower_normalization,
    "GroupNormalization": lower_normalization,
    "LayerNormalization": lower_normalization,
    "QuantizeLinear": lower_quantize_linear,
    "DequantizeLinear": lower_dequantize_linear,
    "QLinearConv": lower_any_qlinear_conv,
    "QLinearDense": lower_qlinear_dense,
    "QLinearAdd": lower_qlinear_add,
    "QLinearGlobalAveragePool": lower_qlinear_global_average_pool,
    "QLinearAveragePool": lower_qlinear_average_pool,
    "QLinearSoftmax": lower_qlinear_softmax,
    "QLinearLookup": lower_qlinear_lookup,
    "QLinearMul": lower_qlinear_mul,
    "ConvInteger": lower_conv_integer,
    "MatMulInteger": lower_matmul_integer,
}


def lower(
    graph: Graph,
    function_name: str | None = None,
    halos: bool | str = "auto",
    memory: str = "speed",
    budget: int = 0,
    requantize: str = "float",
    target: Target | None = None,
) -> Program:
    """`halos`: store tensors that only padded Convs read inside a zero border (see halo.py). `auto`
    (the default) does it only where the readers are cache-blocked Convs: it removes every border
    check, which on a small image is every pixel (resnet18's layer4 at 96x96, avx2: 1860 -> 1400 us),
    but for the other layers gcc's code came out as often slower as faster (robot avx2 -2 %,
    pedestrian ssse3 +23 %). true: for every padded Conv; false: never. `memory` (speed, balanced,
    min) and `budget` (bytes; 0: none) choose the layers run in bands (see band_plan.py), priced for
    `target` (None: 4-lane vector figures) under `requantize`, which is
    how the integer ops of an int8 model scale their results, `float` (onnxruntime's arithmetic) or
    `fixed` (integers only, see lowering/requantize.py)."""
    name = program_name(function_name or graph.name)
    ctx = LoweringContext(graph, name, halos, requantize)
    plan = plan_layers(graph, memory, budget, target, requantize)
    groups = {group.nodes[0]: group for group in plan.groups}
    by_name = {node.name: node for node in graph.nodes}
    banded = {name for group in plan.groups for name in group.nodes}
    # a line buffer has no halo; a group's output neither, as it would only add memory
    unbordered = band_values(graph, plan.groups)
    ctx.halos = {value: halo for value, halo in ctx.halos.items() if value not in unbordered}
    for node in graph.nodes:  # not where halos=true gives a tensor a zero border the plan did not count
        if node.name in plan.in_place and not {node.inputs[0], node.outputs[0]} & ctx.halos.keys():
            ctx.in_place[node.outputs[0]] = (node.inputs[0], node.attrs.pads_begin[0] + 1)
    in_place = {name for name in plan.in_place if by_name[name].outputs[0] in ctx.in_place}
    for value in graph.inputs:
        order = row_major(len(value.shape))
        ctx.refs[value.name] = ctx.add_buffer(
            value.name, "input", value.shape, order, value.name, graph.dtype(value.name)
        )
    outputs = {}
    for value in graph.outputs:
        outputs[value.name] = ctx.add_buffer(
            value.name, "output", value.shape, row_major(len(value.shape)), value.name, graph.dtype(value.name)
        )
        if value.name not in ctx.refs:  # an input that is also an output is copied, not aliased
            ctx.refs[value.name] = outputs[value.name]
    stored = []
    ends = {group.nodes[-1] for group in groups.values()}
    for node in graph.nodes:
        if node.name in groups:
            _lower_group(ctx, groups[node.name])
        elif node.name in in_place:
            lower_in_place_depthwise(ctx, node)
        elif node.name not in banded:
            _lower_node(ctx, node)
        if node.name not in banded or node.name in ends:  # a line buffer holds no whole value to read back
            stored += _stored_values(ctx, node)
    for value, target in outputs.items():
        if ctx.refs[value] != target:
            ctx.emit_helper(f"copy_{value}", "Copy", copy_nest(ctx.refs[value], target))
    return Program(name, tuple(ctx.buffers), tuple(ctx.kernels), ctx.constants, values=tuple(stored))


def _stored_values(ctx: LoweringContext, node: Node) -> list[StoredValue]:
    """Where the node's outputs live, complete after the last kernel so far (none before the first
    kernel: a relabelled input has nothing to read back)."""
    if not ctx.kernels:
        return []
    layer = ctx.kernels[-1].name
    refs = {value: ctx.refs[value] for value in node.outputs if value in ctx.refs}
    return [StoredValue(v, r.buffer, r.shape, r.order, _stored_halo(r), layer) for v, r in refs.items()]


def _stored_halo(ref: TensorRef) -> tuple[tuple[int, int], ...]:
    """The rows before a tensor with a lead (one image, no halo) read back as a halo above it."""
    return ((0, 0), (0, 0), (ref.lead, 0), (0, 0)) if ref.lead else ref.halo


def _lower_node(ctx: LoweringContext, node: Node) -> None:
    lowering = LOWERINGS.get(node.op)
    if lowering is None:
        raise NncgError(f"no lowering for op {node.op} (node '{node.name}'); supported: {', '.join(LOWERINGS)}")
    lowering(ctx, node)
    _emit_pending_copies(ctx, node.name)


def _lower_group(ctx: LoweringContext, group: BandGroup) -> None:
    lower_band_group(ctx, group)
    _emit_pending_copies(ctx, group.nodes[-1])


def _emit_pending_copies(ctx: LoweringContext, layer: str) -> None:
    for value, temp, target in ctx.pending_copies:
        ctx.emit_helper(f"{layer}_to_{value}", "Copy", copy_nest(temp, target))
    ctx.pending_copies.clear()
