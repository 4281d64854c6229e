"""The layout of the image inputs at the C boundary (--input-layout, input_layout=).

ONNX models from torch are NCHW; tf2onnx keeps Keras' NHWC at the graph inputs and transposes to NCHW
right after them. Asking for the other layout inserts a Transpose at each 4-D graph input (ONNX level,
before import): the C function takes the chosen layout, and cancel-transposes removes the inserted
Transpose together with tf2onnx's own, so no copy kernel is left for the common case.

A model's own layout is read from its graph, not from its producer_name (text any model can set):
an input is NHWC when the graph converts it to NCHW before computing on it, as tf2onnx does.
"""

from __future__ import annotations

import math

import onnx
from onnx import helper, numpy_helper

from nncg.errors import NncgError
from nncg.frontend.constants import constant_tensors
from nncg.ir.names import fresh_name
from nncg.safe_text import capped

LAYOUTS = ("nchw", "nhwc")
# perm of the inserted Transpose: from the layout the C takes to the one the model has
_PERM = {("nchw", "nhwc"): (0, 2, 3, 1), ("nhwc", "nchw"): (0, 3, 1, 2)}


def check_layout(layout: object) -> None:
    if layout is not None and layout not in LAYOUTS:
        raise NncgError(
            f"input_layout must be one of {', '.join(map(repr, LAYOUTS))} or None; got {capped(repr(layout), 60)}"
        )


def model_layout(model: onnx.ModelProto, default: str = "nchw") -> str:
    """The layout of the model's 4-D inputs as its graph shows it (graph_layout), else `default`
    (ONNX's NCHW; the Keras route passes what Keras says)."""
    return graph_layout(model) or default


# Ops that leave the layout question open: they treat every axis alike when their other operands
# are single values (a Keras Rescaling's Mul, per-tensor quantisation), so the walk goes on past them.
_AXIS_BLIND = frozenset(
    {"Mul", "Add", "Sub", "Div", "Relu", "LeakyRelu", "Clip", "Identity", "Cast", "QuantizeLinear", "DequantizeLinear"}
)
_TO_NCHW = (0, 3, 1, 2)


def graph_layout(model: onnx.ModelProto) -> str | None:
    """ "nhwc" when the graph converts each 4-D input to NCHW before computing on it (a Transpose by
    (0, 3, 1, 2); with one channel, tf2onnx's Reshape of (N, H, W, 1) to (N, 1, H, W)), past ops blind
    to axes; "nchw" when one input goes to any other op first (a Conv, or the Transpose by (0, 2, 3, 1)
    with_input_layout inserts for "nchw" before tf2onnx's own); None without 4-D inputs."""
    found = {_input_layout(model.graph, value) for value in image_inputs(model)}
    if not found:
        return None
    return "nhwc" if found == {"nhwc"} else "nchw"


def _input_layout(graph: onnx.GraphProto, value: onnx.ValueInfoProto) -> str:
    dims = [d.dim_value if d.HasField("dim_value") else None for d in value.type.tensor_type.shape.dim]
    readers: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for name in set(node.input):
            readers.setdefault(name, []).append(node)
    values, returned = _single_values(graph), {v.name for v in graph.output}
    frontier, seen = [value.name], set()
    while frontier:
        name = frontier.pop()
        if name in returned or name not in readers:
            return "nchw"  # a path that never converts: nothing says the layout is not ONNX's own
        for node in readers[name]:
            if id(node) in seen:
                continue
            seen.add(id(node))
            others = [i for i in node.input[1:] if i]
            if node.op_type in _AXIS_BLIND and node.input[0] == name and all(i in values for i in others):
                frontier += [o for o in node.output if o]
            elif not _to_nchw(node, dims, graph):
                return "nchw"
    return "nhwc"


def _to_nchw(node: onnx.NodeProto, dims: list[int | None], graph: onnx.GraphProto) -> bool:
    """Whether the node turns an NHWC tensor of `dims` into NCHW."""
    if node.op_type == "Transpose":
        perm = next((tuple(a.ints) for a in node.attribute if a.name == "perm"), ())
        return perm == _TO_NCHW
    if node.op_type == "Reshape" and len(node.input) > 1 and dims[3] == 1 and None not in dims[1:3]:
        shape = _constant(graph, node.input[1])
        return shape is not None and len(shape) == 4 and list(shape[1:]) == [1, dims[1], dims[2]]
    return False


def _single_values(graph: onnx.GraphProto) -> set[str]:
    """Constants of one element."""
    return {name for name, tensor in constant_tensors(graph).items() if math.prod(tensor.dims) == 1}


def _constant(graph: onnx.GraphProto, name: str) -> list[int] | None:
    tensor = constant_tensors(graph).get(name)
    return None if tensor is None else numpy_helper.to_array(tensor).tolist()


def image_inputs(model: onnx.ModelProto) -> list[onnx.ValueInfoProto]:
    constants = {t.name for t in model.graph.initializer}
    return [
        v
        for v in model.graph.input
        if v.name not in constants and v.type.tensor_type.HasField("shape") and len(v.type.tensor_type.shape.dim) == 4
    ]


def with_input_layout(model: onnx.ModelProto, layout: str | None, own: str | None = None) -> onnx.ModelProto:
    """`model` whose 4-D inputs take `layout` (None: the model's own, `own` or else model_layout's);
    the input names are kept."""
    check_layout(layout)
    own = own or model_layout(model)
    if layout is None or layout == own:
        return model
    inputs = image_inputs(model)
    if not inputs:
        raise NncgError(f"input_layout {layout} is for models with 4-D (image) inputs; this model has none")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    perm = _PERM[(layout, own)]
    taken = {n for node in out.graph.node for n in (*node.input, *node.output)} | {v.name for v in out.graph.input}
    transposes = []
    for value in out.graph.input:
        if value.name not in {v.name for v in inputs}:
            continue
        inner = fresh_name(f"{value.name}_{own}", taken)
        taken.add(inner)
        for node in out.graph.node:
            node.input[:] = [inner if n == value.name else n for n in node.input]
        for output in out.graph.output:
            if output.name == value.name:
                raise NncgError(f"input {capped(value.name)} is also an output; input_layout cannot change it")
        dims = list(value.type.tensor_type.shape.dim)
        inverse = [perm.index(i) for i in range(4)]  # the C-side dims from the model-side ones
        new_dims = [dims[inverse[i]] for i in range(4)]
        copies = [onnx.TensorShapeProto.Dimension() for _ in range(4)]
        for copy, dim in zip(copies, new_dims):
            copy.CopyFrom(dim)
        del value.type.tensor_type.shape.dim[:]
        value.type.tensor_type.shape.dim.extend(copies)
        transposes.append(helper.make_node("Transpose", [value.name], [inner], name=inner, perm=list(perm)))
    nodes = transposes + list(out.graph.node)
    del out.graph.node[:]
    out.graph.node.extend(nodes)
    return out
