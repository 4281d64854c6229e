"""Recipe -> ONNX model. Steps are built in order with every value's shape tracked, so a step that
no longer fits its inputs (after the shrinker changed a shape) raises Invalid instead of emitting a
bad graph."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .recipe import Recipe, Shape, Step

MAX_ELEMENTS = 1 << 16  # per value: bigger tensors only slow the builds down


class Invalid(Exception):
    """A step does not fit the shapes of its inputs (or the opset): the recipe is not a valid graph."""


class StepContext:
    """What an op's build function sees: its input shapes and parameters, and ways to add nodes,
    constants and extra graph inputs to the model."""

    def __init__(self, builder: ModelBuilder, step: Step, index: int):
        self.builder, self.step, self.index = builder, step, index
        self.params = step.params
        self.opset = builder.opset
        self.rng = np.random.default_rng(int(step.params.get("seed", 0)))
        self._temps = 0

    def shape(self, i: int = 0) -> Shape:
        return self.builder.shapes[self.step.inputs[i]]

    def input(self, i: int = 0) -> str:
        return self.step.inputs[i]

    def output(self, i: int = 0) -> str:
        return self.step.outputs[i]

    @property
    def name(self) -> str:
        return f"{self.step.op.lower()}_{self.step.outputs[0]}"

    def axis(self, axis: int, rank: int, allow_end: bool = False) -> int:
        """A possibly negative axis as an index; `allow_end`: rank itself is allowed too (Flatten)."""
        if not -rank <= axis < rank + allow_end:
            raise self.invalid(f"axis {axis} out of range for rank {rank}")
        if axis < 0 and self.opset < 11:
            raise self.invalid("negative axes need opset >= 11")
        return axis + rank if axis < 0 else axis

    def temp(self) -> str:
        """A fresh value name for an intermediate the step needs (e.g. the Sigmoid before a Div)."""
        self._temps += 1
        return f"{self.step.outputs[0]}_t{self._temps}"

    def node(self, op_type: str, inputs: Sequence[str], outputs: Sequence[str], **attrs: Any) -> None:
        suffix = f"_{len(self.builder.nodes)}" if self._temps else ""
        name = self.name + suffix
        attrs = {k: v for k, v in attrs.items() if v is not None}
        inputs = list(inputs)
        while inputs and not inputs[-1]:  # trailing optional inputs left out
            inputs.pop()
        self.builder.nodes.append(helper.make_node(op_type, list(inputs), list(outputs), name=name, **attrs))

    def const(self, array: np.ndarray | Sequence, dtype: Any = np.float32, role: str = "c") -> str:
        """An initializer holding `array`; returns its name."""
        name = f"{self.step.outputs[0]}_{role}{len(self.builder.initializers)}"
        self.builder.initializers.append(numpy_helper.from_array(np.asarray(array, dtype=dtype), name))
        return name

    def const_node(self, array: np.ndarray) -> str:
        """`array` as the output of a Constant node (NNCG folds it at import)."""
        name = self.temp()
        self.node("Constant", [], [name], value=numpy_helper.from_array(array, name + "_value"))
        return name

    def ints(self, values: Sequence[int], role: str = "i") -> str:
        return self.const(np.asarray(values, dtype=np.int64), np.int64, role)

    def weights(self, *shape: int, fan_in: int | None = None, scale: float = 1.0) -> np.ndarray:
        """Normal weights scaled by 1/sqrt(fan_in), so activations keep unit-ish magnitude."""
        fan = fan_in if fan_in is not None else (math.prod(shape[1:]) or 1)
        return (self.rng.standard_normal(shape) * scale / math.sqrt(max(fan, 1))).astype(np.float32)

    def weight_operand(self, array: np.ndarray, runtime: bool, role: str = "w") -> str:
        """The weight as an initializer, or (runtime) as an extra graph input of its shape."""
        if not runtime:
            return self.const(array, role=role)
        name = f"{self.step.outputs[0]}_{role}_in"
        self.builder.add_input(name, array.shape)
        return name

    def invalid(self, why: str) -> Invalid:
        return Invalid(f"step {self.index} ({self.step.op}): {why}")


class ModelBuilder:
    """Builds steps one at a time (the generator adds a step, sees its output shapes, goes on)."""

    def __init__(
        self, opset: int, inputs: dict[str, Shape], max_elements: int = MAX_ELEMENTS, generating: bool = False
    ):
        self.opset = opset
        self.generating = generating  # the generator's builder: also refuses steps reading a dead end
        self.max_elements = max_elements
        self.inputs: dict[str, Shape] = {}
        self.shapes: dict[str, Shape] = {}
        self.index_values: set[str] = set()  # ArgMax/ArgMin outputs: int64, read by no step
        # values the generator reads no further: onnx's shape inference gets their shape wrong, or
        # they hold -FLT_MAX (a MaxPool window wholly in the padding: squared or summed it overflows)
        self.dead_ends: set[str] = set()
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        for name, shape in inputs.items():
            self.add_input(name, shape)

    def add_input(self, name: str, shape: Sequence[int]) -> None:
        self.inputs[name] = tuple(int(d) for d in shape)
        self.shapes[name] = self.inputs[name]

    def add(self, step: Step, index: int) -> list[Shape]:
        """Builds one step; on Invalid the builder is left unchanged."""
        from .ops import OPS  # the op table imports this module

        spec = OPS.get(step.op)
        if spec is None:
            raise Invalid(f"unknown op {step.op}")
        if not spec.min_opset <= self.opset <= spec.max_opset:
            raise Invalid(f"{step.op} is not in opset {self.opset}")
        missing = [v for v in step.inputs if v not in self.shapes]
        if missing:
            raise Invalid(f"step {index} ({step.op}) reads undefined {missing}")
        indices = [v for v in step.inputs if v in self.index_values]
        if indices:
            raise Invalid(f"step {index} ({step.op}) reads int64 indices {indices}")
        dead_ends = [v for v in step.inputs if v in self.dead_ends]
        if dead_ends and self.generating:
            raise Invalid(f"step {index} ({step.op}) reads {dead_ends}, which the generator leaves unread")
        saved = (len(self.nodes), len(self.initializers), dict(self.inputs), dict(self.shapes))
        sets = (set(self.index_values), set(self.dead_ends))
        try:
            shapes = [tuple(int(d) for d in s) for s in spec.build(StepContext(self, step, index))]
            if len(shapes) != len(step.outputs):
                raise Invalid(
                    f"step {index} ({step.op}) defines {len(shapes)} values, recipe names {len(step.outputs)}"
                )
            for shape in shapes:
                if min(shape, default=1) < 1 or math.prod(shape) > self.max_elements:
                    raise Invalid(f"step {index} ({step.op}) gives shape {list(shape)}")
        except Invalid:
            del self.nodes[saved[0] :], self.initializers[saved[1] :]
            self.inputs, self.shapes = saved[2], saved[3]
            self.index_values, self.dead_ends = sets
            raise
        self.shapes.update(zip(step.outputs, shapes))
        return shapes

    def model(self, outputs: Sequence[str], name: str = "fuzz") -> onnx.ModelProto:
        missing = [v for v in outputs if v not in self.shapes]
        if missing or not outputs:
            raise Invalid(f"graph outputs {missing or 'none'} are not defined")
        graph = helper.make_graph(
            self.nodes,
            name,
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in self.inputs.items()],
            [helper.make_tensor_value_info(v, self._elem_type(v), self.shapes[v]) for v in outputs],
            self.initializers,
        )
        opsets = [helper.make_opsetid("", self.opset)]
        model = helper.make_model(graph, opset_imports=opsets, producer_name="nncg.fuzz")
        model.ir_version = helper.find_min_ir_version_for(opsets)
        return model

    def _elem_type(self, value: str) -> int:
        return TensorProto.INT64 if value in self.index_values else TensorProto.FLOAT


def build(recipe: Recipe) -> onnx.ModelProto:
    """The ONNX model of a recipe; raises Invalid when a step does not fit."""
    builder = ModelBuilder(recipe.opset, recipe.inputs)
    for index, step in enumerate(recipe.steps):
        builder.add(step, index)
    return builder.model(recipe.outputs)


def value_shapes(recipe: Recipe) -> dict[str, Shape]:
    """The shape of every value of a recipe (graph inputs included)."""
    builder = ModelBuilder(recipe.opset, recipe.inputs)
    for index, step in enumerate(recipe.steps):
        builder.add(step, index)
    return dict(builder.shapes)
