"""Graph pass `winograd{layers=conv2:true;conv1:false}`: Winograd F(2x2, 3x3) for 3x3 convs.

Winograd (nncg/lowering/winograd.py) does 2.25x fewer multiplies than direct convolution but adds
an input and an output transform (adds only) and two scratch buffers. The multiplies it saves grow
with the input channels, the transforms' adds do not, so the cost model takes it for every 3x3,
stride-1, ungrouped 2-D Conv with at least MIN_INPUT_CHANNELS input channels and either MIN_TILES
output tiles or transformed weights that fit L2 (see chosen_by_cost_model); `layers` overrides
the choice per layer (what `--tune` measured). Layers Winograd does not apply to stay direct.

A QLinearConv of the same window runs the exact integer Winograd (lowering/winograd_integer.py) where
its sums fit the integer transforms, on the targets whose vectors run it (integer_chosen_by_cost_model).

The GEMMs' output channels are internal, so they may be padded with zero filters: with the target's
vector widths of the target, a count that would take more vector instructions than its padded form (12 on
16/8/4: an 8- and a 4-lane block, padded to 16: one block) is padded, if the padding stays under a
quarter of the lanes computed (measured on robot, avx512: 12 -> 16 ran 1.5x faster; 8 -> 16 and
20 -> 32 ran slower)."""

from __future__ import annotations

from dataclasses import replace

from ..errors import NncgError
from ..ir.analysis import vector_instructions
from ..ir.applicability import integer_winograd_shaped, winograd_applies
from ..ir.graph import Graph
from ..ir.kinds import ConvAlgorithm, DType
from ..ir.target import Target
from ..lowering.winograd import tile_count
from ..lowering.winograd_integer import integer_winograd_fits
from .per_layer import check_layer_names, parse_layer_map
from .plan_memory import parse_bool

MIN_INPUT_CHANNELS = 8
# Output tiles that reuse each transformed weight enough where the weights do not fit L2; more where
# they exceed LARGE_WEIGHTS_BYTES. resnet18 at 224x224, whole model with layer4 (7x7 outputs: 16 tiles,
# 16.8 MB transformed) direct: avx2 0.874x the time, avx512 0.963x; with layer3 (49 tiles, 4.2 MB)
# direct: avx2 1.060x. mlperf_ic_resnet8's last 3x3 (16 tiles, 262 KB) direct: avx512 1.15x, ssse3 1.12x.
MIN_TILES = 16
MIN_TILES_LARGE = 25
LARGE_WEIGHTS_BYTES = 4 * 1024 * 1024
MIN_INTEGER_TILES = 4  # integer Winograd's transforms and scratch on fewer tiles buy nothing (below)
FLOAT_BYTES, INT16_BYTES = DType.FLOAT32.bytes, DType.INT16.bytes  # a transformed weight, float or integer


def parse_layers(text: str) -> dict[str, bool]:
    """`conv2:true;conv1:false` -> {"conv2": True, "conv1": False}."""
    return parse_layer_map(text, parse_bool, "conv2:true;conv1:false")


def winograd(graph: Graph, target: Target, layers: dict[str, bool] | None = None) -> Graph:
    lanes = target.vector_widths or (1,)
    layers = layers or {}
    check_layer_names(graph, layers, "winograd")
    nodes = []
    for node in graph.nodes:
        wanted = layers.get(node.name)
        if wanted and not applies(graph, node):
            raise NncgError(
                f"winograd: layer {node.name} is not a 3x3, stride-1, ungrouped 2-D Conv with constant weights "
                "(or a QLinearConv whose sums the integer transforms cannot hold exactly)"
            )
        chosen = chosen_by_cost_model(graph, node, target) if wanted is None else wanted
        nodes.append(_as_winograd(graph, node, lanes) if chosen else node)
    return graph.with_nodes(nodes)


def _as_winograd(graph: Graph, node, lanes: tuple[int, ...]):
    """The node marked Winograd; a float one's GEMM channels padded where that pays (padded_channels)."""
    if node.op == "QLinearConv":
        return replace(node, attrs=replace(node.attrs, algorithm=ConvAlgorithm.WINOGRAD))
    c_out = graph.shape(node.inputs[1])[0]
    width = padded_channels(c_out, lanes)
    return replace(
        node, attrs=replace(node.attrs, algorithm=ConvAlgorithm.WINOGRAD, gemm_channels=width if width != c_out else 0)
    )


def applies(graph: Graph, node) -> bool:
    """A float Conv Winograd applies to, or a QLinearConv integer Winograd does (exactly)."""
    return winograd_applies(graph, node) or (integer_winograd_shaped(node) and integer_winograd_fits(graph, node))


def chosen_by_cost_model(graph: Graph, node, target: Target) -> bool:
    if node.op == "QLinearConv":
        return integer_chosen_by_cost_model(graph, node, target)
    return float_chosen_by_cost_model(graph, node, target)


