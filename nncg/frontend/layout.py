"""The layout of the image inputs at the C boundary (--input-layout, input_layout=).

ONNX models from torch are NCHW; tf2onnx keeps Keras' NHWC at the graph inputs and transposes to NCHW
right after them. Asking for the other layout inserts a Transpose at each 4-D graph input (ONNX level,
before import): the C function takes the chosen layout, and cancel-transposes removes the inserted
Transpose together with tf2onnx's own, so no copy kernel is left for the common case.
"""

from __future__ import annotations

import onnx
from onnx import helper

from nncg.errors import NncgError
from nncg.ir.names import fresh_name
from nncg.safe_text import capped

LAYOUTS = ("nchw", "nhwc")
TF2ONNX = "tf2onnx"
# perm of the inserted Transpose: from the layout the C takes to the one the model has
_PERM = {("nchw", "nhwc"): (0, 2, 3, 1), ("nhwc", "nchw"): (0, 3, 1, 2)}


def check_layout(layout: object) -> None:
    if layout is not None and layout not in LAYOUTS:
        raise NncgError(
            f"input_layout must be one of {', '.join(map(repr, LAYOUTS))} or None; got {capped(repr(layout), 60)}"
        )


def model_layout(model: onnx.ModelProto) -> str:
    """The layout of the model's 4-D inputs: NHWC for tf2onnx's models (Keras, TensorFlow), else NCHW;
    after with_input_layout, the layout it gave them (recorded in producer_name)."""
    for layout in LAYOUTS:
        if model.producer_name.endswith(f"(input layout {layout})"):
            return layout
    return "nhwc" if model.producer_name == TF2ONNX else "nchw"


def image_inputs(model: onnx.ModelProto) -> list[onnx.ValueInfoProto]:
    constants = {t.name for t in model.graph.initializer}
    return [
        v
        for v in model.graph.input
        if v.name not in constants and v.type.tensor_type.HasField("shape") and len(v.type.tensor_type.shape.dim) == 4
    ]


def with_input_layout(model: onnx.ModelProto, layout: str | None) -> onnx.ModelProto:
    """`model` whose 4-D inputs take `layout` (None: the model's own); the input names are kept."""
    check_layout(layout)
    own = model_layout(model)
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
    out.producer_name = f"{model.producer_name} (input layout {layout})"
    return out
