"""ONNX front end (ONNX -> graph IR), step 3 helpers: `OnnxOp` (one ONNX node, attributes decoded)
and `Context` (folded constants, static shapes, fresh names) are what every op converter sees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import onnx
from onnx import helper

from nncg.errors import NncgError
from nncg.ir.graph import Node, Shape
from nncg.ir.names import fresh_name
from nncg.safe_text import shown

WEIGHT_HINT = "runtime weights are not supported yet: export the model with constant weights"
SHAPE_HINT = "NNCG needs it constant: simplify the model (e.g. with onnxsim) after fixing the input shapes"


@dataclass(frozen=True)
class OnnxOp:
    """One ONNX node with its stable name and decoded attributes."""

    node: onnx.NodeProto
    name: str
    attrs: dict[str, object] = field(default_factory=dict)

    @classmethod
    def of(cls, node: onnx.NodeProto, name: str) -> OnnxOp:
        attrs = {a.name: _decode(helper.get_attribute_value(a)) for a in node.attribute}
        return cls(node, name, attrs)

    @property
    def type(self) -> str:
        return self.node.op_type

    def attr(self, key: str, default: object = None) -> object:
        return self.attrs.get(key, default)

    def input(self, index: int) -> str | None:
        """The input's value name, or None when it is omitted ("" or past the end)."""
        inputs = self.node.input
        return inputs[index] if index < len(inputs) and inputs[index] else None

    def output(self, index: int) -> str | None:
        outputs = self.node.output
        return outputs[index] if index < len(outputs) and outputs[index] else None

    def error(self, message: str) -> NncgError:
        return NncgError(f"{self.type} {shown(self.name)} {message}")

    def ir_node(self, op: str, inputs: tuple[str, ...] | list[str], attrs: object = None) -> Node:
        """The graph IR node for this op; only the first ONNX output survives conversion."""
        return Node(op=op, name=self.name, inputs=tuple(inputs), outputs=(self.node.output[0],), attrs=attrs)

    def ir_step(self, op: str, step: str, inputs: tuple[str, ...] | list[str], output: str, attrs: object) -> Node:
        """A graph IR node computing an intermediate value of this op (which becomes several IR nodes;
        the last one, made by ir_node, keeps the op's name)."""
        return Node(op=op, name=f"{self.name}_{step}", inputs=tuple(inputs), outputs=(output,), attrs=attrs)


def _decode(value: object) -> object:
    return value.decode() if isinstance(value, bytes) else value


@dataclass
class Context:
    """Model-wide state for converters: constants, shapes, which values are read, taken names, and
    qdq.py's notes on the nodes it wrote (by output: real ranges of folded clamps, int8 pools
    onnxruntime computes in uint8)."""

    opset: int
    constants: dict[str, np.ndarray]
    shapes: dict[str, Shape]
    used: set[str]
    taken: set[str]
    output_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    uint8_pools: set[str] = field(default_factory=set)

    def shape(self, value: str) -> Shape:
        if value in self.constants:
            return tuple(self.constants[value].shape)
        if value not in self.shapes:
            raise NncgError(f"no static shape is known for value {shown(value)}; check the model with onnxruntime")
        return self.shapes[value]

    def const(self, value: str | None) -> np.ndarray | None:
        return self.constants.get(value) if value else None

    def constant_input(self, op: OnnxOp, index: int, role: str, hint: str = WEIGHT_HINT) -> np.ndarray:
        """Input `index` of `op`, which must be a compile-time constant."""
        value = self.const(op.input(index))
        if value is None:
            raise op.error(f"has its {role} {shown(op.input(index))} computed at runtime; {hint}")
        return value

    def is_used(self, value: str | None) -> bool:
        """Whether a remaining node reads `value` or the graph returns it."""
        return bool(value) and value in self.used

    def add_constant(self, base: str, array: np.ndarray) -> str:
        name = fresh_name(base, self.taken)
        self.taken.add(name)
        self.constants[name] = array
        return name

    def intermediate(self, op: OnnxOp, step: str, shape: Shape) -> str:
        """A fresh value of `shape` between the IR nodes that `op` becomes."""
        name = fresh_name(f"{op.node.output[0]}_{step}", self.taken)
        self.taken.add(name)
        self.shapes[name] = tuple(shape)
        return name

    def set_shape(self, op: OnnxOp, value: str, shape: Shape) -> None:
        """Record the shape NNCG computed, refusing if ONNX shape inference disagrees."""
        inferred = self.shapes.get(value)
        if inferred is not None and tuple(inferred) != tuple(shape):
            raise op.error(
                f"gets output shape {list(shape)} by the ONNX spec but {list(inferred)} by ONNX shape "
                "inference; please report this model"
            )
        self.shapes[value] = tuple(shape)
