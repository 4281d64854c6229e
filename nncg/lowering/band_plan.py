"""Which layers run in bands (bands.py), for a memory setting: `speed` runs every layer whole (the
layer-by-layer arena), `min` takes the smallest activation memory, `balanced` the fastest plan with at
most half of speed's arena whose estimated latency stays within BALANCED_LATENCY of speed's (none: the
smallest arena within that latency), and a RAM budget the fastest plan that fits it.

The model is cut into steps, consecutive in graph order: a layer run whole, or a group run in bands
with some band height. A step needs the memory of the whole tensors live across it (its inputs, its
output, tensors passing over it to later layers) plus its line buffers, and a Winograd layer run
whole its scratch (float32, or integer Winograd's int16 V and int32 M: winograd_integer.py); a plan
needs the largest of its steps. Memory is counted in bytes, each tensor at its type's size (an int8
model's activations 1 byte an element). Its latency is estimated per target (band_costs.py): a layer
run whole keeps the graph passes' choices (Winograd, cache blocking), one in bands runs direct or, in
a group's variant that keeps Winograd, Winograd over 2-row tiles (its scratch a band's, shared by the
group's Winograd layers of one arithmetic), and every band adds per-layer overhead and line-buffer
shifts. Dynamic programming over the steps gives the fastest plan
under a memory bound; `min` is the smallest bound any plan meets. The figures are estimates (no
alignment, no fragmentation): the driver checks the planned arena against a budget. A single layer
in bands is a Winograd layer run direct, without its scratch buffers."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..ir.applicability import FUSED_OPS, fused_ops_vectorise, integer_kernel_vectorises, requantises_fixed
from ..ir.graph import Graph, Node
from ..ir.kinds import DType, VectorAxis
from ..ir.ops import IR_OPS
from ..ir.target import Target
from ..safe_text import shown
from .band_costs import SCALAR, BandCosts, band_costs
from .bands import POINTWISE, WINDOWED, BandGroup, geometry, row_bytes, streamable, window_attrs
from .conv import conv_extras
from .halo import conv_halos
from .in_place import in_place_lead
from .winograd import band_scratch_bytes, scratch_bytes

MEMORY_MODES = ("speed", "balanced", "min")
BAND_ROWS = (1, 2, 4, 8)
BALANCED_LATENCY = 1.3  # issue 18: balanced at most 1.3x speed's latency ...
BALANCED_CUT = 2  # ... with at least 2x less arena
CONVS = ("Conv", "QLinearConv")  # priced by their MACs (an int8 one as a float one)
FLOAT_BYTES = DType.FLOAT32.bytes  # shifts are priced per 4 bytes moved
# a group of bands: every Conv direct, the Winograd layers kept, or kept but those of the largest band
# scratch (which sets the group's: a layer of many channels, resnet8's stage2_b_conv) direct
WINOGRAD_VARIANTS = ("direct", "kept", "small")


@dataclass(frozen=True)
class Step:
    """Nodes [start, stop) run whole (group None) or in bands; `bytes` live while it runs, `lines`
    of them in line buffers."""

    start: int
    stop: int
    group: BandGroup | None
    bytes: int
    cost: float  # estimated time, in MACs of a whole direct Conv (band_costs.py)
    lines: int = 0
    in_place: bool = False  # a depthwise Conv run whole over its input (in_place.py)


def parse_memory(text: str) -> str:
    if text not in MEMORY_MODES:
        raise ValueError(f"memory is one of {', '.join(MEMORY_MODES)}")
    return text


@dataclass(frozen=True)
class BandPlan:
    """How the layers run: the `groups` in bands, the depthwise Convs named in `in_place` whole over
    their input (in_place.py), every other layer whole. Each layer is in one step of the plan, so
    none is both banded and in place."""

    groups: tuple[BandGroup, ...] = ()
    in_place: frozenset[str] = frozenset()


def plan_layers(
    graph: Graph, memory: str = "speed", budget: int = 0, target: Target | None = None, requantize: str = "float"
) -> BandPlan:
    """The plan for `memory`; `budget` (bytes, 0: none) takes precedence over it, and `target` prices
    the plans under lower's `requantize` (StepCosts). A budget no plan meets gets the `min` plan (the driver
    then refuses with its arena); `speed` without a budget runs every layer whole."""
    if memory == "speed" and not budget:
        return BandPlan()
    steps = plan_steps(graph, memory, budget, target, requantize)
    return BandPlan(
        tuple(s.group for s in steps if s.group is not None),
        frozenset(graph.nodes[s.start].name for s in steps if s.in_place),
    )


def plan_steps(graph: Graph, memory: str, budget: int, target: Target | None, requantize: str = "float") -> list[Step]:
    """The steps of the plan plan_layers chooses (for `speed`: every layer whole). The candidates are
    the fastest plan under every memory bound, from the steps without in-place depthwise Convs and,
    where a model has some, from the steps with them (their tensors counted with the rows they are
    stored down, wherever they are live: an estimate on the safe side)."""
    costs, count = StepCosts(target, requantize), len(graph.nodes)
    exact = candidate_steps(graph, costs)
    speed = [s for s in exact if s.group is None]
    if memory == "speed" and not budget:
        return speed
    plans = _fastest_per_bound(count, exact)
    if _Liveness(graph).leads:
        plans += _fastest_per_bound(count, candidate_steps(graph, costs, in_place=True))
    fitting = [p for p in plans if _bytes(p) <= budget] if budget else []
    if fitting:
        return min(fitting, key=lambda p: (_cost(p), _in_place(p), _bytes(p)))
    if memory == "balanced" and not budget:
        return _balanced(plans, speed)
    return min(plans, key=lambda p: (_bytes(p), _cost(p), _in_place(p)))


@dataclass(frozen=True)
class KernelCosts:
    """What a kernel's work costs: the target's figures (band_costs.py; scalar C's int8 ones for an int8
    kernel left scalar), and the ops of its layers whose work stays in scalar C (`scalar`), each of their
    MACs and elements at the target's `lanes`."""

    figures: BandCosts
    lanes: float = 1.0
    scalar: frozenset[str] = frozenset()

    def element(self, node: Node) -> float:
        """What one of the node's MACs or elements costs: 1 vectorised, the target's lanes scalar."""
        return self.lanes if node.op in self.scalar else 1.0


