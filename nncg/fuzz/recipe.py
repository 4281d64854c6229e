"""A fuzz case's graph as data: input shapes and a list of steps (an op kind, the values it reads,
its parameters). The builder turns a recipe into ONNX; the shrinker edits recipes, not ONNX."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

Shape = tuple[int, ...]


@dataclass(frozen=True)
class Step:
    """One layer of the recipe: `op` names a generator op (nncg.fuzz.ops.OPS), `inputs` are value
    names, `outputs` the value names it defines, `params` its JSON-able parameters."""

    op: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Recipe:
    """Graph inputs (name -> shape), steps in topological order, the values returned."""

    opset: int
    inputs: dict[str, Shape]
    steps: tuple[Step, ...]
    outputs: tuple[str, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "opset": self.opset,
            "inputs": {name: list(shape) for name, shape in self.inputs.items()},
            "steps": [
                asdict(step) | {"inputs": list(step.inputs), "outputs": list(step.outputs)} for step in self.steps
            ],
            "outputs": list(self.outputs),
        }

    @staticmethod
    def from_json(data: dict[str, Any]) -> Recipe:
        steps = tuple(Step(s["op"], tuple(s["inputs"]), tuple(s["outputs"]), dict(s["params"])) for s in data["steps"])
        inputs = {name: tuple(shape) for name, shape in data["inputs"].items()}
        return Recipe(int(data["opset"]), inputs, steps, tuple(data["outputs"]))

    def key(self) -> str:
        """A canonical text of the recipe (for caching shrink evaluations)."""
        return json.dumps(self.to_json(), sort_keys=True)

    def renamed(self, old: str, new: str) -> Recipe:
        """Every read of value `old` (by steps and as a graph output) reads `new` instead."""
        steps = tuple(replace(s, inputs=tuple(new if v == old else v for v in s.inputs)) for s in self.steps)
        outputs = tuple(dict.fromkeys(new if v == old else v for v in self.outputs))
        return replace(self, steps=steps, outputs=outputs)

    def without_dead_steps(self) -> Recipe:
        """Drops steps none of whose outputs is read (by a later step or as a graph output)."""
        live = set(self.outputs)
        kept = []
        for step in reversed(self.steps):
            if live.intersection(step.outputs):
                kept.append(step)
                live.update(step.inputs)
        inputs = {name: shape for name, shape in self.inputs.items() if name in live}
        return replace(self, steps=tuple(reversed(kept)), inputs=inputs or self.inputs)
