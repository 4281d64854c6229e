"""ONNX front end (ONNX -> graph IR), step 1 helpers: the graph's wiring, checked before onnx.checker
so that its generic complaints become messages naming the value, node or operator at fault.

Every value has one producer (a node, a graph input or an initializer); every value a node reads is
produced somewhere; the nodes form no cycle (a graph merely out of order is sorted, as onnxruntime
does); every operator exists in the model's opset and every node fits its schema.
"""

from __future__ import annotations

import heapq

import onnx
from onnx import defs

from nncg.errors import NncgError, UnsupportedOpsError
from nncg.frontend.names import node_names, node_reads
from nncg.safe_text import capped, escaped, shown

ONNX_OPERATORS_URL = "https://onnx.ai/onnx/operators/"


def check_wiring(graph: onnx.GraphProto) -> None:
    """Refuse values with two producers, reads of undefined values and cycles; sort the nodes into
    an order in which every value is produced before it is read (node names stay the same)."""
    names = node_names(graph)
    producers = _producers(graph, names)
    _check_defined(graph, names, producers)
    order = _topological_order(graph, producers)
    if len(order) < len(graph.node):
        raise NncgError(_cycle_message(graph, names, producers, set(range(len(graph.node))) - set(order)))
    if order != sorted(order):
        _reorder(graph, names, order)


def check_operators(graph: onnx.GraphProto, opset: int, ir_version: int) -> None:
    """Every default-domain operator exists in `opset`, and every node fits its schema (input and
    output counts, attributes): one message naming the node instead of onnx.checker's. Nodes with
    subgraphs are left to onnx.checker, which knows the outer values they may read; onnxruntime's
    contrib ops (load.CONTRIB_OPS) to their converters."""
    nodes = [(n, name) for n, name in zip(graph.node, node_names(graph), strict=True) if n.domain in ("", "ai.onnx")]
    unknown = [
        f"{capped(escaped(node.op_type))} (node {shown(name)})"
        for node, name in nodes
        if _schema(node.op_type, opset) is None or _schema(node.op_type, opset).deprecated
    ]
    if unknown:
        raise UnsupportedOpsError(
            f"operators that ONNX opset {opset} does not have (or has deprecated, as Upsample from opset 10): "
            f"{', '.join(unknown)}; NNCG compiles standard ONNX operators ({ONNX_OPERATORS_URL}): replace them "
            "(Upsample by Resize) or re-export the model"
        )
    context = onnx.checker.C.CheckerContext()
    context.ir_version = ir_version
    context.opset_imports = {"": opset, "ai.onnx": opset}
    for node, name in nodes:
        if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS) for a in node.attribute):
            continue
        try:
            onnx.checker.check_node(node, context)
        except Exception as exc:  # ValidationError
            schema = _schema(node.op_type, opset)
            raise NncgError(
                f"{node.op_type} node {shown(name)} does not fit the {node.op_type}-{schema.since_version} schema: "
                f"{_checker_detail(exc)}; give it the inputs, outputs and attributes that "
                f"{ONNX_OPERATORS_URL}onnx__{node.op_type}.html lists, or re-export the model"
            ) from None


def _schema(op_type: str, opset: int):
    try:
        return defs.get_schema(op_type, opset, "")
    except defs.SchemaError:
        return None


def _checker_detail(exc: BaseException) -> str:
    """The checker's sentence without its context trailer (which repeats the node's name and type)."""
    text = str(exc).split("==> Context:")[0]
    return " ".join(text.split()).rstrip(".") or type(exc).__name__


# --- producers and reads ---------------------------------------------------------------------------


def _producers(graph: onnx.GraphProto, names: list[str]) -> dict[str, int]:
    """value -> index of the node producing it; a second producer of any value is an error."""
    sources: dict[str, str] = {}
    for value in graph.input:
        _claim(sources, value.name, "a graph input")
    for tensor in graph.initializer:
        if sources.get(tensor.name) != "a graph input":  # IR < 4 lists initializers among the inputs
            _claim(sources, tensor.name, "an initializer")
    for sparse in graph.sparse_initializer:
        _claim(sources, sparse.values.name, "a sparse initializer")
    producers = {}
    for index, (node, name) in enumerate(zip(graph.node, names, strict=True)):
        for output in node.output:
            if output:
                _claim(sources, output, f"the output of {node.op_type} node {shown(name)}")
                producers[output] = index
    return producers