class StepCosts:
    """What a step costs on `target` (None: band_costs's default) under lower's `requantize`. One rule,
    the vectorize pass's: work left in scalar C costs the target's lanes a MAC and element. That is every
    layer of an int8 kernel that stays scalar (integer_kernel_vectorises: one that requantises in the
    fixed-point form, or any on scalar C), priced at scalar C's int8 figures, and a requantised add
    (FUSED_OPS) on a target where those do not vectorise (fused_ops_vectorise): run whole, or as a stage of
    a band kernel whose convolutions still vectorise (vectorize.py _mark_band_stages)."""

    def __init__(self, target: Target | None, requantize: str = "float"):
        self.target, self.requantize = target, requantize
        figures = band_costs(target and target.name)
        lanes = float(target.lanes) if target else 1.0
        fused = frozenset(FUSED_OPS) if target is not None and not fused_ops_vectorise(target) else frozenset()
        self.vector = KernelCosts(figures, lanes, fused)
        integer = {k: getattr(SCALAR, k) for k in ("integer_banded", "integer_winograd", "kept_banded")}
        self.scalar_figures = replace(figures, **integer)

    def of(self, graph: Graph, nodes: list[Node]) -> KernelCosts:
        """The costs of the kernel computing `nodes` (a layer, or a group of bands)."""
        if self.target is None or not any(_integer(graph, node) for node in nodes):
            return self.vector
        fixed = requantises_fixed([node.op for node in nodes], self.requantize)
        if integer_kernel_vectorises(self.target, fixed):
            return self.vector
        return KernelCosts(self.scalar_figures, self.vector.lanes, frozenset(node.op for node in nodes))


def _integer(graph: Graph, node: Node) -> bool:
    """An int8 layer: it reads or writes integer values (the vectorize pass's integer kernels)."""
    return any(graph.dtype(value) != DType.FLOAT32 for value in (*node.inputs, *node.outputs) if value)


def _balanced(plans: list[list[Step]], speed: list[Step]) -> list[Step]:
    """The fastest plan with at most 1/BALANCED_CUT of speed's memory, if its latency is within
    BALANCED_LATENCY of speed's; else the smallest memory any plan within that latency needs."""
    fast = [p for p in plans if _cost(p) <= _cost(speed) * BALANCED_LATENCY]
    cut = [p for p in fast if _bytes(p) <= _bytes(speed) / BALANCED_CUT]
    if cut:
        return min(cut, key=lambda p: (_cost(p), _in_place(p), _bytes(p)))
    return min(fast, key=lambda p: (_bytes(p), _cost(p), _in_place(p)))


