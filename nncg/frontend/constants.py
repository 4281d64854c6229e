"""ONNX front end: the constants an ONNX graph states itself, its initializers and its Constant nodes'
`value` tensors, for the readers of the model as loaded (its input layout, the scale and zero point of
its integer inputs and outputs, the quantisation step of its tensors)."""

from __future__ import annotations

import numpy as np
import onnx
from onnx import numpy_helper


def constant_tensors(graph: onnx.GraphProto) -> dict[str, onnx.TensorProto]:
    """ONNX name -> tensor of every initializer and every Constant node's `value`."""
    found = {t.name: t for t in graph.initializer}
    found.update(
        (node.output[0], node.attribute[0].t)
        for node in graph.node
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value"
    )
    return found


def constant_arrays(graph: onnx.GraphProto) -> dict[str, np.ndarray]:
    """constant_tensors as arrays."""
    return {name: numpy_helper.to_array(tensor) for name, tensor in constant_tensors(graph).items()}
