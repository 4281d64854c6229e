"""Graph pass `vectorize-pixels{layers=conv1:true;conv2:false}`: SIMD over output pixels.

Vectorising over output channels (the default) leaves a wide vector part empty when a layer has
few of them: 3 channels fill 3 of 16 lanes. Such a layer can instead be lowered with a planar
(NCHW) output whose rows are innermost: vectorize then runs along the row, every lane busy, the
weight broadcast and the input loaded as a vector, and register-block jams output channels x row
vectors. That needs an input whose rows are contiguous too (planar: the graph input, or another
such layer's output) and stride 1 along them. A padded layer gets its padding as an explicit Pad
node (a planar copy inside a zero border), so its rows have no border columns, which would each be
a scalar iteration per row.

The output stays planar: a consumer that vectorises over channels (a MaxPool, a channels-last Conv)
then reads it element by element, and pays for the layer's gain. The cost model takes the pixel
axis where the gain is large (see chosen_by_cost_model); `layers` overrides it per layer, and
`--tune` decides by timing the whole model, consumers included.

A Conv that reads a planar tensor but keeps the channel axis (a stem: stride 2, 3 input channels)
gets `planes_outside_row` where it pays (see planes_outside_row_pays): its reduction
loops over the input channels outside the taps along a row, so the innermost loop walks a plane's
row rather than 3 planes. Inside, with the few input channels unrolled, the row-tap loop was
innermost and its pixels' taps overlap (stride 2, 3 taps): gcc -O3 carries the overlapping input
values from one tap to the next (predictive commoning) and spills the register block for it
(avx512 mobilenet_v2-shaped stem: 20 accumulators, 18 carried scalars stored to the stack)."""

from __future__ import annotations

from dataclasses import replace

from ..errors import NncgError
from ..ir.graph import ConvAttrs, Graph, Node, PadAttrs
from ..ir.kinds import ConvAlgorithm, VectorAxis
from ..ir.names import fresh_name
from ..ir.target import Target
from .per_layer import check_layer_names, parse_layer_map
from .plan_memory import parse_bool

MIN_ROW_VECTORS = 4


def parse_layers(text: str) -> dict[str, bool]:
    """`conv1:true;conv2:false` -> {"conv1": True, "conv2": False}."""
    return parse_layer_map(text, parse_bool, "conv1:true;conv2:false")


def vectorize_pixels(graph: Graph, target: Target, layers: dict[str, bool] | None = None) -> Graph:
    lanes = target.vector_widths or (1,)
    layers = layers or {}
    check_layer_names(graph, layers, "vectorize-pixels")
    planar = {value.name for value in graph.inputs}
    nodes: list[Node] = []
    shapes = dict(graph.shapes)
    for node in graph.nodes:
        wanted = layers.get(node.name)
        applies = pixel_axis_applies(graph, node, planar)
        if wanted and not applies:
            raise NncgError(
                f"vectorize-pixels: layer {node.name} is not a direct Conv with stride 1 along its rows "
                "reading a planar tensor (the graph input or another pixel-vectorised layer's output)"
            )
        if applies and (chosen_by_cost_model(graph, node, lanes) if wanted is None else wanted):
            if any(node.attrs.pads_begin) or any(node.attrs.pads_end):
                pad, node = explicit_padding(graph, node, shapes)
                nodes.append(pad)
            node = replace(node, attrs=replace(node.attrs, vector_axis=VectorAxis.PIXELS))
            planar.add(node.outputs[0])
        elif planes_outside_row_pays(graph, node, planar, target):
            node = replace(node, attrs=replace(node.attrs, planes_outside_row=True))
        nodes.append(node)
    return replace(graph, shapes=shapes).with_nodes(nodes)


