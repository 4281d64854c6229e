"""Graph pass `cache-block{layers=NAME:PANELxBLOCK;NAME:off}`: packed, cache-blocked direct convolution.

A register-blocked convolution computes P pixels x C channel vectors at a time, reading for each
reduction step (tap, input channel) C weight vectors. Unblocked, the pixel loops are outside the
channel loops, so every block of P pixels streams the whole weight tensor again: from L1 or L2 in
an early layer, from memory in a late one (resnet18's layer4: 9.4 MB of weights, 9 output pixels,
read 5 times at 11 GFLOP/s). Blocked, the layer is computed one *panel* of output channels at a time
(as many as one register block holds), with its weights packed in exactly the order the kernel
streams them ([panel][input-channel block][taps][input channels][panel channels]), and the
reduction split into blocks of `ci_block` input channels whose weight slice fits half of L1: every
block of pixels then reuses that slice from L1, and the weights come from memory once. The price:
the output is read back between reduction blocks and the input is read once per panel.

The cost model (`chosen_blocks`) blocks a layer whose weights exceed the target's L1; the panel is
the register block's channel vectors (register_block.channel_block), the input-channel block the
largest divisor of the input channels that fits. A grouped (not depthwise) Conv is always computed
one group per panel, whatever its size: unblocked, its group loop is the innermost loop around the
channels, so register-block jams groups, which share neither inputs nor weights (regnet_x_400mf's
16-channel groups on avx2: 1 pixel x 5 groups, 1.5 loads per multiply-add); per panel it jams
pixels, which share the group's weights. A depthwise Conv is not packed in panels but computed
`channel_block` channels at a time outside its pixel loops: a cache line of them on x86 FMA targets,
elsewhere blocks of 64 where its weights exceed L1 (depthwise_blocks).
`layers` overrides it per layer (what `--tune` measured); lowering/conv_blocked.py (lowering/conv.py
for the depthwise channel blocks) does the rest."""

from __future__ import annotations

import math
from dataclasses import replace

from ..errors import NncgError
from ..ir.applicability import (
    cache_block_applies,
    depthwise_blocks_apply,
    group_panels_apply,
    panel_packing_applies,
    reduction_streams,
)
from ..ir.graph import Graph, Node
from ..ir.target import Target
from .per_layer import check_layer_names, parse_layer_map
from .register_block import MAX_CHANNEL_BLOCK, RESERVED, channel_block, fma_from_memory

OFF = (0, 0)
FLOAT_BYTES = 4
# Channels a depthwise Conv whose weights exceed L1 computes over all its pixels at a time: 4 vectors
# of 16, their 5x5 weights 6.4 KB.
DEPTHWISE_CHANNEL_BLOCK = 64
# Channels a depthwise Conv computes over all its pixels at a time where a multiply-add reads memory
# (x86 FMA): one 64-byte cache line of every pixel (depthwise_blocks).
DEPTHWISE_LINE_CHANNELS = 16
DEPTHWISE_LINES = (DEPTHWISE_LINE_CHANNELS, 0)


def parse_choice(text: str) -> tuple[int, int]:
    """`32x8` -> (32, 8): output channels per panel x input channels per reduction block; `32` ->
    (32, 0): the whole reduction at once; `off` -> (0, 0)."""
    if text == "off":
        return OFF
    panel, x, block = text.partition("x")
    if not panel.isdigit() or int(panel) < 1 or (x and (not block.isdigit() or int(block) < 1)):
        raise ValueError("a cache block is PANEL or PANELxBLOCK (output channels x input channels, at least 1) or off")
    return int(panel), int(block) if x else 0


def format_choice(choice: tuple[int, int]) -> str:
    return "off" if choice == OFF else f"{choice[0]}x{choice[1]}" if choice[1] else str(choice[0])


def parse_layers(text: str) -> dict[str, tuple[int, int]]:
    """`conv1:32x8;conv2:off;fc:32` -> {"conv1": (32, 8), "conv2": (0, 0), "fc": (32, 0)}."""
    return parse_layer_map(text, parse_choice, "conv1:32x8;conv2:off;fc:32")


def cache_block(graph: Graph, target: Target, layers: dict[str, tuple[int, int]] | None = None) -> Graph:
    layers = layers or {}
    check_layer_names(graph, layers, "cache-block")
    nodes = []
    for node in graph.nodes:
        choice = layers.get(node.name)
        if choice is None:
            choice = chosen_blocks(graph, node, target)
        elif choice != OFF:
            _check_choice(graph, node, choice)
        if choice != OFF:
            node = replace(node, attrs=_blocked(graph, node, choice, target))
        nodes.append(node)
    return graph.with_nodes(nodes)


