"""Graph pass `cancel-transposes`: layout Transposes (as tf2onnx wraps every NHWC convolution in,
Transpose(0,3,1,2) -> Conv -> Transpose(0,2,3,1)) are pushed towards the outputs until inverse pairs meet
and cancel, so the NCHW ops between them become adjacent to their producers again (a Clip or a residual Add
can then fuse into the Conv).

Rules, applied until none fires:
- two Transposes in a row compose into one; one with the identity permutation disappears (one writing a
  graph output makes its input's producer write the output);
- a Transpose that only moves size-1 dims, read by a Reshape, is skipped by it (same row-major order);
- a node whose runtime inputs all come from Transposes with the same permutation p runs before the
  transpose instead (a Transpose also read by a node that cannot take it, such as a Conv or a Reshape, stays
  where it is): y = op(T_p(a), T_p(b), c) becomes op(a, b, c') -> T_p. This holds
  for the pointwise activations, Add, Sub, Mul, Div, Max, Min, Sum and PRelu (a constant operand c is
  broadcast to the output's rank and permuted by p's inverse), Concat (axis remapped), Pad and Slice (per-dim
  attributes permuted), Softmax and LogSoftmax (axis remapped) and the reductions, ReduceMean, ReduceSum,
  ReduceMax, ... (axes remapped; without keepdims the Transpose of what is left, if any).
A Transpose that reads a graph input, or writes a graph output, stays: the C API's layout does not change. A
node writing a graph output keeps the Transpose in front of it (lowered, that Transpose is a free relabelling;
after the node, it would be a copy kernel).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir import names
from ..ir.graph import (
    Activation,
    ConcatAttrs,
    Graph,
    Node,
    ReduceAttrs,
    SliceAttrs,
    SoftmaxAttrs,
    TransposeAttrs,
)
from .rewrite import fresh_name, rename_input

POINTWISE = ("Add", "Sub", "Mul", "Div", "Max", "Min", "Sum", "PRelu")


def cancel_transposes(graph: Graph) -> Graph:
    while True:
        rewritten = _compose(graph) or _push(graph)
        if rewritten is None:
            return graph
        graph = _drop_dead_transposes(rewritten)


# --- Transpose after Transpose -------------------------------------------------------------------------


def _compose(graph: Graph) -> Graph | None:
    for node in graph.nodes:
        if node.op != "Transpose":
            continue
        perm = node.attrs.perm
        out = node.outputs[0]
        if _is_identity(perm) and not graph.is_graph_output(out):
            return _bypass(graph, node)
        if _is_identity(perm) and _writes_privately(graph, node.inputs[0], node):
            return _retarget(graph, node)
        inner = graph.producer(node.inputs[0])
        if inner is not None and inner.op == "Transpose":  # out dim k = inner's input dim inner_perm[perm[k]]
            composed = tuple(inner.attrs.perm[k] for k in perm)
            return _replace(graph, node, replace(node, inputs=inner.inputs, attrs=TransposeAttrs(composed)))
        if _moves_only_ones(graph, node):
            if any(n.op == "Reshape" for n in graph.consumers(out)):
                src = node.inputs[0]
                nodes = [rename_input(n, out, src) if n.op == "Reshape" else n for n in graph.nodes]
                return graph.with_nodes(nodes)
    return None


def _bypass(graph: Graph, node: Node) -> Graph:
    """Readers of node's output read its input; node disappears."""
    src, dst = node.inputs[0], node.outputs[0]
    return graph.with_nodes(rename_input(n, dst, src) for n in graph.nodes if n is not node)


def _writes_privately(graph: Graph, value: str, reader: Node) -> bool:
    """value is computed by a node and read by `reader` alone."""
    return (
        graph.producer(value) is not None
        and not graph.is_graph_output(value)
        and all(n is reader for n in graph.consumers(value))
    )


def _retarget(graph: Graph, node: Node) -> Graph:
    """An identity Transpose writing a graph output: its input's producer writes the output instead."""
    src, dst = node.inputs[0], node.outputs[0]
    producer = graph.producer(src)
    renamed = replace(producer, outputs=tuple(dst if o == src else o for o in producer.outputs))
    return graph.with_nodes(renamed if n is producer else n for n in graph.nodes if n is not node)


def _moves_only_ones(graph: Graph, node: Node) -> bool:
    """The Transpose keeps the order of the input's dims bigger than 1: a reshape."""
    shape = graph.shape(node.inputs[0])
    kept = [d for d in node.attrs.perm if shape[d] != 1]
    return kept == sorted(kept)


def _is_identity(perm) -> bool:
    return tuple(perm) == tuple(range(len(perm)))


# --- pushing a Transpose past the node that reads it -------------------------------------------------


def _push(graph: Graph) -> Graph | None:
    for node in graph.nodes:
        pushed = _push_one(graph, node)
        if pushed is not None:
            return pushed
    return None