def explicit_padding(graph: Graph, node: Node, shapes: dict) -> tuple[Node, Node]:
    """A Pad node writing the conv's input inside its zero padding, and the conv reading that."""
    attrs: ConvAttrs = node.attrs
    x = node.inputs[0]
    taken = (graph.shapes, graph.constants, {n.name for n in graph.nodes})
    padded = fresh_name(f"{x}_padded_for_{node.name}", *taken)
    begin, end = (0, 0, *attrs.pads_begin), (0, 0, *attrs.pads_end)
    shapes[padded] = tuple(d + b + e for d, b, e in zip(graph.shape(x), begin, end))
    pad = Node("Pad", fresh_name(f"{node.name}_pad", *taken), (x,), (padded,), PadAttrs(begin, end))
    zero = (0,) * len(attrs.kernel)
    conv = replace(node, inputs=(padded, *node.inputs[1:]), attrs=replace(attrs, pads_begin=zero, pads_end=zero))
    return pad, conv


def pixel_axis_applies(graph: Graph, node: Node, planar: set[str]) -> bool:
    attrs = node.attrs
    return (
        node.op == "Conv"
        and isinstance(attrs, ConvAttrs)
        and attrs.algorithm == ConvAlgorithm.DIRECT
        and attrs.strides[-1] == 1
        and node.inputs[0] in planar
    )


def planes_outside_row_pays(graph: Graph, node: Node, planar: set[str], target: Target) -> bool:
    """A direct Conv on the channel axis reading a planar tensor, with input channels to loop over,
    taps along a row, a row stride above 1 and at least a widest vector of output channels, on an FMA
    target with 32 registers (register blocks of 20+ accumulators, which the commoning spills).
    Measured on avx512 (loaded, --profile --cpu-time and interleaved A/B): squeezenet1_1's 3 -> 64
    stem 0.80-0.90x the time, 3x3 stride-2 stems alone 0.87-0.93x for 24-64 channels; mobilenet_v2's
    and mnasnet0_5's unchanged in the model. Left out where it measured slower: avx2 (16 registers;
    mobilenet_v2's stem 1.08-1.13x in the model), ssse3 (1.25x on 3 -> 32: gcc then hoists and spills
    the weights), mobilenet_v1_025's 3 -> 8 stem on avx512 (1.09x the model: 24 pixels x one 8-lane
    vector keep the row-tap loop, which overlaps again) and stride 1 (resnet8's 3 -> 16, 1.01-1.04x)."""
    attrs = node.attrs
    wide = target.fma and target.registers >= 32 and target.vector_widths
    if not (wide and node.op == "Conv" and isinstance(attrs, ConvAttrs)):
        return False
    c_out, c_in = graph.shape(node.inputs[1])[:2]
    return (
        attrs.algorithm == ConvAlgorithm.DIRECT
        and attrs.vector_axis == VectorAxis.CHANNELS
        and node.inputs[0] in planar
        and c_in > 1
        and attrs.kernel[-1] > 1
        and attrs.strides[-1] > 1
        and c_out // attrs.group >= max(target.vector_widths)
    )


def chosen_by_cost_model(graph: Graph, node: Node, lanes: tuple[int, ...]) -> bool:
    """Channels filling at most half the widest vector, rows of at least MIN_ROW_VECTORS of them.
    Measured on robot (conv1: 3 -> 8 channels, rows of 80, then a MaxPool; best of 15 interleaved
    runs): avx512 conv1 29.5 -> 22.4 us, pool1 1.7 -> 2.4 us, the model 87.5 -> 82.5 us; where 8
    channels fill the vectors the gain is small (avx2 96.1 -> 94.7, ssse3 181.0 -> 179.6), and
    pedestrian's conv1 (12 channels, rows of 18) got slower on avx512."""
    widest = max(lanes)
    c_out = graph.shape(node.inputs[1])[0] // node.attrs.group
    return widest > 1 and 2 * c_out <= widest and graph.shape(node.outputs[0])[-1] >= MIN_ROW_VECTORS * widest


def tuning_candidates(graph: Graph, target: Target) -> dict[str, tuple[bool, ...]]:
    """For --tune: channels or pixels for each layer the pixel axis applies to (in graph order)."""
    return {name: (False, True) for name in pixel_candidates(graph)}


def pixel_candidates(graph: Graph) -> list[str]:
    """The layers the pixel axis applies to, if every earlier one took it (what --tune measures)."""
    planar = {value.name for value in graph.inputs}
    names = []
    for node in graph.nodes:
        if pixel_axis_applies(graph, node, planar):
            names.append(node.name)
            planar.add(node.outputs[0])
    return names