def _fastest_per_bound(count: int, steps: list[Step]) -> list[list[Step]]:
    plans = (_cheapest(count, steps, bound) for bound in sorted({s.bytes for s in steps}))
    return [p for p in plans if p is not None]


def layer_bound_bytes(graph: Graph) -> int:
    """The layer-by-layer bound: the most activation bytes live at one layer computed whole (its
    input and output, and tensors passing over it), scratch buffers left out."""
    live = _Liveness(graph)
    return max((live.whole(i) for i in range(len(graph.nodes))), default=0)


def overwriting_layers(graph: Graph) -> set[int]:
    """The layers counted as writing their output over an input that dies there (plan-memory's in
    place: elementwise ops, Convs over their fused residual), by index."""
    return set(_Liveness(graph).shared)


def whole_activation_bytes(graph: Graph) -> int:
    """Every activation of the arena computed whole, side by side (no reuse, no bands)."""
    return sum(size for _, _, _, size in _Liveness(graph).tensors)


def describe_plan(groups: tuple[BandGroup, ...]) -> str:
    """The plan in words, the layers' names escaped (they come from the model)."""
    if not groups:
        return "every layer computed whole"
    return "; ".join(
        f"{shown(g.nodes[0])}..{shown(g.nodes[-1])} in bands of {g.rows} output row(s)"
        + (", Winograd kept" if g.winograd else "")
        + (f" but not on {', '.join(shown(name) for name in g.direct)}" if g.direct else "")
        for g in groups
    )


def candidate_steps(graph: Graph, costs: StepCosts, in_place: bool = False) -> list[Step]:
    """Every layer run whole, and every group that can run in bands at each height; with `in_place`,
    also every depthwise Conv that can run in place, its input and output counted as stored for it."""
    live = _Liveness(graph, in_place)
    steps = [
        Step(
            i, i + 1, None, live.whole(i) + _scratch(graph, node) + _output_copy(graph, node),
            _whole_time(graph, node, costs.of(graph, [node])),
        )
        for i, node in enumerate(graph.nodes)
    ]  # fmt: skip
    ceiling = max((s.bytes for s in steps), default=0)  # what a plan of whole layers needs
    for i in live.leads if in_place else ():  # after the layer run whole, which wins a tie
        steps.append(replace(steps[i], bytes=steps[i].bytes - live.size[graph.nodes[i].outputs[0]], in_place=True))
    nodes = graph.nodes
    for i in range(len(nodes)):
        stop = i
        while stop < len(nodes) and streamable(graph, nodes[stop]):
            stop += 1
        for rows in BAND_ROWS:
            for winograd in WINOGRAD_VARIANTS:
                for j in range(i + 1, stop + 1):  # one layer alone: run direct, without a Winograd scratch
                    step = _band_step(graph, live, costs, i, j, rows, winograd)
                    if step is not None and step.lines > ceiling:
                        break  # a longer group only adds line buffers
                    if step is not None:
                        steps.append(step)
    return steps


def _band_step(
    graph: Graph, live: _Liveness, step_costs: StepCosts, i: int, j: int, rows: int, winograd: str
) -> Step | None:
    """The group of nodes [i, j) in bands of `rows`, its Winograd layers as `winograd` says
    (WINOGRAD_VARIANTS; None where that keeps none, or for one layer alone: it would be the layer
    run whole)."""
    group = BandGroup(tuple(n.name for n in graph.nodes[i:j]), rows, winograd != "direct")
    if rows > graph.shape(graph.nodes[j - 1].outputs[0])[2]:
        return None
    geo = geometry(graph, group)
    if geo is not None and winograd == "small":
        group = replace(group, direct=_largest_scratch(graph, [n for n in graph.nodes[i:j] if n.name in geo.winograd]))
        geo = geometry(graph, group)
    if geo is None or (group.winograd and (j - i == 1 or not geo.winograd)):
        return None
    scratch = band_scratch_bytes(graph, [n for n in graph.nodes[i:j] if n.name in geo.winograd])
    scratch += sum(_quantized_row(graph, n) for n in graph.nodes[i:j])
    lines = sum(geo.rows[v].lines * row_bytes(graph, v) for v in geo.internal) + scratch
    shifted = sum(
        (geo.rows[v].lines - geo.rows[v].step) * row_bytes(graph, v) // FLOAT_BYTES * geo.runs(0, geo.rows[v].level)
        for v in geo.internal
    )
    runs = sum(geo.runs(0, geo.rows[n.outputs[0]].level) for n in graph.nodes[i:j])  # of the layers per band
    kernel = step_costs.of(graph, graph.nodes[i:j])
    costs = kernel.figures
    banded = costs.banded if j - i > 1 else 1.0  # one layer alone: its direct nest under a band loop

    def per_mac(node: Node) -> float:
        if node.op == "QLinearConv":  # in the target's int8 dot products, in bands as whole (vectorize.py)
            if node.name in geo.winograd:
                return costs.integer_winograd * (costs.kept_banded or costs.integer_banded)
            return costs.integer_banded if j - i > 1 else 1.0
        return banded * (costs.winograd if node.name in geo.winograd else 1.0)

    def work(nodes: list[Node]) -> float:
        return sum(_conv_macs(graph, n) * per_mac(n) + _window_work(graph, n) for n in nodes)

    vector = work([n for n in graph.nodes[i:j] if n.op not in kernel.scalar])
    scalar = work([n for n in graph.nodes[i:j] if n.op in kernel.scalar])  # at the lanes: KernelCosts.element
    cost = vector + kernel.lanes * scalar + geo.bands * (costs.per_band * runs + costs.shift * shifted)
    return Step(i, j, group, live.bytes(i, j, geo.internal) + lines, cost, lines)


