"""A quantised model's outputs against onnxruntime's in quantisation steps: one step of a graph output is
the scale of the DequantizeLinear that computes it, so "within one step" reads the same for every output.
The int8 benchmark (benchmarks/int8_suite.py) and the int8 tests report these figures."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import onnx
from onnx import numpy_helper


@dataclass(frozen=True)
class Comparison:
    """The largest difference in quantisation steps and the share of bit-identical elements."""

    max_steps: float
    identical: float  # 0 to 1
    elements: int

    def __str__(self) -> str:
        return f"max {self.max_steps:g} steps, {100 * self.identical:.2f} % of {self.elements} identical"


def output_scales(model: onnx.ModelProto) -> dict[str, float]:
    """The scale of the DequantizeLinear that computes each graph output."""
    consts = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    outputs = {v.name for v in model.graph.output}
    return {
        n.output[0]: float(consts[n.input[1]])
        for n in model.graph.node
        if n.op_type == "DequantizeLinear" and n.output[0] in outputs
    }


def compare_steps(
    model: onnx.ModelProto, runs: Iterable[tuple[Sequence[np.ndarray], Sequence[np.ndarray]]]
) -> Comparison:
    """`runs`: per input, (NNCG's outputs, onnxruntime's outputs), both in the graph's output order."""
    scales = output_scales(model)
    names = [v.name for v in model.graph.output]
    steps, same, total = 0.0, 0, 0
    for ours, references in runs:
        for name, mine, ref in zip(names, ours, references, strict=True):
            ref = np.asarray(ref).reshape(mine.shape)
            diff = np.abs(mine.astype(np.float64) - ref.astype(np.float64)) / scales[name]
            steps = max(steps, float(diff.max()))
            same += int((mine == ref).sum())
            total += mine.size
    return Comparison(steps, same / total, total)
