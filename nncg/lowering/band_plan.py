"""Which layers run in bands (bands.py), for a memory setting: `speed` runs every layer whole (the
layer-by-layer arena), `min` takes the smallest activation memory, `balanced` the smallest whose
extra work stays under BALANCED_EXTRA of the model's multiply-accumulates, and a RAM budget the
least extra work that fits it.

The model is cut into steps, consecutive in graph order: a layer run whole, or a group run in bands
with some band height. A step needs the memory of the whole tensors live across it (its inputs, its
output, tensors passing over it to later layers) plus its line buffers; a plan needs the largest of
its steps. Its cost is the work banding adds, in multiply-accumulates: a Winograd layer run direct
does 2.25x the multiplies, a cache-blocked or pixel-vectorised one loses that gain (a share of its
MACs), every band adds loop and border overhead per layer, and line buffers are shifted. Dynamic
programming over the steps gives the cheapest plan under a memory bound; `min` is the smallest
bound any plan meets. The figures are estimates (no alignment, no fragmentation): the driver checks
the planned arena against a budget. A single layer in bands is a Winograd layer run direct, without
its scratch buffers."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..ir.graph import Graph, Node
from ..ir.kinds import ConvAlgorithm, VectorAxis
from ..safe_text import shown
from .bands import STREAMABLE, BandGroup, geometry, row_floats, streamable
from .winograd import scratch_floats

MEMORY_MODES = ("speed", "balanced", "min")
BAND_ROWS = (1, 2, 4, 8)
LOST_WINOGRAD = 0.55
LOST_CHOICE = 0.25
PER_BAND = 64
BALANCED_EXTRA = 0.3


@dataclass(frozen=True)
class Step:
    """Nodes [start, stop) run whole (group None) or in bands; `floats` live while it runs, `lines`
    of them in line buffers."""

    start: int
    stop: int
    group: BandGroup | None
    floats: int
    cost: float
    lines: int = 0


def parse_memory(text: str) -> str:
    if text not in MEMORY_MODES:
        raise ValueError(f"memory is one of {', '.join(MEMORY_MODES)}")
    return text


def plan_bands(graph: Graph, memory: str = "speed", budget: int = 0) -> tuple[BandGroup, ...]:
    """The groups to run in bands; `budget` (bytes, 0: none) takes precedence over `memory`. A
    budget no plan meets gets the `min` plan (the driver then refuses with its arena)."""
    if memory == "speed" and not budget:
        return ()
    steps = candidate_steps(graph)
    plan = _cheapest(len(graph.nodes), steps, budget // 4) if budget else None
    if plan is None:
        bounds = sorted({s.floats for s in steps})
        limit = sum(_conv_macs(graph, n) for n in graph.nodes) * BALANCED_EXTRA if memory == "balanced" else math.inf
        plan = next(p for p in (_cheapest(len(graph.nodes), steps, b) for b in bounds) if p and _cost(p) <= limit)
    return tuple(s.group for s in plan if s.group is not None)


def layer_bound_floats(graph: Graph) -> int:
    """The layer-by-layer bound: the most activation floats live at one layer computed whole (its
    input and output, and tensors passing over it), scratch buffers left out."""
    live = _Liveness(graph)
    return max((live.floats(i, i + 1, ()) for i in range(len(graph.nodes))), default=0)


def whole_activation_floats(graph: Graph) -> int:
    """Every activation of the arena computed whole, side by side (no reuse, no bands)."""
    return sum(size for _, _, _, size in _Liveness(graph).tensors)


def describe_plan(groups: tuple[BandGroup, ...]) -> str:
    """The plan in words, the layers' names escaped (they come from the model)."""
    if not groups:
        return "every layer computed whole"
    return "; ".join(f"{shown(g.nodes[0])}..{shown(g.nodes[-1])} in bands of {g.rows} output row(s)" for g in groups)


def candidate_steps(graph: Graph) -> list[Step]:
    """Every layer run whole, and every group that can run in bands at each height."""
    live = _Liveness(graph)
    steps = [
        Step(i, i + 1, None, live.floats(i, i + 1, ()) + _scratch(graph, node) + _output_copy(graph, node), 0.0)
        for i, node in enumerate(graph.nodes)
    ]
    ceiling = max((s.floats for s in steps), default=0)  # what a plan of whole layers needs
    nodes = graph.nodes
    for i in range(len(nodes)):
        stop = i
        while stop < len(nodes) and streamable(graph, nodes[stop]):
            stop += 1
        for rows in BAND_ROWS:
            for j in range(i + 1, stop + 1):  # one layer alone: run direct, without a Winograd scratch
                step = _band_step(graph, live, i, j, rows)
                if step is not None and step.lines > ceiling:
                    break  # a longer group only adds line buffers
                if step is not None:
                    steps.append(step)
    return steps


