"""A fuzz case end to end: the recipe and options drawn for (seed, index), the model built and
checked, the code-size limit for it, and the outcome of compiling and running it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import onnx
from onnx import helper, numpy_helper

from .build import Invalid, build, value_shapes
from .generator import generate
from .options import Options, options_rng, random_options
from .recipe import Recipe
from .runner import Outcome, run_case, validate

# Calibrated on 300 generated models: with --unroll none every layer but Winograd's stays under 4 KB
# (its transforms are straight-line code by design: ~170 KB whatever the image size); with auto
# under 10 KB more. The limits leave 2-5x headroom over what was measured.
BASE_BYTES = 16 << 10  # header, helpers, the function's frame
BYTES_PER_NODE = 8 << 10  # one layer's loop nests with vector blocks, tails and border splits
WINOGRAD_NODE_BYTES = 256 << 10
BYTES_PER_WEIGHT = 48  # a float printed as a C literal; Winograd and vector padding up to double the count
BYTES_PER_STATEMENT = 200  # an unrolled statement (~100 bytes measured; vector intrinsics are the longest)
NESTS_PER_LAYER = 4  # a layer's loop nests: border and interior splits, vector and tail blocks
AUTO_STATEMENTS_PER_NODE = NESTS_PER_LAYER * 64  # unroll auto: a few nests per layer, each unrolled to 64 statements


@dataclass(frozen=True)
class Case:
    seed: int
    index: int
    recipe: Recipe
    options: Options

    @property
    def name(self) -> str:
        return f"s{self.seed}-{self.index}"


def make_case(
    seed: int,
    index: int,
    targets: list[str],
    sanitize_fraction: float,
    focus: tuple[str, ...] = (),
    every_target: bool = False,
) -> Case | Outcome:
    """Case `index` of the run with `seed`: the same arguments give the same case. With `every_target`,
    cases come in runs of len(targets): one graph, each target in turn (its own random options)."""
    graph = index // len(targets) if every_target else index
    if every_target:
        targets = [targets[index % len(targets)]]
    recipe = generate([seed, graph], focus=focus)
    try:
        model = build(recipe)
    except Invalid as exc:
        return Outcome("invalid", f"generator: {exc}")
    elements = max(math.prod(s) for s in value_shapes(recipe).values())
    options = random_options(options_rng(seed, index), model, targets, sanitize_fraction, elements)
    return Case(seed, index, recipe, options)


def evaluate(recipe: Recipe, options: Options) -> Outcome:
    """Build the recipe's model, check it is valid, then run the case."""
    try:
        model = build(recipe)
        shapes = value_shapes(recipe)
    except Invalid as exc:
        return Outcome("invalid", f"generator: {exc}")
    problem = validate(model, {v: shapes[v] for v in recipe.outputs})
    if problem is not None:
        return Outcome("invalid", problem)
    return run_case(model, options, size_limit(model, options))


def size_limit(model: onnx.ModelProto, options: Options) -> int | None:
    """The most C the model should give with these options: code per layer, the weights, and what
    unrolling may add under the code budget. None when nothing caps unrolling (--code-budget 0)."""
    nodes = sum(1 for n in model.graph.node if n.op_type != "Constant")
    # ArgMax/ArgMin count twice: each register block carries the running extreme and its index
    nodes += sum(1 for n in model.graph.node if n.op_type in ("ArgMax", "ArgMin"))
    weights = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    forced = {name for name, on in options.layers.get("winograd", {}).items() if on}
    winograd = sum(1 for n in model.graph.node if n.name in forced or _winograd_shaped(n, weights))
    fixed = BASE_BYTES + BYTES_PER_NODE * nodes + WINOGRAD_NODE_BYTES * winograd
    fixed += BYTES_PER_WEIGHT * sum(w.size for w in weights.values())
    layer_budgets = options.layers.get("unroll", {})
    if options.unroll == "none" and not layer_budgets:
        return fixed
    if options.code_budget is None:
        return None
    statements = options.code_budget
    if options.unroll == "auto":
        statements = min(statements, AUTO_STATEMENTS_PER_NODE * nodes)
    # per-layer budgets cap each of the layer's nests and are exempt from the total (passes/unroll.py)
    statements += NESTS_PER_LAYER * sum(layer_budgets.values())
    return fixed + BYTES_PER_STATEMENT * statements


def _winograd_shaped(node: onnx.NodeProto, weights: dict) -> bool:
    """A Conv the winograd pass may take: 3x3, stride 1, no dilation, ungrouped, >= 8 input channels."""
    w = weights.get(node.input[1]) if node.op_type == "Conv" else None
    attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    return (
        w is not None
        and w.shape[2:] == (3, 3)
        and w.shape[1] >= 8
        and attrs.get("group", 1) == 1
        and all(v == 1 for key in ("strides", "dilations") for v in attrs.get(key, [1]))
    )
