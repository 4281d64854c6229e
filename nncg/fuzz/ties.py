"""Nearest-neighbour Resize at a tie: an output coordinate that maps exactly half-way between two
input pixels in real arithmetic (6.5 / 1.3 - 0.5 = 4.5) lands on either side of the half in float32,
and onnxruntime, onnx.reference and NNCG each round such ties their own way. A mismatch on a model
with such a coordinate is outcome `resize-tie`, not blamed on NNCG (see nncg/lowering/resize.py)."""

from __future__ import annotations

import math

import numpy as np
import onnx
from onnx import numpy_helper

from ..lowering.resize import source_coordinate

TIE_ULPS = 4  # how close to a half-way point, in float32 ulps, a coordinate counts as a tie


def has_nearest_resize_tie(model: onnx.ModelProto) -> bool:
    """Whether some nearest Resize of the model (with constant scales or sizes) has a tie."""
    inferred = onnx.shape_inference.infer_shapes(model)
    shapes = {v.name: _dims(v) for v in (*inferred.graph.input, *inferred.graph.value_info, *inferred.graph.output)}
    constants = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type not in ("Resize", "Upsample"):
            continue
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        rounding = _text(attrs.get("nearest_mode", b"round_prefer_floor"))
        if _text(attrs.get("mode", b"nearest")) != "nearest" or not rounding.startswith("round"):
            continue
        in_shape, out_shape = shapes.get(node.input[0]), shapes.get(node.output[0])
        if in_shape and out_shape and _tie(node, attrs, in_shape, out_shape, constants):
            return True
    return False


def _tie(node, attrs, in_shape, out_shape, constants) -> bool:
    mode = _text(attrs.get("coordinate_transformation_mode", b"half_pixel"))
    given = [constants.get(name) for name in node.input[1:]]
    scales = next((g for g in given if g is not None and g.dtype.kind == "f" and g.size), None)
    for d, (n_in, n_out) in enumerate(zip(in_shape, out_shape)):
        scale = np.float32(scales.reshape(-1)[d]) if scales is not None and scales.size == len(in_shape) else None
        scale = scale if scale is not None else np.float32(n_out) / np.float32(n_in)
        if scale == 1 or n_in == n_out:
            continue
        for o in range(n_out):
            x = float(source_coordinate(mode, np.float32(o), scale, n_in, n_out))
            half = math.floor(x) + 0.5
            if abs(x - half) <= TIE_ULPS * float(np.spacing(np.float32(abs(half)))):
                return True
    return False


def _dims(value: onnx.ValueInfoProto) -> tuple[int, ...] | None:
    dims = value.type.tensor_type.shape.dim
    return tuple(d.dim_value for d in dims) if all(d.HasField("dim_value") for d in dims) and dims else None


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)
