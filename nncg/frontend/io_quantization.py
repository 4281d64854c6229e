"""ONNX front end: the scale and zero point of each integer graph input and output, which the header
states (NAME_X_SCALE, NAME_X_ZERO_POINT) so that a caller can quantise its inputs and dequantise its
outputs without opening the model. An input's are those of the DequantizeLinear or QLinear operator
that reads it, an output's those of the QuantizeLinear or QLinear operator that writes it, through
operators that move integers without changing them; a tensor read with different parameters, or
quantised per channel, has none."""

from __future__ import annotations

import numpy as np
import onnx

from .constants import constant_arrays
from .qdq import PASS_THROUGH

Quantization = tuple[float, int]  # (scale, zero point)

# where a QuantizeLinear or QLinear operator takes its output's scale and zero point
_OUTPUT_PARAMS = {
    "QuantizeLinear": 1, "QLinearConv": 6, "QLinearMatMul": 6, "QLinearAdd": 6, "QLinearMul": 6, "QGemm": 7,
    "QLinearAveragePool": 3, "QLinearGlobalAveragePool": 3, "QLinearLeakyRelu": 3, "QLinearSigmoid": 3,
    "QLinearSoftmax": 3, "QLinearConcat": 0,
}  # fmt: skip
# ops that move integers without changing them (their output is quantised as their input)
MOVING_OPS = frozenset({*PASS_THROUGH, "Squeeze", "Unsqueeze", "Identity"})
_FLOAT_TYPES = frozenset({onnx.TensorProto.FLOAT, onnx.TensorProto.DOUBLE, onnx.TensorProto.FLOAT16})


def io_quantization(model: onnx.ModelProto) -> dict[str, Quantization]:
    """ONNX name -> (scale, zero point) of the integer graph inputs and outputs that have them."""
    graph = model.graph
    consts = constant_arrays(graph)
    readers: dict[str, list[tuple[onnx.NodeProto, int]]] = {}
    writer: dict[str, onnx.NodeProto] = {}
    for node in graph.node:
        for i, name in enumerate(node.input):
            readers.setdefault(name, []).append((node, i))
        writer.update((name, node) for name in node.output if name)
    initializers = {t.name for t in graph.initializer}
    found = {}
    for value in graph.input:
        if value.name not in initializers and _is_integer(value):
            found[value.name] = _read_params(value.name, readers, consts)
    for value in graph.output:
        if _is_integer(value):
            found[value.name] = _written_params(value.name, writer, consts)
    return {name: q for name, q in found.items() if q is not None}


def _is_integer(value: onnx.ValueInfoProto) -> bool:
    return value.type.tensor_type.elem_type not in _FLOAT_TYPES


def _read_params(name: str, readers, consts) -> Quantization | None:
    """The parameters every reader of `name` (through moving operators) dequantises it with."""
    found = []
    for node, i in readers.get(name, []):
        if node.op_type in MOVING_OPS and i == 0:
            found.append(_read_params(node.output[0], readers, consts))
        elif _is_operand(node.op_type, i):
            found.append(_params(node, i + 1, consts))
        else:
            found.append(None)
    return _agreed(found)


def _is_operand(op: str, i: int) -> bool:
    """Whether input `i` of `op` is a quantised operand, its scale and zero point the next two inputs."""
    if op == "QLinearConcat":
        return i >= 2 and (i - 2) % 3 == 0
    if op in ("QLinearConv", "QLinearMatMul", "QLinearAdd", "QLinearMul", "QGemm"):
        return i in (0, 3)
    return i == 0 and (op == "DequantizeLinear" or op in _OUTPUT_PARAMS and op != "QuantizeLinear")


def _written_params(name: str, writer, consts) -> Quantization | None:
    node = writer.get(name)
    if node is None:
        return None
    if node.op_type in MOVING_OPS:
        return _written_params(node.input[0], writer, consts)
    return _params(node, _OUTPUT_PARAMS[node.op_type], consts) if node.op_type in _OUTPUT_PARAMS else None


def _params(node: onnx.NodeProto, at: int, consts) -> Quantization | None:
    """The scalar constant scale at input `at` and the zero point after it (0 when absent)."""
    scale = consts.get(node.input[at]) if at < len(node.input) else None
    zero_name = node.input[at + 1] if at + 1 < len(node.input) else ""
    zero = consts.get(zero_name) if zero_name else np.array(0)
    if scale is None or zero is None or scale.size != 1 or zero.size != 1:
        return None
    return float(np.float32(scale.reshape(()))), int(zero.reshape(()))


def _agreed(found: list[Quantization | None]) -> Quantization | None:
    return found[0] if found and found[0] is not None and all(q == found[0] for q in found) else None
