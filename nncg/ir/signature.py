"""Signatures of layers built from the IR itself (not from its printed text): what --tune keys its
cache by, so the same layer in another model, or under another name, finds its earlier measurement.
Buffers are named by role and size, constants by shape, nodes by op, attributes and shapes."""

from __future__ import annotations

import hashlib
from dataclasses import fields, is_dataclass

import numpy as np

from .graph import Graph, Node
from .loops import Kernel, Load, Program, Store


def kernel_signature(program: Program, kernel: Kernel) -> str:
    """The kernel's loop nest with each buffer replaced by its role and size."""
    names = {b.name: f"{b.role}{b.size}" for b in program.buffers}
    return _digest((kernel.op, kernel.overlapping_stores, _canonical(kernel.body, names)))


def node_signature(graph: Graph, node: Node) -> str:
    """The node's op and attributes with the shapes of what it reads and writes (constant or not)."""
    values = tuple((graph.is_constant(v), graph.shape(v)) for v in (*node.inputs, *node.outputs))
    return _digest((node.op, _canonical(node.attrs, {}), values))


def layer_signature(ir: Graph | Program, layer: str) -> str:
    """The signature of the layer named `layer`: a node of a graph, a kernel of a program."""
    if isinstance(ir, Graph):
        return node_signature(ir, next(n for n in ir.nodes if n.name == layer))
    return kernel_signature(ir, next(k for k in ir.kernels if k.name == layer))


def ir_signature(ir: Graph | Program) -> str:
    """The whole graph's signature, or every kernel's in order."""
    if isinstance(ir, Graph):
        return graph_signature(ir)
    return hashlib.sha256("|".join(kernel_signature(ir, k) for k in ir.kernels).encode()).hexdigest()


def graph_signature(graph: Graph) -> str:
    """Every node's signature in order, with how each reads the earlier ones' outputs."""
    producers = {v: i for i, n in enumerate(graph.nodes) for v in n.outputs}
    wiring = tuple(tuple(producers.get(v, -1) for v in n.inputs) for n in graph.nodes)
    return _digest((tuple(node_signature(graph, n) for n in graph.nodes), wiring))


def _canonical(value: object, names: dict[str, str]) -> object:
    if isinstance(value, (Load, Store)):
        rest = tuple(_canonical(getattr(value, f.name), names) for f in fields(value) if f.name != "buffer")
        return (type(value).__name__, names.get(value.buffer, value.buffer), rest)
    if is_dataclass(value):
        return (type(value).__name__, tuple(_canonical(getattr(value, f.name), names) for f in fields(value)))
    if isinstance(value, tuple):
        return tuple(_canonical(v, names) for v in value)
    if isinstance(value, np.ndarray):
        return ("array", value.shape)
    return value


def _digest(value: object) -> str:
    return hashlib.sha256(repr(value).encode()).hexdigest()
