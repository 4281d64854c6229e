"""A fuzz case end to end: the recipe and options drawn for (seed, index), the model built and
checked, the code-size limit for it, and the outcome of compiling and running it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import onnx
from onnx import numpy_helper

from .build import Invalid, build, value_shapes
from .generator import generate
from .options import Options, options_rng, random_options
from .recipe import Recipe
from .runner import Outcome, run_case, validate

BASE_BYTES = 32 << 10  # header, helpers, the function's frame
BYTES_PER_NODE = 16 << 10  # one layer's loop nests with vector blocks, tails and border splits
BYTES_PER_WEIGHT = 48  # a float printed as a C literal; Winograd and vector padding up to double the count
BYTES_PER_STATEMENT = 200  # an unrolled statement (vector intrinsics are the longest)
AUTO_STATEMENTS_PER_NODE = 8 * 64  # unroll auto: a few nests per layer, each unrolled to 64 statements


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
    seed: int, index: int, targets: list[str], sanitize_fraction: float, focus: tuple[str, ...] = ()
) -> Case | Outcome:
    """Case `index` of the run with `seed`: the same arguments give the same case."""
    recipe = generate([seed, index], focus=focus)
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
    weights = sum(numpy_helper.to_array(t).size for t in model.graph.initializer)
    fixed = BASE_BYTES + BYTES_PER_NODE * nodes + BYTES_PER_WEIGHT * weights
    if options.unroll == "none" and "unroll" not in options.layers:
        return fixed
    if options.code_budget is None:
        return None
    statements = options.code_budget
    if options.unroll == "auto" and "unroll" not in options.layers:
        statements = min(statements, AUTO_STATEMENTS_PER_NODE * nodes)
    return fixed + BYTES_PER_STATEMENT * statements