def _claim(sources: dict[str, str], value: str, source: str) -> None:
    if value in sources:
        raise NncgError(
            f"value {shown(value)} is both {sources[value]} and {source}; every value of an ONNX graph has "
            "exactly one source: rename one of them"
        )
    sources[value] = source


def _check_defined(graph: onnx.GraphProto, names: list[str], producers: dict[str, int]) -> None:
    defined = set(producers) | {v.name for v in graph.input} | {t.name for t in graph.initializer}
    defined |= {t.values.name for t in graph.sparse_initializer}
    for node, name in zip(graph.node, names, strict=True):
        for value in node.input:
            if value and value not in defined:
                raise NncgError(
                    f"{node.op_type} node {shown(name)} reads {shown(value)}, which no node, graph input or "
                    "initializer defines; the model is broken: fix the name or re-export it"
                )


def _dependencies(node: onnx.NodeProto, producers: dict[str, int]) -> set[int]:
    """Nodes whose outputs `node` reads, directly or from inside its subgraphs."""
    return {producers[value] for value in node_reads(node) if value in producers}


# --- order and cycles --------------------------------------------------------------------------------


def _topological_order(graph: onnx.GraphProto, producers: dict[str, int]) -> list[int]:
    """Node indices, each after the nodes it reads from, ties in the model's order; nodes on or
    behind a cycle are left out."""
    needs = [_dependencies(node, producers) - {index} for index, node in enumerate(graph.node)]
    self_loops = {index for index, node in enumerate(graph.node) if index in _dependencies(node, producers)}
    readers: dict[int, list[int]] = {}
    for index, deps in enumerate(needs):
        for dep in deps:
            readers.setdefault(dep, []).append(index)
    waiting = [len(deps) for deps in needs]
    ready = [i for i in range(len(needs)) if not waiting[i] and i not in self_loops]
    heapq.heapify(ready)
    order = []
    while ready:
        index = heapq.heappop(ready)
        order.append(index)
        for reader in readers.get(index, []):
            waiting[reader] -= 1
            if not waiting[reader] and reader not in self_loops:
                heapq.heappush(ready, reader)
    return order


def _cycle_message(graph: onnx.GraphProto, names: list[str], producers: dict[str, int], stuck: set[int]) -> str:
    cycle = _find_cycle(graph, producers, stuck)

    def described(index: int) -> str:
        return f"{graph.node[index].op_type} node {shown(names[index])}"

    loop = described(cycle[0])
    for position, index in enumerate(cycle):
        source = cycle[(position + 1) % len(cycle)]
        value = min(v for v in node_reads(graph.node[index]) if producers.get(v) == source)
        loop += f" reads {shown(value)} from {described(source)}" + (", which" if source != cycle[0] else "")
    return (
        f"the graph has a cycle: {loop}; an ONNX graph must be acyclic (loops belong in a Loop node): "
        "fix the wiring or re-export the model"
    )


def _find_cycle(graph: onnx.GraphProto, producers: dict[str, int], stuck: set[int]) -> list[int]:
    """A cycle among the nodes topological sorting could not place: walk from any of them to a node
    it reads from that is stuck too, until a node repeats."""
    path, seen = [], {}
    index = min(stuck)
    while index not in seen:
        seen[index] = len(path)
        path.append(index)
        index = min(dep for dep in _dependencies(graph.node[index], producers) if dep in stuck)
    return path[seen[index] :]


def _reorder(graph: onnx.GraphProto, names: list[str], order: list[int]) -> None:
    """Put the nodes in `order`, naming each after its name in the given order first, so names
    derived from positions (`<OpType>_<index>`) stay what they were."""
    nodes = [onnx.NodeProto() for _ in order]
    for target, index in zip(nodes, order, strict=True):
        target.CopyFrom(graph.node[index])
        target.name = names[index]
    del graph.node[:]
    graph.node.extend(nodes)
