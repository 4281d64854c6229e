"""A quantised model's outputs against onnxruntime's in quantisation steps, the one rule by which int8
results are judged (`--verify`, `--per-layer`, the int8 benchmark, the int8 tests): one step of a tensor
is the scale of the DequantizeLinear that computes it (per channel where that scale is), or 1 for the
integers a QuantizeLinear or QLinear operator writes, so "within one step" reads the same for every
tensor. A quantised model passes when every such tensor is within one step of onnxruntime's."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import onnx

from .errors import NncgError
from .frontend.constants import constant_arrays
from .frontend.io_quantization import MOVING_OPS

# ops whose first output is quantised integers (onnxruntime's contrib QLinear* included)
_QUANTIZING = ("QuantizeLinear", "QLinear")
ALLOWED_STEPS = 1
# A one-step difference of two dequantised float32 values reads 1 up to the rounding of the products
# (q - zero_point) * scale: the pass rule counts steps to this many decimals.
_STEP_DECIMALS = 3


def within_allowed_steps(max_steps: float) -> bool:
    """The pass rule for a quantised tensor: at most one step from onnxruntime's."""
    return round(max_steps, _STEP_DECIMALS) <= ALLOWED_STEPS


@dataclass(frozen=True)
class Step:
    """One tensor's quantisation step: a scalar, or per channel along `axis`."""

    scale: np.ndarray
    axis: int = 1

    def per_element(self, ndim: int) -> np.ndarray:
        """The step broadcastable against a tensor of rank `ndim`."""
        if self.scale.ndim == 0:
            return self.scale.astype(np.float64)
        axis = self.axis % ndim
        return self.scale.astype(np.float64).reshape((-1,) + (1,) * (ndim - 1 - axis))


@dataclass(frozen=True)
class Comparison:
    """The largest difference in quantisation steps and the share of bit-identical elements."""

    max_steps: float
    identical: float  # 0 to 1
    elements: int

    def __str__(self) -> str:
        return f"max {self.max_steps:g} steps, {100 * self.identical:.2f} % of {self.elements} identical"


def tensor_steps(model: onnx.ModelProto) -> dict[str, Step]:
    """The quantisation step of every tensor that has one (see the module's docstring)."""
    consts = constant_arrays(model.graph)
    steps: dict[str, Step] = {}
    for node in model.graph.node:
        step = _step_of(node, consts, steps)
        if step is not None and node.output and node.output[0]:
            steps[node.output[0]] = step
    return steps


def _step_of(node: onnx.NodeProto, consts: dict[str, np.ndarray], steps: dict[str, Step]) -> Step | None:
    if node.op_type.startswith(_QUANTIZING):
        return Step(np.array(1.0))
    if node.op_type == "DequantizeLinear" and len(node.input) > 1 and node.input[1] in consts:
        scale = consts[node.input[1]]
        axis = next((a.i for a in node.attribute if a.name == "axis"), 1)
        return Step(scale, axis) if scale.ndim <= 1 else None  # blocked scales (opset 21) are not per channel
    if node.op_type in MOVING_OPS and node.input and node.input[0] in steps:  # the input's per-tensor step
        step = steps[node.input[0]]
        return step if step.scale.ndim == 0 else None  # a per-channel axis may move
    return None


def steps_apart(step: Step, ours: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """|ours - reference| per element, in steps."""
    ref = np.asarray(reference).reshape(ours.shape)
    return np.abs(ours.astype(np.float64) - ref.astype(np.float64)) / step.per_element(ours.ndim)


def compare_steps(
    model: onnx.ModelProto, runs: Iterable[tuple[Sequence[np.ndarray], Sequence[np.ndarray]]]
) -> Comparison:
    """`runs`: per input, (NNCG's outputs, onnxruntime's outputs), both in the graph's output order."""
    steps = tensor_steps(model)
    names = [v.name for v in model.graph.output]
    missing = [name for name in names if name not in steps]
    if missing:
        raise NncgError(f"output {missing[0]!r} has no quantisation step (no DequantizeLinear or QuantizeLinear)")
    most, same, total = 0.0, 0, 0
    for ours, references in runs:
        for name, mine, ref in zip(names, ours, references, strict=True):
            apart = steps_apart(steps[name], mine, ref)
            most = max(most, float(apart.max()) if apart.size else 0.0)
            same += int((mine == np.asarray(ref).reshape(mine.shape)).sum())
            total += mine.size
    return Comparison(most, same / total, total)