def _largest_scratch(graph: Graph, nodes: list[Node]) -> tuple[str, ...]:
    """The Winograd layers of a group of bands whose band scratch is the largest (the group's)."""
    sizes = {node.name: band_scratch_bytes(graph, [node]) for node in nodes}
    largest = max(sizes.values(), default=0)
    return tuple(name for name, size in sizes.items() if size == largest)


def _quantized_row(graph: Graph, node: Node) -> int:
    """The scratch row a QuantizeLinear in bands quantises into before interleaving its channels
    (lowering/quantized.py lower_banded_quantize_linear)."""
    several = node.op == "QuantizeLinear" and graph.shape(node.outputs[0])[1] > 1
    return row_bytes(graph, node.outputs[0]) if several else 0


def _scratch(graph: Graph, node: Node) -> int:
    """The scratch bytes of a Winograd layer run whole: float32 V and M, or int16 V and int32 M, in
    chunks of their op's size."""
    return scratch_bytes(graph, node) if node.runs_winograd else 0


def _output_copy(graph: Graph, node: Node) -> int:
    """A graph output a Conv or pooling layer run whole writes channels last, then copies out."""
    shape = graph.shape(node.outputs[0])
    copied = node.op in WINDOWED and graph.is_graph_output(node.outputs[0]) and shape[1] > 1
    return _tensor_bytes(graph, node.outputs[0]) if copied and math.prod(shape[2:]) > 1 else 0


def _whole_time(graph: Graph, node: Node, kernel: KernelCosts) -> float:
    """A layer run whole: a Conv at the speed of what the graph passes chose for it."""
    macs, costs = _conv_macs(graph, node), kernel.figures
    if macs and node.runs_winograd:
        macs *= costs.integer_winograd if node.op == "QLinearConv" else costs.winograd
    elif macs and (node.cache_blocked or node.vectorises_pixels):
        macs *= costs.blocked
    return (macs + _window_work(graph, node)) * kernel.element(node)


def _window_work(graph: Graph, node: Node) -> float:
    """A pooling layer's window reads, or an elementwise int8 op's one per element."""
    if node.op in POINTWISE:
        return math.prod(graph.shape(node.outputs[0]))
    if node.op not in WINDOWED or node.op in CONVS:
        return 0
    return math.prod(graph.shape(node.outputs[0])) * math.prod(window_attrs(node).kernel)


def _conv_macs(graph: Graph, node: Node) -> int:
    if node.op not in CONVS:
        return 0
    return math.prod(graph.shape(node.outputs[0])) * math.prod(graph.shape(node.inputs[1])[1:])