def _band_step(graph: Graph, live: _Liveness, i: int, j: int, rows: int) -> Step | None:
    group = BandGroup(tuple(n.name for n in graph.nodes[i:j]), rows)
    if rows > graph.shape(graph.nodes[j - 1].outputs[0])[2]:
        return None
    geo = geometry(graph, group)
    if geo is None:
        return None
    lines = sum(geo.rows[v].lines * row_floats(graph, v) for v in geo.internal)
    shifted = sum(
        (geo.rows[v].lines - geo.rows[v].step) * row_floats(graph, v) * geo.runs(0, geo.rows[v].level)
        for v in geo.internal
    )
    runs = sum(geo.runs(0, geo.rows[n.outputs[0]].level) for n in graph.nodes[i:j])  # of the layers per band
    cost = sum(_lost(graph, n) for n in graph.nodes[i:j]) + geo.bands * (PER_BAND * runs + shifted)
    return Step(i, j, group, live.floats(i, j, geo.internal) + lines, cost, lines)


def _scratch(graph: Graph, node: Node) -> int:
    winograd = node.op == "Conv" and node.attrs.algorithm == ConvAlgorithm.WINOGRAD
    return scratch_floats(graph, node) if winograd else 0


def _output_copy(graph: Graph, node: Node) -> int:
    """A graph output a Conv or pooling layer run whole writes channels last, then copies out."""
    shape = graph.shape(node.outputs[0])
    copied = node.op in STREAMABLE and graph.is_graph_output(node.outputs[0]) and shape[1] > 1
    return math.prod(shape) if copied and math.prod(shape[2:]) > 1 else 0


def _lost(graph: Graph, node: Node) -> float:
    """The work a layer loses in bands: the graph passes' choices do not apply there."""
    if node.op != "Conv":
        return 0.0
    attrs = node.attrs
    if attrs.algorithm == ConvAlgorithm.WINOGRAD:
        return LOST_WINOGRAD * _conv_macs(graph, node)
    if attrs.panel or attrs.vector_axis == VectorAxis.PIXELS:
        return LOST_CHOICE * _conv_macs(graph, node)
    return 0.0


def _conv_macs(graph: Graph, node: Node) -> int:
    if node.op != "Conv":
        return 0
    return math.prod(graph.shape(node.outputs[0])) * math.prod(graph.shape(node.inputs[1])[1:])


class _Liveness:
    """Which whole tensors are live across a run of nodes: produced before its end and read at or
    after its start (graph inputs and outputs are the caller's, not the arena's)."""

    def __init__(self, graph: Graph):
        index = {node.name: i for i, node in enumerate(graph.nodes)}
        outputs = {v.name for v in graph.outputs}
        readers = {value: index[node.name] for node in graph.nodes for value in node.inputs}  # the last
        self.tensors = [  # (name, producer, last reader, floats)
            (value, i, max(i, readers.get(value, i)), math.prod(graph.shape(value)))
            for i, node in enumerate(graph.nodes)
            for value in node.outputs
            if value not in outputs
        ]

    def floats(self, start: int, stop: int, inside: tuple[str, ...]) -> int:
        live = (size for name, made, last, size in self.tensors if made < stop and last >= start and name not in inside)
        return sum(live)


def _cheapest(count: int, steps: list[Step], limit: float) -> list[Step] | None:
    """The plan of least cost whose steps each need at most `limit` floats, or None."""
    by_start: dict[int, list[Step]] = {}
    for step in steps:
        if step.floats <= limit:
            by_start.setdefault(step.start, []).append(step)
    best: dict[int, tuple[float, list[Step]]] = {count: (0.0, [])}
    for i in reversed(range(count)):
        options = [(s.cost + best[s.stop][0], s) for s in by_start.get(i, ()) if s.stop in best]
        if options:
            cost, step = min(options, key=lambda o: o[0])
            best[i] = (cost, [step, *best[step.stop][1]])
    return best[0][1] if 0 in best else None


def _cost(plan: list[Step]) -> float:
    return sum(s.cost for s in plan)
