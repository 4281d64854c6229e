"""ONNX front end (ONNX -> graph IR): ONNX shape inference and reading static shapes and dtypes.

Shared by loading (validating the user's model) and folding (re-inferring after constants fold).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

from nncg.errors import NncgError
from nncg.frontend.context import OnnxOp
from nncg.frontend.names import node_names
from nncg.frontend.windows import pool_attrs, pool_output_shape
from nncg.ir.graph import Shape
from nncg.safe_text import capped, escaped, shown

POOLS = ("MaxPool", "AveragePool")
RESIZES = ("Resize", "Upsample")


def inferred_shapes(model: onnx.ModelProto) -> dict[str, Shape]:
    """Static shapes of all values by strict ONNX inference, ceil-mode pool and Resize outputs fixed.

    ONNX's MaxPool and AveragePool inference before opset 22 ignores the spec rule that drops a
    window starting in the end padding (onnxruntime follows it), its Resize inference rounds n * scale
    in double where onnxruntime uses float32, and its ConvTranspose inference adds output_padding to a
    SAME output (onnxruntime gives in * stride), and it leaves GroupNormalization's (opset 21) unknown;
    such outputs are pinned to the right shape,
    fed in as inputs, and inference re-runs so everything downstream (and Shape folding) sees the
    real shape. A negative dimension anywhere is refused, naming the node that makes it.
    """
    pinned: dict[str, Shape] = {}
    while True:
        shapes = static_shapes(infer(_inference_model(model, pinned)))
        wrong = _misinferred(model, shapes, pinned)
        if wrong is None:
            _check_no_negative_dims(model, shapes)
            _check_declared_outputs(model, shapes)
            return shapes
        pinned[wrong[0]] = wrong[1]


def infer(model: onnx.ModelProto) -> onnx.ModelProto:
    """Strict ONNX shape inference; any inconsistency becomes a one-line NncgError."""
    try:
        return onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    except Exception as exc:  # onnx raises InferenceError, ValidationError or RuntimeError
        raise NncgError(
            f"ONNX shape inference finds the model inconsistent: {one_line(exc)}; fix the node it names (its "
            "attributes or its inputs' shapes, e.g. through --input-shape) or re-export the model"
        ) from None


def one_line(exc: BaseException, limit: int = 300) -> str:
    """An exception text squeezed into one line, short enough for a CLI message."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."


def dtype_name(elem_type: int) -> str:
    """numpy-style name of an ONNX element type: 'float32', 'int64', 'float16', ..."""
    names = {onnx.TensorProto.FLOAT: "float32", onnx.TensorProto.DOUBLE: "float64"}
    if elem_type in names:
        return names[elem_type]
    try:
        return onnx.TensorProto.DataType.Name(elem_type).lower()
    except ValueError:
        return f"type {elem_type}"


def static_shape(value: onnx.ValueInfoProto) -> Shape | None:
    """The shape if it is fully known (rank and every dim), else None."""
    ttype = value.type.tensor_type
    if not value.type.HasField("tensor_type") or not ttype.HasField("shape"):
        return None
    dims = ttype.shape.dim
    if not all(d.HasField("dim_value") for d in dims):
        return None
    return tuple(int(d.dim_value) for d in dims)


def static_shapes(model: onnx.ModelProto) -> dict[str, Shape]:
    """Every value of the main graph whose shape ONNX (inference) knows statically."""
    graph = model.graph
    shapes = {}
    for value in (*graph.input, *graph.value_info, *graph.output):
        shape = static_shape(value)
        if shape is not None:
            shapes[value.name] = shape
    return shapes


def format_shape(name: str, value: onnx.ValueInfoProto) -> str:
    """`x[N,3,224,224]` with dim_params as names and unknown dims as '?' (outside text escaped)."""
    ttype = value.type.tensor_type
    shown_name = capped(escaped(name))
    if not ttype.HasField("shape"):
        return f"{shown_name}[unknown rank]"
    dims = [_dim_text(d) for d in ttype.shape.dim]
    return f"{shown_name}[{','.join(dims)}]"


def _dim_text(dim: onnx.TensorShapeProto.Dimension) -> str:
    if dim.HasField("dim_value"):
        return str(dim.dim_value)
    return capped(escaped(dim.dim_param), 20) or "?"


def _misinferred(model: onnx.ModelProto, shapes: dict[str, Shape], pinned: dict) -> tuple[str, Shape] | None:
    """The first output whose ONNX-inferred shape differs from what onnxruntime computes."""
    initializers = {t.name: t for t in model.graph.initializer}
    for node, name in zip(model.graph.node, node_names(model.graph), strict=True):
        if node.output[0] in pinned or not node.input or node.input[0] not in shapes:
            continue
        in_shape = shapes[node.input[0]]
        if node.op_type in POOLS and OnnxOp.of(node, name).attr("ceil_mode", 0):
            expected = pool_output_shape(pool_attrs(OnnxOp.of(node, name), in_shape), in_shape)
        elif node.op_type in RESIZES:
            expected = _resize_output_shape(OnnxOp.of(node, name), in_shape, initializers)
        elif node.op_type == "ConvTranspose":
            expected = _same_conv_transpose_shape(OnnxOp.of(node, name), in_shape, shapes.get(node.output[0]))
        elif node.op_type == "GroupNormalization":
            expected = in_shape  # a function op whose output ONNX inference leaves unknown
        else:
            continue
        if expected is not None and shapes.get(node.output[0]) != expected and min(expected) >= 1:
            return node.output[0], expected
    return None


