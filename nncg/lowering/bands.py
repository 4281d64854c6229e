"""Band geometry: a chain of layers run over bands of rows, so the tensors inside the chain are line
buffers (the last few rows) instead of whole tensors.

A group is a run of Conv and pooling layers, float or int8, and the int8 model's elementwise
QuantizeLinear, table lookups and requantised adds (a window of one row), consecutive in graph
order, whose tensors other than the last layer's output are read only inside the group. Each band,
the last layer produces `rows` more output rows and every other layer the rows its readers need
next: tensor t advances `step` rows per band (`rows` times the strides between it and the output)
and is complete up to row step * band + ahead, `ahead` being what its readers' windows reach beyond
their own rows. A line buffer keeps the `lines` newest rows: from the lowest row a reader's window
starts at to the newest. The first bands (band < 0, before the output's first row) fill the line
buffers; rows outside a tensor are skipped, so the same loop body serves every band, and each band
computes only rows no earlier band computed.

Layers before a stride advance faster: where the steps fall along the chain (4, 4, 2, 2, 1), the
faster layers run in nested loops (level 1 twice per band, level 2 twice per level-1 run), each run
computing `rows` rows, so a line buffer between two layers of one level holds only what one run
needs (a 3x3 window: 3 rows, not step + 2). A tensor's step and ahead count runs of its producer's
level; a reader at an outer level reads it after the last of the runs nested in its own."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..ir.graph import Graph, Node
from ..ir.loops import Affine
from .conv import conv_extras
from .winograd import TILE

WINDOWED = ("Conv", "QLinearConv", "MaxPool", "AveragePool", "QLinearAveragePool")  # write channels last
POINTWISE = ("QuantizeLinear", "QLinearLookup", "QLinearAdd")  # follow their first input's layout (elementwise.py)
STREAMABLE = WINDOWED + POINTWISE


@dataclass(frozen=True)
class BandGroup:
    """Layers (node names, consecutive in graph order) run together, `rows` output rows per band;
    with `winograd`, the Convs (float or int8) the graph passes made Winograd stay Winograd where their
    rows advance in whole 2-row tiles, but those named in `direct` (else every Conv runs direct)."""

    nodes: tuple[str, ...]
    rows: int
    winograd: bool = False
    direct: tuple[str, ...] = ()

    def __str__(self) -> str:
        direct = "".join(f":{name}" for name in self.direct)
        return f"{self.nodes[0]}..{self.nodes[-1]}:{self.rows}{':winograd' if self.winograd else ''}{direct}"


@dataclass(frozen=True)
class Rows:
    """How a tensor of a group advances: `step` rows per run of its producer's `level`, complete up
    to step * run + ahead (unclamped) after run `run`, its line buffer `lines` rows high (tensors
    kept whole: 0)."""

    step: int
    ahead: int
    lines: int = 0
    level: int = 0

    def first(self, run: Affine) -> Affine:
        """The first row a run computes."""
        return run * self.step + (self.ahead - self.step)

    def origin(self, run: Affine, runs: int = 1) -> Affine:
        """The tensor row in the first line of the line buffer when a reader whose one run spans
        `runs` runs of the producer's level reads it in its run `run`."""
        return (run * runs + (runs - 1)) * self.step + (self.ahead - self.lines)


@dataclass(frozen=True)
class Geometry:
    """Rows of every tensor the group produces, the runs of each level per run of the level
    outside it (`reps[0]` is 1: level 0 is the band loop), the bands to run (from `first_band` <= 0)
    and the tensors that become line buffers."""

    rows: dict[str, Rows]
    reps: tuple[int, ...]
    bands: int
    internal: tuple[str, ...]
    output: str
    first_band: int = 0
    winograd: tuple[str, ...] = ()  # the layers run as Winograd tiles (stream.py)

    def runs(self, outer: int, inner: int) -> int:
        """Runs of level `inner` per run of level `outer` (<= inner)."""
        return math.prod(self.reps[outer + 1 : inner + 1])


def streamable(graph: Graph, node: Node) -> bool:
    """A 2-D Conv (constant weights), pooling or elementwise int8 op over a batch of one, at least two
    output rows; an elementwise op's tensors all of its output's shape."""
    if node.op not in STREAMABLE or len(node.outputs) != 1:
        return False
    shape = graph.shape(node.outputs[0])
    if len(shape) != 4 or shape[0] != 1 or shape[2] < 2:
        return False
    if node.op in POINTWISE:
        return all(graph.shape(v) == shape for v in node.inputs if not graph.is_constant(v))
    if len(window_attrs(node).kernel) != 2:
        return False
    return node.op != "Conv" or all(graph.is_constant(v) for v in (node.inputs[1], conv_extras(node)[0]) if v)


def window_attrs(node: Node):
    """The kernel, strides, dilations and pads of a windowed layer."""
    return node.attrs.pool if node.op == "QLinearAveragePool" else node.attrs


def row_window(node: Node, index: int) -> tuple[int, int, int, int]:
    """(kernel, stride, dilation, padding before) along the rows, as `node` reads its input `index`;
    a fused residual, and an elementwise op's every input, are read at the output's own rows."""
    if index > 0 or node.op in POINTWISE:
        return 1, 1, 1, 0
    attrs = window_attrs(node)
    return attrs.kernel[0], attrs.strides[0], attrs.dilations[0], attrs.pads_begin[0]