def _blocked(graph: Graph, node: Node, choice: tuple[int, int], target: Target):
    if depthwise_blocks_apply(graph, node):
        return replace(node.attrs, channel_block=choice[0])
    if node.op == "Conv":
        return replace(node.attrs, panel=choice[0], ci_block=choice[1] or graph.shape(node.inputs[1])[1])
    vectors = -(-choice[0] // target.lanes)
    return replace(node.attrs, panel=choice[0], streams=reduction_streams(graph, node, vectors, _accumulators(target)))


def _check_choice(graph: Graph, node: Node, choice: tuple[int, int]) -> None:
    panel, block = choice
    if group_panels_apply(graph, node):
        c_out, c_in = graph.shape(node.inputs[1])[:2]
        if panel != c_out // node.attrs.group:
            raise NncgError(
                f"cache-block: layer {node.name}: a grouped Conv's panel is its group, {c_out // node.attrs.group}"
            )
        if block > c_in or (block and c_in % block):
            raise NncgError(f"cache-block: layer {node.name}: the input-channel block {block} does not divide {c_in}")
    elif cache_block_applies(graph, node):
        c_out, c_in = graph.shape(node.inputs[1])[:2]
        if block > c_in or (block and c_in % block):
            raise NncgError(f"cache-block: layer {node.name}: the input-channel block {block} does not divide {c_in}")
    elif depthwise_blocks_apply(graph, node):
        c_out = graph.shape(node.inputs[1])[0]
        if block:
            raise NncgError(f"cache-block: layer {node.name} is a depthwise Conv: give its channel block alone")
    elif panel_packing_applies(graph, node):
        c_out = _columns(graph, node)
        if block:
            raise NncgError(f"cache-block: layer {node.name} is a Gemm/MatMul: give its panel alone (PANEL)")
    else:
        raise NncgError(
            f"cache-block: layer {node.name} is neither a direct Conv over output channels with constant "
            "weights (the winograd and vectorize-pixels passes may have taken it) nor a Gemm/MatMul "
            "with a constant 2-D w"
        )
    if panel > c_out:
        raise NncgError(f"cache-block: layer {node.name}: a panel of {panel} is more than its {c_out} channels")


def _columns(graph: Graph, node: Node) -> int:
    """A Gemm/MatMul's output columns (N)."""
    return graph.shape(node.outputs[0])[-1]


def _shape(graph: Graph, node: Node) -> tuple[int, int, int]:
    """(output channels, input channels (of a group), taps) of a Conv or Gemm/MatMul."""
    if node.op == "Conv":
        c_out, c_in, *kernel = graph.shape(node.inputs[1])
        return c_out, c_in, math.prod(kernel)
    c_out = graph.shape(node.outputs[0])[-1]
    return c_out, math.prod(graph.shape(node.inputs[1])) // c_out, 1


def chosen_blocks(graph: Graph, node: Node, target: Target) -> tuple[int, int]:
    """(panel, input-channel block) for a grouped Conv or a layer whose weights exceed L1, else OFF. A Gemm/MatMul
    takes the whole reduction at once (block 0): its rows are few, there is little to reuse; a depthwise
    Conv is blocked by channels alone (depthwise_blocks)."""
    if not target.l1_bytes or not target.vector_widths:
        return OFF
    if depthwise_blocks_apply(graph, node):
        return depthwise_blocks(graph, node, target)
    if group_panels_apply(graph, node):
        c_out, c_in, taps = _shape(graph, node)
        panel = c_out // node.attrs.group
        return panel, input_block(c_in, taps, panel, target)
    conv = cache_block_applies(graph, node)
    if not (conv or panel_packing_applies(graph, node)):
        return OFF
    c_out, c_in, taps = _shape(graph, node)
    if FLOAT_BYTES * c_out * c_in * taps <= target.l1_bytes:
        return OFF
    panel = panel_width(graph, node, target)
    return panel, input_block(c_in, taps, panel, target) if conv else 0


def depthwise_blocks(graph: Graph, node: Node, target: Target) -> tuple[int, int]:
    """DEPTHWISE_LINES for a depthwise Conv of more channels where a multiply-add reads
    memory (x86 FMA); elsewhere (DEPTHWISE_CHANNEL_BLOCK, 0) for one whose weights exceed L1, else OFF.

    In lines of channels, register-block takes a row of pixels of the line's vectors (avx512 15x1,
    avx2 5x2) instead of 3 pixels x 4 vectors: an input vector serves the taps of up to 3 neighbouring
    pixels, a weight vector the whole row, and every input cache line is read whole. mobilenet_v2_96's
    layers alone, hot caches (gcc -O3): 144 channels 3x3 on 24x24, avx512 25.0 -> 15.4 us, avx2
    23.7 -> 18.3; stride 2 to 12x12 6.5 -> 4.3 (avx512 with a 12x1 block) / 5.8 -> 5.1; 384 on 6x6
    4.1 -> 1.7 / 3.7 -> 2.9. Lines of one 8-lane vector (avx2) read each cache line twice, a block
    apart: stride 2 went 1.2x slower than unblocked. SSE (no memory operands) gained on stride 1 and
    lost on stride 2: unchanged.

    Blocks of 64 where the weights exceed L1: a block's weights, packed together, stay in L1 while it
    sweeps every pixel, where channels innermost read all the layer's weights again at each pixel (from
    L2 once they pass L1: efficientnet_b0's 1152-channel 5x5 layers on 3x3 pixels, 115 KB, ran 1.9x
    slower on avx512 alone, loaded); packed, the block's weights stream from memory in one run."""
    if fma_from_memory(target) and _spans_lines(graph, node):
        return DEPTHWISE_LINES
    if FLOAT_BYTES * math.prod(_shape(graph, node)) <= target.l1_bytes:
        return OFF
    return DEPTHWISE_CHANNEL_BLOCK, 0


def _spans_lines(graph: Graph, node: Node) -> bool:
    """More channels than one line: only then do lines of channels change a depthwise Conv's loops."""
    return _shape(graph, node)[0] > DEPTHWISE_LINE_CHANNELS


def panel_width(graph: Graph, node: Node, target: Target) -> int:
    """The output channels one register block holds (all of them when they fit one). A GEMV's panel is
    MAX_CHANNEL_BLOCK vectors, the most register-block jams, or 1 or 2 fewer where that leaves no rest (a
    rest of one vector holds few accumulators: the autoencoder's 128 columns on avx2, panels of 5 vectors
    and a rest of 1 -> 4 panels of 4), read in as many reduction streams as the registers hold
    accumulators for: each stream broadcasts an x value per step (on SSE a load and a
    shuffle), so few wide streams beat many narrow ones. 1280x1000 classifier, 4 streams of 2 vectors
    -> 2 streams of 5 (loaded, hand C in one process, weights from L3 / from memory): ssse3 78 -> 62 us /
    287 -> 185 us, avx2 56 -> 53 / 171 -> 148 us; avx512's 4 of 4 -> 4 of 5: 50 / 148-152 us either way."""
    c_out = _shape(graph, node)[0]
    vectors = -(-c_out // target.lanes)
    channels = channel_block(vectors)
    if node.op != "Conv" and reduction_streams(graph, node, 1, _accumulators(target)) > 1:
        whole = [v for v in range(MAX_CHANNEL_BLOCK, MAX_CHANNEL_BLOCK - 3, -1) if c_out % (v * target.lanes) == 0]
        channels = min(vectors, whole[0] if whole else MAX_CHANNEL_BLOCK)
    return min(c_out, channels * target.lanes)


def _accumulators(target: Target) -> int:
    """The vector registers register blocking leaves to accumulators."""
    return target.registers - RESERVED


def input_block(c_in: int, taps: int, panel: int, target: Target) -> int:
    """The most input channels (a divisor of c_in) whose panel slice fits half of L1."""
    fits = max(1, target.l1_bytes // 2 // (FLOAT_BYTES * taps * panel))
    return max(d for d in range(1, min(c_in, fits) + 1) if c_in % d == 0)


def tuning_candidates(graph: Graph, target: Target) -> dict[str, tuple[tuple[int, int], ...]]:
    """For --tune: the cost model's choice, unblocked, and (Convs) the input block halved and doubled,
    for each layer whose weights exceed half of L1 (smaller ones stay in L1 either way); for every
    depthwise Conv its choice, unblocked and in lines of channels."""
    out = {}
    if not target.l1_bytes or not target.vector_widths:
        return out
    for node in graph.nodes:
        if group_panels_apply(graph, node):
            out[node.name] = (chosen_blocks(graph, node, target), OFF)
            continue
        if depthwise_blocks_apply(graph, node):
            lines = DEPTHWISE_LINES if _spans_lines(graph, node) else OFF
            out[node.name] = tuple(dict.fromkeys([chosen_blocks(graph, node, target), OFF, lines]))
            continue
        applies = cache_block_applies(graph, node) or panel_packing_applies(graph, node)
        if not applies or 2 * FLOAT_BYTES * math.prod(_shape(graph, node)) <= target.l1_bytes:
            continue
        if cache_block_applies(graph, node):
            c_out, c_in, taps = _shape(graph, node)
            panel = panel_width(graph, node, target)
            block = input_block(c_in, taps, panel, target)
            options = [chosen_blocks(graph, node, target), OFF, (panel, block)]
            options += [(panel, b) for b in (block // 2, block * 2) if 1 <= b <= c_in and c_in % b == 0]
        else:
            options = [chosen_blocks(graph, node, target), OFF, (panel_width(graph, node, target), 0)]
        out[node.name] = tuple(dict.fromkeys(options))
    return out