def integer_chosen_by_cost_model(graph: Graph, node, target: Target) -> bool:
    """On a target whose vectors run its nests (Target.int16_dots: ssse3, avx2), a QLinearConv the exact
    integer transforms hold, of at least MIN_INPUT_CHANNELS input channels and enough tiles or
    transformed weights (int16) in L2, as float's. Measured on resnet8 int8, one inference, callgrind
    Ir of each 3x3 layer (`python3 -m benchmarks.int8_winograd`): 16 to 64 input channels 0.63-0.66x
    the direct kernel's on ssse3, 0.53-0.58x on avx2; the stem's 3 channels least (0.76x, 0.71x), left
    direct as float's. The whole model at speed 0.74x on ssse3 (7.34M -> 5.46M), 0.69x on avx2; its
    scratch, one tile at a time along each tile row (winograd.WHOLE_CHUNKS; a whole tile row before
    took speed's arena from 48 to 72 KB), takes it to 49.5 KB, and the model to 0.89x the Ir of
    whole-row chunks on avx2 (clang), 0.94x on ssse3 (gcc); 4-tile chunks 0.95x, 1.02x. In time, whole rows
    ran ~8 % faster on resnet8 avx2 (longer chunks block tiles per weight load; idle, side by side), on ssse3 and
    pedestrian 1-tile chunks as fast or faster: the 1-tile chunks trade that for 24 KB of arena. Not on
    scalar C: 2.6x fewer instructions, but scalar C is the microcontroller target, where RAM is what int8
    is for (`layers` forces it); nor on the AVX-512 targets (no int16 templates) or neon: unmeasured. Nor on fewer than
    MIN_INTEGER_TILES tiles: ball's conv2 (8 -> 12 channels, one tile) saved 0.5 % of the model's Ir on
    ssse3 while its scratch took the arena from 768 to 1,216 B; pedestrian's conv3 (10 tiles) saved 24 %
    of it (960K -> 727K Ir); between the two, unmeasured."""
    if not target.int16_dots or not integer_winograd_shaped(node) or not integer_winograd_fits(graph, node):
        return False
    rows, columns = graph.shape(node.outputs[0])[2:]
    if graph.shape(node.inputs[1])[1] < MIN_INPUT_CHANNELS or _tiles(rows, columns) < MIN_INTEGER_TILES:
        return False
    return _pays(graph, node, target, INT16_BYTES)


def float_chosen_by_cost_model(graph: Graph, node, target: Target) -> bool:
    """Enough input channels, and either enough 2x2 output tiles to reuse each transformed weight over
    or transformed weights that stay in L2: its 16 GEMMs stream 16/9 the direct weights, each used
    once per tile. resnet18 at 96x96, avx2: layer4 (4 tiles, 16.8 MB) 3550 us against 1400 direct,
    cache-blocked; layer3 (9 tiles) even; pedestrian's conv3 (10 tiles, 131 KB) 24 -> 40 us direct; at
    224x224 see MIN_TILES."""
    if not winograd_applies(graph, node) or graph.shape(node.inputs[1])[1] < MIN_INPUT_CHANNELS:
        return False
    return _pays(graph, node, target, FLOAT_BYTES)


def _pays(graph: Graph, node, target: Target, weight_bytes: int) -> bool:
    """Transformed weights of `weight_bytes` an element that fit L2, or enough output tiles to reuse
    each over (MIN_TILES; MIN_TILES_LARGE beyond LARGE_WEIGHTS_BYTES)."""
    rows, columns = graph.shape(node.outputs[0])[2:]
    c_out, c_in = graph.shape(node.inputs[1])[:2]
    transformed = 16 * c_out * c_in * weight_bytes
    if not target.l2_bytes or transformed < target.l2_bytes:  # with room for the tiles
        return True
    return _tiles(rows, columns) >= (MIN_TILES_LARGE if transformed > LARGE_WEIGHTS_BYTES else MIN_TILES)


def _tiles(rows: int, columns: int) -> int:
    """The 2x2 output tiles of a rows x columns output."""
    return tile_count(rows) * tile_count(columns)


def winograd_candidates(graph: Graph) -> list[str]:
    """The layers Winograd applies to (what --tune measures both ways)."""
    return [node.name for node in graph.nodes if applies(graph, node)]


def tuning_candidates(graph: Graph, target: Target) -> dict[str, tuple[bool, ...]]:
    """For --tune: direct or Winograd for each layer Winograd applies to."""
    return {name: (False, True) for name in winograd_candidates(graph)}


def padded_channels(channels: int, lanes: tuple[int, ...]) -> int:
    best = channels
    for width in lanes:
        padded = -(-channels // width) * width
        cheaper = vector_instructions(padded, lanes) < vector_instructions(best, lanes)
        if cheaper and 4 * channels >= 3 * padded:
            best = padded
    return best