def _push_one(graph: Graph, node: Node) -> Graph | None:
    if len(node.outputs) != 1:
        return None
    data = [name for name in node.inputs if not graph.is_constant(name)]
    transposes = [graph.producer(name) for name in data]
    if not transposes or not all(t is not None and t.op == "Transpose" for t in transposes):
        return None
    perm = transposes[0].attrs.perm
    if any(t.attrs.perm != perm for t in transposes):
        return None
    if any(graph.is_graph_output(name) or not _all_movable(graph, name, node, perm) for name in data):
        return None
    rewritten = _rewrite(graph, node, perm)
    if rewritten is None:
        return None
    new_node, added, out_perm = rewritten
    constants = {**graph.constants, **added}
    if out_perm is not None and graph.is_graph_output(node.outputs[0]):
        return None  # the Transpose would be a copy kernel at the output, where node writes it in place
    source = {t.outputs[0]: t.inputs[0] for t in transposes}
    new_node = replace(new_node, inputs=tuple(source.get(name, name) for name in new_node.inputs))
    out = node.outputs[0]
    out_shape = graph.shape(out)
    if out_perm is None:  # nothing left to transpose
        return _replace(graph, node, replace(new_node, outputs=(out,)), constants)
    inverse = _inverse(out_perm)
    inner = fresh_name(graph, f"{out}_{_perm_text(inverse)}", constants)
    node_names = {n.name for n in graph.nodes}
    transpose = Node(
        "Transpose",
        names.fresh_name(f"{node.name}_transpose", node_names),
        (inner,),
        (out,),
        TransposeAttrs(tuple(out_perm)),
    )
    nodes = []
    for n in graph.nodes:
        nodes += [replace(new_node, outputs=(inner,)), transpose] if n is node else [n]
    shaped = replace(graph, shapes={**graph.shapes, inner: tuple(out_shape[k] for k in inverse)})
    return shaped.with_nodes(nodes, constants)


def _all_movable(graph: Graph, value: str, node: Node, perm) -> bool:
    """Every other reader of the transposed value is a Transpose or can take the Transpose too: pushing into
    node keeps the Transpose for them, and it disappears once they have taken it (a Conv reader would keep
    it for good, and pushing would only add a Transpose)."""
    return all(
        reader is node or reader.op == "Transpose" or _rewrite(graph, reader, perm) is not None
        for reader in graph.consumers(value)
    )


def _rewrite(graph: Graph, node: Node, perm) -> tuple[Node, dict, tuple[int, ...] | None] | None:
    """The node computing on the untransposed inputs (constant inputs still to rename), the constants it
    adds and the permutation its output still needs (None: none); None if the node cannot move."""
    rank = len(perm)
    inverse = _inverse(perm)
    added: dict[str, np.ndarray] = {}
    attrs = node.attrs
    if isinstance(attrs, Activation):
        return (node, added, perm) if len(node.inputs) == 1 else None
    if node.op in POINTWISE:
        if len(graph.shape(node.outputs[0])) != rank:
            return None
        inputs = []
        for name in node.inputs:
            if graph.is_constant(name):
                value = graph.constants[name]
                if value.ndim > rank:
                    return None
                value = np.transpose(value.reshape((1,) * (rank - value.ndim) + value.shape), inverse)
                name = fresh_name(graph, f"{name}_{_perm_text(inverse)}", added)
                added[name] = np.ascontiguousarray(value)
            elif len(graph.shape(name)) != rank:
                return None
            inputs.append(name)
        return replace(node, inputs=tuple(inputs)), added, perm
    if node.op == "Concat":
        if any(graph.is_constant(name) for name in node.inputs):
            return None
        return replace(node, attrs=ConcatAttrs(perm[attrs.axis])), added, perm
    if node.op == "Pad":
        begin, end = (tuple(pads[k] for k in inverse) for pads in (attrs.pads_begin, attrs.pads_end))
        return replace(node, attrs=replace(attrs, pads_begin=begin, pads_end=end)), added, perm
    if node.op == "Slice":
        starts, steps = (tuple(values[k] for k in inverse) for values in (attrs.starts, attrs.steps))
        return replace(node, attrs=SliceAttrs(starts, steps)), added, perm
    if node.op in ("Softmax", "LogSoftmax") and not attrs.coerce_2d:
        return replace(node, attrs=SoftmaxAttrs(perm[attrs.axis])), added, perm
    if isinstance(attrs, ReduceAttrs):
        axes = tuple(sorted(perm[a] for a in attrs.axes))
        new_node = replace(node, attrs=ReduceAttrs(axes, attrs.keepdims))
        if attrs.keepdims:
            return new_node, added, perm
        left = [d for d in range(rank) if d not in axes]  # the input dims the output keeps, in order
        out_perm = tuple(left.index(perm[k]) for k in range(rank) if k not in attrs.axes)
        return new_node, added, None if _is_identity(out_perm) else out_perm
    return None


# --- helpers ----------------------------------------------------------------------------------------------


def _inverse(perm) -> tuple[int, ...]:
    inverse = [0] * len(perm)
    for k, d in enumerate(perm):
        inverse[d] = k
    return tuple(inverse)


def _perm_text(perm) -> str:
    return "t" + "".join(map(str, perm))


def _replace(graph: Graph, old: Node, new: Node, constants=None) -> Graph:
    return graph.with_nodes((new if n is old else n for n in graph.nodes), constants)


def _drop_dead_transposes(graph: Graph) -> Graph:
    read = {name for n in graph.nodes for name in n.inputs} | {v.name for v in graph.outputs}
    kept = [n for n in graph.nodes if n.op != "Transpose" or n.outputs[0] in read]
    return graph.with_nodes(kept) if len(kept) < len(graph.nodes) else graph
