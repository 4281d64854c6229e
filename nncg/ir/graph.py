"""Graph IR: the ONNX model after import, with static shapes, folded constants and typed attributes.

Stage 1 of the pipeline (ONNX -> graph IR -> graph passes -> loop-nest IR -> loop passes -> backend).
Every value has a static shape; every constant is a float32 numpy array; every node carries one
frozen attribute record with ONNX defaults already filled in, so passes and lowerings never look
at raw ONNX attributes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

Shape = tuple[int, ...]


@dataclass(frozen=True)
class Activation:
    """An activation that a producer applies at its store: relu, leaky_relu with slope alpha, or
    clip to [low, high] (ReLU6 is clip(0, 6))."""

    kind: str  # "relu" | "leaky_relu" | "clip"
    alpha: float = 0.0
    low: float = float("-inf")
    high: float = float("inf")

    def __str__(self) -> str:
        if self.kind == "clip":
            return f"clip({self.low:g}, {self.high:g})"
        return "relu" if self.kind == "relu" else f"leaky_relu(alpha={self.alpha:g})"


@dataclass(frozen=True)
class ConvAttrs:
    """Conv over len(kernel) spatial dims; pads already resolved from auto_pad, begin and end apart."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    group: int = 1
    activation: Activation | None = None


@dataclass(frozen=True)
class PoolAttrs:
    """MaxPool and AveragePool (also their Global forms); the output shape (ceil_mode included) is
    recorded in Graph.shapes. count_include_pad: AveragePool divides by the padded window size."""

    kernel: Shape
    strides: Shape
    dilations: Shape
    pads_begin: Shape
    pads_end: Shape
    ceil_mode: bool = False
    count_include_pad: bool = False


@dataclass(frozen=True)
class BatchNormAttrs:
    """Inference BatchNormalization: inputs are x, scale, bias, mean, var (the last four constant)."""

    epsilon: float = 1e-5


@dataclass(frozen=True)
class ScaleShiftAttrs:
    """y = x * scale[c] + shift[c] over axis 1 (a BatchNorm that had no producer to fold into)."""

    activation: Activation | None = None


@dataclass(frozen=True)
class DenseAttrs:
    """y[m, n] = sum_k x[m, k] * w[k, n] + b[n]; inputs x, w (constant [K, N]) and optionally b ([N]).

    x may have rank > 2: all leading dims are rows. trans_x reads x as [K, M] (Gemm transA=1).
    """

    trans_x: bool = False
    activation: Activation | None = None


@dataclass(frozen=True)
class SoftmaxAttrs:
    """Softmax along `axis`; coerce_2d is the opset < 13 meaning (flatten to 2-D at axis)."""

    axis: int
    coerce_2d: bool = False


@dataclass(frozen=True)
class ReshapeAttrs:
    """Reshape, Flatten, Squeeze, Unsqueeze: the row-major element order is kept, shape changes."""

    shape: Shape


# Canonical op names of the graph IR and their attribute record type (None: no attributes).
OPS: dict[str, type | None] = {
    "Conv": ConvAttrs,
    "MaxPool": PoolAttrs,
    "AveragePool": PoolAttrs,
    "Relu": Activation,
    "Clip": Activation,
    "LeakyRelu": Activation,
    "BatchNormalization": BatchNormAttrs,
    "ScaleShift": ScaleShiftAttrs,
    "Dense": DenseAttrs,
    "Softmax": SoftmaxAttrs,
    "Reshape": ReshapeAttrs,
    "Identity": None,
    "Add": None,
    "Sub": None,
    "Mul": None,
    "Div": None,
}


@dataclass(frozen=True)
class Value:
    """A graph input or output: a float32 tensor with a static shape."""

    name: str
    shape: Shape


@dataclass(frozen=True)
class Node:
    op: str
    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    attrs: object = None


@dataclass(frozen=True)
class Graph:
    """Nodes in topological order. `shapes` holds the shape of every non-constant value."""

    name: str
    inputs: tuple[Value, ...]
    outputs: tuple[Value, ...]
    nodes: tuple[Node, ...]
    constants: dict[str, np.ndarray] = field(default_factory=dict, compare=False)
    shapes: dict[str, Shape] = field(default_factory=dict)

    def is_constant(self, name: str) -> bool:
        return name in self.constants

    def shape(self, name: str) -> Shape:
        if name in self.constants:
            return tuple(self.constants[name].shape)
        return self.shapes[name]

    def producer(self, name: str) -> Node | None:
        for node in self.nodes:
            if name in node.outputs:
                return node
        return None

    def consumers(self, name: str) -> list[Node]:
        return [node for node in self.nodes if name in node.inputs]

    def is_graph_output(self, name: str) -> bool:
        return any(v.name == name for v in self.outputs)

    def with_nodes(self, nodes, constants: dict[str, np.ndarray] | None = None) -> Graph:
        """A copy with new nodes (and constants), dropping constants and shapes no node uses."""
        nodes = tuple(nodes)
        constants = dict(self.constants if constants is None else constants)
        used = {name for node in nodes for name in (*node.inputs, *node.outputs)}
        used |= {v.name for v in (*self.inputs, *self.outputs)}
        return replace(
            self,
            nodes=nodes,
            constants={k: v for k, v in constants.items() if k in used},
            shapes={k: v for k, v in self.shapes.items() if k in used},
        )