def geometry(graph: Graph, group: BandGroup) -> Geometry | None:
    """The group's geometry, or None when it cannot run in bands."""
    by_name = {node.name: node for node in graph.nodes}
    nodes = [by_name.get(name) for name in group.nodes]
    if group.rows < 1 or None in nodes or not all(streamable(graph, n) for n in nodes):
        return None
    if not _consecutive(graph, nodes):
        return None
    output = nodes[-1].outputs[0]
    internal = tuple(n.outputs[0] for n in nodes[:-1])
    if any(graph.is_graph_output(v) for v in internal) or not _kept_inside(graph, group, internal, output):
        return None
    if not all(_channels_last_inputs(graph, n, internal) for n in nodes if n.op in POINTWISE):
        return None
    tiled = {n.name for n in nodes if group.winograd and n.runs_winograd and n.name not in group.direct}
    flat = _rows(nodes, group.rows, {}, (1,), tiled)
    if flat is None:
        return None
    levels, reps = _levels(nodes, flat)
    rows = _rows(nodes, group.rows, levels, reps, tiled)
    if rows is None:
        rows, reps = flat, (1,)
    first_band = min((r.step - r.ahead) // (r.step * math.prod(reps[1 : r.level + 1])) for r in rows.values())
    bands = -(-graph.shape(output)[2] // group.rows) - first_band
    winograd = tuple(n.name for n in nodes if n.name in tiled and _whole_tiles(rows[n.outputs[0]]))
    return Geometry(rows, reps, bands, internal, output, first_band, winograd)


def _whole_tiles(rows: Rows) -> bool:
    """Every run starts at an even row and computes an even number of rows: whole 2-row tiles."""
    return rows.step % TILE == 0 and rows.ahead % TILE == 0


def _channels_last_inputs(graph: Graph, node: Node, internal: tuple[str, ...]) -> bool:
    """An elementwise op in a group writes its output in its first input's layout, which must be
    channels last (a line buffer's): its first input from inside the group, every other one from
    inside or from a windowed layer, which writes channels last (unless it vectorises pixels). A
    QuantizeLinear in a group writes channels last whatever it reads (stream.py)."""
    if node.op == "QuantizeLinear":
        return True
    inputs = [v for v in node.inputs if not graph.is_constant(v)]
    outside = [graph.producer(v) for v in inputs[1:] if v not in internal]
    planar = any(p.vectorises_pixels for p in outside if p)
    return inputs[0] in internal and not planar and all(p is not None and p.op in WINDOWED for p in outside)


def _kept_inside(graph: Graph, group: BandGroup, internal: tuple[str, ...], output: str) -> bool:
    """The group's inner tensors are read only inside it, its output only outside."""
    members, inner = set(group.nodes), set(internal)
    for node in graph.nodes:
        inside = node.name in members
        if any((v in inner and not inside) or (v == output and inside) for v in node.inputs):
            return False
    return True


def _consecutive(graph: Graph, nodes: list[Node]) -> bool:
    index = {node.name: i for i, node in enumerate(graph.nodes)}
    first = index[nodes[0].name]
    return [index[n.name] for n in nodes] == list(range(first, first + len(nodes)))


def _levels(nodes: list[Node], flat: dict[str, Rows]) -> tuple[dict[str, int], tuple[int, ...]]:
    """Each tensor's level, from its step in one loop over bands, and the runs per level: one level
    per distinct step, when the steps fall along the chain, each a multiple of the next."""
    steps = [flat[node.outputs[0]].step for node in nodes]
    distinct = sorted(set(steps))
    ratios = [b // a for a, b in zip(distinct, distinct[1:]) if b % a == 0]
    if steps != sorted(steps, reverse=True) or len(ratios) != len(distinct) - 1:
        return {}, (1,)
    return {v: distinct.index(r.step) for v, r in flat.items()}, (1, *ratios)


def _rows(
    nodes: list[Node], rows: int, levels: dict[str, int], reps: tuple[int, ...], tiled: set[str]
) -> dict[str, Rows] | None:
    """Per tensor the group produces, from the output back: what its readers need of it, counted in
    runs of its level (`levels`; absent: 0). A `tiled` layer (Winograd) whose step is even computes
    from an even row: one row further ahead where its readers need an odd count."""
    produced = {n.outputs[0] for n in nodes}
    out: dict[str, Rows] = {nodes[-1].outputs[0]: Rows(rows, rows)}
    lowest: dict[str, int] = {}
    for node in reversed(nodes):
        y = out.get(node.outputs[0])
        if y is None:  # read by nobody in the group
            return None
        if node.name in tiled and y.step % TILE == 0 and y.ahead % TILE:
            y = out[node.outputs[0]] = replace(y, ahead=y.ahead + 1)
        for index, x in enumerate(node.inputs):
            if x not in produced:
                continue
            kernel, stride, dilation, pad = row_window(node, index)
            level = levels.get(x, 0)
            runs = math.prod(reps[y.level + 1 : level + 1])  # of x's producer per run of this reader
            if level < y.level or (y.step * stride) % runs:
                return None
            step = y.step * stride // runs
            late = step * (runs - 1)  # rows x's producer makes after the reader's first needed ones
            ahead = y.ahead * stride + (kernel - 1) * dilation - pad - stride + 1 - late
            low = (y.ahead - y.step) * stride - pad - late
            if x in out:
                if out[x].step != step:
                    return None
                ahead, low = max(ahead, out[x].ahead), min(low, lowest[x])
            out[x], lowest[x] = Rows(step, ahead, 0, level), low
    return {v: r if v not in lowest else replace(r, lines=max(r.step, r.ahead - lowest[v])) for v, r in out.items()}


def row_bytes(graph: Graph, value: str) -> int:
    """Bytes in one row of a (1, C, H, W) tensor."""
    shape = graph.shape(value)
    return shape[1] * shape[3] * graph.dtype(value).bytes