class _Liveness:
    """Which whole tensors are live across a run of nodes: produced before its end and read at or
    after its start (graph inputs and outputs are the caller's, not the arena's). A Conv run whole
    whose fused residual dies at it writes its output over the residual, and an elementwise op over
    an input dying at it (plan-memory computes them in place), so its layer holds one of the
    two (`shared`). With `in_place`, the input and output of
    every depthwise Conv that can run in place (`leads`) count the rows it is stored down."""

    def __init__(self, graph: Graph, in_place: bool = False):
        index = {node.name: i for i, node in enumerate(graph.nodes)}
        outputs = {v.name for v in graph.outputs}
        readers = {value: index[node.name] for node in graph.nodes for value in node.inputs}  # the last
        producers = {value: node for node in graph.nodes for value in node.outputs}
        halos = conv_halos(graph, blocked_only=True)
        leads = {i: in_place_lead(graph, node, readers, i, halos) for i, node in enumerate(graph.nodes)}
        self.leads = {i: lead for i, lead in leads.items() if lead}  # depthwise Convs that can run in place
        self.size = {value: _tensor_bytes(graph, value) for node in graph.nodes for value in node.outputs}
        for i, lead in self.leads.items() if in_place else ():  # stored down `lead` rows, written over
            node = graph.nodes[i]
            for value in (node.inputs[0], node.outputs[0]):
                self.size[value] += lead * row_bytes(graph, value)
        self.tensors = [  # (name, producer, last reader, bytes)
            (value, i, max(i, readers.get(value, i)), self.size[value])
            for i, node in enumerate(graph.nodes)
            for value in node.outputs
            if value not in outputs
        ]
        self.shared = {
            i: _tensor_bytes(graph, node.outputs[0])
            for i, node in enumerate(graph.nodes)
            if _writes_over_residual(graph, node, i, readers, producers, halos) or _over_input(graph, node, i, readers)
        }

    def bytes(self, start: int, stop: int, inside: tuple[str, ...]) -> int:
        live = (size for name, made, last, size in self.tensors if made < stop and last >= start and name not in inside)
        return sum(live)

    def whole(self, i: int) -> int:
        """The bytes live while node i runs whole."""
        return self.bytes(i, i + 1, ()) - self.shared.get(i, 0)


def _writes_over_residual(graph: Graph, node: Node, i: int, readers, producers, halos) -> bool:
    """Whether plan-memory will put the Conv's output in its residual's memory: the residual dies
    here, both are channels-last tensors of one size and type without a halo, inside the arena."""
    if node.op != "Conv" or not node.attrs.residual or node.attrs.vector_axis == VectorAxis.PIXELS:
        return False
    residual, out = conv_extras(node)[1], node.outputs[0]
    source = producers.get(residual)
    planar = source.vectorises_pixels if source else True
    channels_last = source is not None and source.op in WINDOWED and not planar
    return (
        channels_last
        and readers.get(residual) == i
        and not graph.is_graph_output(residual)
        and not graph.is_graph_output(out)
        and graph.shape(residual) == graph.shape(out)
        and graph.dtype(residual) == graph.dtype(out)
        and residual not in halos
        and out not in halos
    )


def _over_input(graph: Graph, node: Node, i: int, readers: dict[str, int]) -> bool:
    """Whether plan-memory will compute the elementwise op in place: an input of its output's size
    and type, inside the arena, dies here."""
    if not IR_OPS[node.op].elementwise or graph.is_graph_output(node.outputs[0]):
        return False
    out = node.outputs[0]
    return any(
        readers.get(v) == i
        and graph.producer(v) is not None
        and not graph.is_graph_output(v)
        and graph.shape(v) == graph.shape(out)
        and graph.dtype(v) == graph.dtype(out)
        for v in node.inputs
    )


def _cheapest(count: int, steps: list[Step], limit: float) -> list[Step] | None:
    """The plan of least cost whose steps each need at most `limit` bytes, or None."""
    by_start: dict[int, list[Step]] = {}
    for step in steps:
        if step.bytes <= limit:
            by_start.setdefault(step.start, []).append(step)
    best: dict[int, tuple[float, list[Step]]] = {count: (0.0, [])}
    for i in reversed(range(count)):
        options = [(s.cost + best[s.stop][0], s) for s in by_start.get(i, ()) if s.stop in best]
        if options:
            cost, step = min(options, key=lambda o: o[0])
            best[i] = (cost, [step, *best[step.stop][1]])
    return best[0][1] if 0 in best else None


def _tensor_bytes(graph: Graph, value: str) -> int:
    return math.prod(graph.shape(value)) * graph.dtype(value).bytes


def _cost(plan: list[Step]) -> float:
    return sum(s.cost for s in plan)


def _bytes(plan: list[Step]) -> int:
    return max(s.bytes for s in plan)


def _in_place(plan: list[Step]) -> int:
    """In-place layers: at equal estimated time a plan runs in place only what its memory needs."""
    return sum(s.in_place for s in plan)
