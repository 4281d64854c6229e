"""In-place depthwise convolution: a stride-1 depthwise Conv, float or int8 (QLinearConv), writes its
output over its input.

Output row `oh` reads input rows oh - pad .. oh - pad + k - 1, so once it is computed, the rows
before oh - pad are dead. The input is stored `lead` = pad + 1 rows down in a buffer H + lead rows
high, and the output written from the buffer's first row: output row oh overwrites input row
oh - lead, which no later output row reads, nor the row being computed (so no column order inside
a row matters). The row loop runs in order (it is marked serial, so no pass interleaves it). The
layer then needs H + lead rows instead of 2 H. The band planner (band_plan.py) takes it where it
lowers the memory a plan needs; the kernel is the usual direct one (conv.py), one buffer read and
written, so its pointers never overlap (for int8, quantized.py's integer_conv: a depthwise layer
folds no zero point, so no tap outside the image is read)."""

from __future__ import annotations

from dataclasses import replace

from ..errors import NncgError
from ..ir.graph import ConvAttrs, Graph, Node
from ..ir.loops import Loop
from .bands import WINDOWED
from .context import LoweringContext
from .conv import lower_conv
from .quantized import lower_qlinear_conv

CHANNELS_LAST = (0, 2, 3, 1)
LOWERINGS = {"Conv": lower_conv, "QLinearConv": lower_qlinear_conv}


def in_place_lead(graph: Graph, node: Node, readers: dict[str, int], index: int, halos) -> int:
    """The rows the input of depthwise Conv `node` (graph index `index`) is stored down for its
    output to overwrite it (0: it cannot): a 2-D stride-1 undilated depthwise Conv or QLinearConv, a
    batch of one, output shaped and typed as the input, no fused residual, whose input dies here and
    was written channels last by a convolution or pooling layer, neither tensor a graph output nor
    stored with a zero halo."""
    if node.op not in LOWERINGS or len(node.attrs.kernel) != 2 or len(node.outputs) != 1:
        return 0
    attrs, x, y = node.attrs, node.inputs[0], node.outputs[0]
    shape = graph.shape(x)
    depthwise = attrs.group == shape[1] == graph.shape(node.inputs[1])[0] and graph.shape(node.inputs[1])[1] == 1
    plain = attrs.strides == (1, 1) and attrs.dilations == (1, 1) and not node.vectorises_pixels
    producer = graph.producer(x)
    written = producer is not None and producer.op in WINDOWED and not producer.vectorises_pixels
    if not (depthwise and plain and written and shape[0] == 1 and graph.shape(y) == shape):
        return 0
    if readers.get(x) != index or any(graph.is_graph_output(v) for v in (x, y)) or x in halos or y in halos:
        return 0
    residual = node.op == "Conv" and attrs.residual  # a QLinearConv has none
    if residual or graph.dtype(x) != graph.dtype(y):  # a residual would be written over instead
        return 0
    return attrs.pads_begin[0] + 1


def lower_in_place_depthwise(ctx: LoweringContext, node: Node) -> None:
    """The Conv's or QLinearConv's kernel, writing over its input (stored `lead` rows down by ctx.output)."""
    x = ctx.refs[node.inputs[0]]
    if x.lead != node.attrs.pads_begin[0] + 1 or x.order != CHANNELS_LAST or x.halo:
        raise NncgError(f"the input of in-place depthwise Conv '{node.name}' is not stored for it")
    start = len(ctx.kernels)
    if isinstance(node.attrs, ConvAttrs):  # rows outermost: channel blocks would sweep every row per block
        node = replace(node, attrs=replace(node.attrs, channel_block=0))
    LOWERINGS[node.op](ctx, node)
    kernel = ctx.kernels[start]
    rows = kernel.body[0] if len(kernel.body) == 1 else None
    if not isinstance(rows, Loop) or rows.var != "oh" or len(ctx.kernels) != start + 1:
        raise NncgError(f"in-place depthwise Conv '{node.name}' has no single output-row loop")
    ctx.kernels[start] = replace(kernel, body=(replace(rows, parallel=False),))