def _same_conv_transpose_shape(op: OnnxOp, in_shape: Shape, inferred: Shape | None) -> Shape | None:
    """in * stride per spatial dim for auto_pad SAME, as onnxruntime (ONNX inference adds output_padding)."""
    if inferred is None or op.attr("output_shape") is not None:
        return None
    if op.attr("auto_pad", "NOTSET") not in ("SAME_UPPER", "SAME_LOWER"):
        return None
    strides = op.attr("strides") or [1] * (len(in_shape) - 2)
    return (*inferred[:2], *(int(i) * int(s) for i, s in zip(in_shape[2:], strides)))


def _resize_output_shape(op: OnnxOp, in_shape: Shape, initializers: dict) -> Shape | None:
    """floor(n * scale) in float32, as onnxruntime computes it, for a Resize or Upsample with constant
    scales (ONNX inference computes it in double: 10 x 1.3 is 13 for onnxruntime, 12 for inference)."""
    scales_at = 1 if op.type == "Upsample" or len(op.node.input) == 2 else 2
    scales_name = op.input(scales_at)
    if (len(op.node.input) > 3 and op.input(3)) or scales_name not in initializers or op.attr("axes") is not None:
        return None
    if op.attr("coordinate_transformation_mode") == "tf_crop_and_resize":
        return None
    scales = numpy_helper.to_array(initializers[scales_name]).astype(np.float32).reshape(-1)
    if scales.size != len(in_shape):
        return None
    return tuple(int(np.floor(s * np.float32(n))) for s, n in zip(scales, in_shape))


def _inference_model(model: onnx.ModelProto, pinned: dict[str, Shape]) -> onnx.ModelProto:
    """A copy for inference: outputs without declared shapes (checked afterwards instead), and the
    nodes producing pinned values cut out, those values becoming inputs of the pinned shape."""
    graph = model.graph
    cut = [n for n in graph.node if n.output[0] in pinned]
    extra = [helper.make_tensor_value_info(n.output[0], onnx.TensorProto.FLOAT, pinned[n.output[0]]) for n in cut]
    extra += [  # a cut MaxPool's Indices would otherwise be undefined
        helper.make_tensor_value_info(n.output[1], onnx.TensorProto.INT64, pinned[n.output[0]])
        for n in cut
        if len(n.output) > 1 and n.output[1]
    ]
    outputs = [helper.make_tensor_value_info(v.name, v.type.tensor_type.elem_type, None) for v in graph.output]
    nodes = [n for n in graph.node if n.output[0] not in pinned]
    copy = helper.make_graph(nodes, graph.name, [*graph.input, *extra], outputs, list(graph.initializer))
    copy.sparse_initializer.extend(graph.sparse_initializer)
    return helper.make_model(copy, opset_imports=list(model.opset_import), ir_version=model.ir_version)


def _check_no_negative_dims(model: onnx.ModelProto, shapes: dict[str, Shape]) -> None:
    """ONNX inference lets a kernel larger than its padded input make negative dimensions (onnxruntime
    then refuses to run the model); say which node does it, from which input shapes."""
    for node, name in zip(model.graph.node, node_names(model.graph), strict=True):
        for output in node.output:
            shape = shapes.get(output)
            if shape is None or min(shape, default=1) >= 0:
                continue
            known = shapes | {t.name: tuple(t.dims) for t in model.graph.initializer}
            inputs = ", ".join(f"{shown(i)} {list(known[i])}" for i in node.input if i in known)
            raise NncgError(
                f"{node.op_type} node {shown(name)} gives its output {shown(output)} the shape {list(shape)}: a "
                f"negative dimension, as its attributes do not fit inputs {inputs or 'of unknown shape'} (a kernel "
                "larger than the padded input, or pads that crop away its whole output); onnxruntime refuses it "
                "too: fix the node's attributes or give a larger --input-shape"
            )


def _check_declared_outputs(model: onnx.ModelProto, shapes: dict[str, Shape]) -> None:
    for value in model.graph.output:
        declared = static_shape(value)
        if declared is not None and value.name in shapes and shapes[value.name] != declared:
            raise NncgError(
                f"output {shown(value.name)} is declared with shape {list(declared)} but computes "
                f"{list(shapes[value.name])}; fix the declared output shape or the input shapes"
            )
