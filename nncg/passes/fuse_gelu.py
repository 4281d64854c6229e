"""Part of graph pass `fuse-activation`: the GELU decompositions torch.onnx exports below opset 20
(both exporters) made one Gelu activation node, which x's producer can then apply at its store.

    exact  0.5 * x * (1 + Erf(x / sqrt(2)))                    Div by sqrt(2), or Mul by 1/sqrt(2)
    tanh   0.5 * x * (1 + Tanh(sqrt(2/pi) * (x + 0.044715 * x*x*x)))

The three factors x, 0.5 and the gate (1 + ...) may be multiplied in any association and order
(the legacy exporter: (x * gate) * 0.5; onnxscript: 0.5 * (x * gate) or x * (0.5 * gate); others
(x * 0.5) * gate), each commutative op with its operands either way round. Each constant is one
element within RTOL of its exact value; each intermediate is read by the next node of the pattern
only and is no graph output, so nothing else needs it stored. The cube x*x*x is two Muls (either
association) or Pow(x, 3), onnxscript's form, which the front end made a pow activation node."""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations

import numpy as np

from ..ir.graph import Activation, Graph, Node
from ..ir.kinds import GeluApproximation
from .rewrite import sole_consumer

RTOL = 1e-6  # float32 rounding of the constants is 6e-8 relative; 0.7071 (4 digits) is another function
SQRT_2 = math.sqrt(2.0)
SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)
TANH_CUBIC = 0.044715


@dataclass(frozen=True)
class _Part:
    """The tensor x a part of the pattern reads and the part's nodes."""

    x: str
    nodes: tuple[Node, ...]


def fuse_gelu(graph: Graph) -> Graph:
    """Every GELU decomposition made one Gelu node, at the place of its last Mul."""
    for mul in graph.nodes:
        found = _gelu_ending_in(graph, mul) if mul.op == "Mul" else None
        if found is not None:
            return fuse_gelu(_make_gelu(graph, mul, *found))
    return graph


def _make_gelu(graph: Graph, last: Node, approximate: GeluApproximation, part: _Part) -> Graph:
    fused = Node("Gelu", last.name, (part.x,), last.outputs, Activation("gelu", approximate=approximate))
    dropped = {id(n) for n in part.nodes}
    # At the last Mul's place: x exists before the pattern, which is before the last Mul.
    return graph.with_nodes([fused if n is last else n for n in graph.nodes if id(n) not in dropped])


def _gelu_ending_in(graph: Graph, last: Node) -> tuple[GeluApproximation, _Part] | None:
    """The GELU whose last Mul is `last`: two Muls of x, 0.5 and a gate of x."""
    if len(last.inputs) != 2:
        return None
    for product, factor in (last.inputs, last.inputs[::-1]):
        first = _written_for(graph, product, last, "Mul")
        if first is None or len(first.inputs) != 2:
            continue
        factors = ((factor, last), *((name, first) for name in first.inputs))  # (name, the Mul reading it)
        for (half, _), (x, _), (gate, reader) in permutations(factors):
            found = _gate(graph, gate, reader) if _is_constant(graph, half, 0.5) else None
            if found is not None and found[1].x == x and graph.shape(x) == graph.shape(last.outputs[0]):
                approximate, part = found
                return approximate, _Part(x, (first, *part.nodes))
    return None


def _gate(graph: Graph, value: str, reader: Node) -> tuple[GeluApproximation, _Part] | None:
    """1 + Erf(...) or 1 + Tanh(...) written to `value` for `reader` alone."""
    add = _written_for(graph, value, reader, "Add")
    term = None if add is None else _operand_besides(graph, add, 1.0)
    if term is None:
        return None
    for approximate, part_of in PARTS.items():
        part = part_of(graph, term, add)
        if part is not None:
            return approximate, _Part(part.x, (add, *part.nodes))
    return None


def _erf_part(graph: Graph, value: str, reader: Node) -> _Part | None:
    """Erf(x / sqrt(2)) or Erf(x * (1/sqrt(2))) written to `value` for `reader` alone."""
    erf = _written_for(graph, value, reader, "Erf")
    if erf is None:
        return None
    div = _written_for(graph, erf.inputs[0], erf, "Div")
    if div is not None and _is_constant(graph, div.inputs[1], SQRT_2):
        return _Part(div.inputs[0], (erf, div))
    mul = _written_for(graph, erf.inputs[0], erf, "Mul")
    x = None if mul is None else _operand_besides(graph, mul, 1 / SQRT_2)
    return None if x is None else _Part(x, (erf, mul))


def _tanh_part(graph: Graph, value: str, reader: Node) -> _Part | None:
    """Tanh(sqrt(2/pi) * (x + 0.044715 * x*x*x)) written to `value` for `reader` alone."""
    tanh = _written_for(graph, value, reader, "Tanh")
    scale = None if tanh is None else _written_for(graph, tanh.inputs[0], tanh, "Mul")
    inner = None if scale is None else _operand_besides(graph, scale, SQRT_2_OVER_PI)
    add = None if inner is None else _written_for(graph, inner, scale, "Add")
    if add is None:
        return None
    for x, term in (add.inputs, add.inputs[::-1]):
        mul = _written_for(graph, term, add, "Mul")
        cube = None if mul is None else _operand_besides(graph, mul, TANH_CUBIC)
        cube_nodes = None if cube is None else _cube(graph, cube, mul, x)
        if cube_nodes is not None:
            return _Part(x, (tanh, scale, add, mul, *cube_nodes))
    return None


def _cube(graph: Graph, value: str, reader: Node, x: str) -> tuple[Node, ...] | None:
    """The nodes of x * (x * x), (x * x) * x or Pow(x, 3) written to `value` for `reader` alone."""
    power = _written_for(graph, value, reader, "Pow")
    if power is not None:
        return (power,) if power.inputs == (x,) and power.attrs.alpha == 3.0 else None
    outer = _written_for(graph, value, reader, "Mul")
    if outer is None or len(outer.inputs) != 2 or x not in outer.inputs:
        return None
    square_value = outer.inputs[1] if outer.inputs[0] == x else outer.inputs[0]
    square = _written_for(graph, square_value, outer, "Mul")
    return None if square is None or square.inputs != (x, x) else (outer, square)


PARTS = {GeluApproximation.NONE: _erf_part, GeluApproximation.TANH: _tanh_part}


def _written_for(graph: Graph, value: str, reader: Node, op: str) -> Node | None:
    """The `op` node writing `value`, when `reader` is the only node reading it and it is no graph output."""
    node = graph.producer(value)
    if node is None or node.op != op or sole_consumer(graph, value) is not reader:
        return None
    return node


def _operand_besides(graph: Graph, node: Node, constant: float) -> str | None:
    """The other operand of a two-input node whose one operand is the one-element `constant`."""
    if len(node.inputs) != 2:
        return None
    a, b = node.inputs
    if _is_constant(graph, b, constant):
        return a
    return b if _is_constant(graph, a, constant) else None


def _is_constant(graph: Graph, name: str, value: float) -> bool:
    array = graph.constants.get(name)
    return array is not None and array.size == 1 and bool(np.isclose(array.item(), value, rtol=RTOL, atol=0.0))
