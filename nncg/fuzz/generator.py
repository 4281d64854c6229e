"""Random valid CNN graphs in the spirit of NNSmith: a chain of proposed steps over the values built
so far (recent ones preferred, so residual and concat branches appear), each step built as soon as
it is proposed so every later choice sees real shapes."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .build import Invalid, ModelBuilder
from .draw import CHANNELS, SMALL_ELEMENTS, SPATIAL, Draw, broadcastable_to, numel
from .ops import OPS
from .ops_activation import ACTIVATIONS
from .recipe import Recipe, Shape, Step

OPSETS = (9, 11, 13, 17, 18, 19, 20, 21)
OPSET_WEIGHTS = (0.08, 0.22, 0.25, 0.1, 0.1, 0.1, 0.06, 0.09)
MAX_STEPS = 8
FOCUS_WEIGHT = 10
INPUT_ELEMENTS = 4096
# ops that take rank-0 values
SCALAR_OPS = ("Unary", "Binary", "Variadic", "Unsqueeze", "Reshape", "Identity", "Pow", *ACTIVATIONS)


def generate(seed: int | Sequence[int], max_steps: int = MAX_STEPS, focus: Sequence[str] = ()) -> Recipe:
    """The recipe of one random valid graph; the same seed gives the same recipe. Ops in `focus`
    (step kinds of nncg.fuzz.ops.OPS) are proposed FOCUS_WEIGHT times as often."""
    d = Draw(np.random.default_rng(seed), 0)
    d.opset = d.pick(OPSETS, OPSET_WEIGHTS)
    inputs = {"x": input_shape(d)}
    if d.chance(0.1):
        inputs["y"] = tuple(broadcastable_to(d, inputs["x"])) if d.chance(0.5) else inputs["x"]
    builder = ModelBuilder(d.opset, inputs, SMALL_ELEMENTS, generating=True)
    d.shapes = dict(inputs)
    steps: list[Step] = []
    wanted = d.int(1, max_steps)
    for _ in range(wanted * 12):
        if len(steps) == wanted:
            break
        step = _propose_step(d, len(steps), focus)
        if step is None:
            continue
        try:
            shapes = builder.add(step, len(steps))
        except Invalid:
            continue
        steps.append(step)
        d.shapes.update((v, s) for v, s in zip(step.outputs, shapes) if v not in builder.index_values)
    if not steps:
        steps.append(Step("Identity", ("x",), ("v0",), {}))
    return Recipe(d.opset, inputs, tuple(steps), _outputs(d, steps, builder.index_values))


def input_shape(d: Draw) -> Shape:
    rank = d.pick((4, 3, 5, 2), (0.7, 0.1, 0.07, 0.13))
    batch = 1 if d.chance(0.85) else 2
    if rank == 2:
        return (d.pick((1, 2, 3)), d.pick((1, 7, 16, 33, 64)))
    if rank == 3:
        return (batch, d.channels(), d.int(1, 24))
    if rank == 5:
        return (batch, d.pick((1, 2, 3, 5)), *(d.int(1, 5) for _ in range(3)))
    for _ in range(20):
        h = d.pick(SPATIAL)
        w = h if d.chance(0.5) else d.pick(SPATIAL)
        shape = (batch, d.pick(CHANNELS), h, w)
        if numel(shape) <= INPUT_ELEMENTS:
            return shape
    return (1, 3, 5, 5)


def _propose_step(d: Draw, index: int, focus: Sequence[str]) -> Step | None:
    names = list(d.shapes)
    x = d.pick(names[::-1], [0.5**i for i in range(len(names))])
    ops = [name for name, spec in OPS.items() if spec.min_opset <= d.opset <= spec.max_opset]
    op = d.pick(ops, [OPS[name].weight * (FOCUS_WEIGHT if name in focus else 1) for name in ops])
    if not d.shapes[x] and op not in SCALAR_OPS:
        return None
    proposal = OPS[op].propose(d, x)
    if proposal is None:
        return None
    outputs = tuple(f"v{index}" if proposal.outputs == 1 else f"v{index}_{k}" for k in range(proposal.outputs))
    return Step(op, tuple(proposal.inputs), outputs, proposal.params)


def _outputs(d: Draw, steps: list[Step], indices: set[str]) -> tuple[str, ...]:
    """The last value, and some of the values nothing reads (multiple outputs); ArgMax/ArgMin indices
    (`indices`, which no step reads) all, so none is computed for nothing."""
    read = {v for step in steps for v in step.inputs}
    last = steps[-1].outputs[0]
    leaves = [v for step in steps for v in step.outputs if v not in read and v != last]
    extra = [v for v in leaves if v in indices] + [v for v in leaves if v not in indices and d.chance(0.5)][:2]
    return (*extra, last) if d.chance(0.5) else (last, *extra)
