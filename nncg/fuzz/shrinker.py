"""Delta debugging of a failing case: drop outputs, steps and options, cut the graph, shrink input
shapes and parameters, keeping each change that still fails the same way, until none does."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

from .build import Invalid, value_shapes
from .options import Options
from .recipe import Recipe

Candidate = tuple[Recipe, Options]
MAX_EVALUATIONS = 150
MAX_SECONDS = 600


@dataclass(frozen=True)
class Shrunk:
    recipe: Recipe
    options: Options
    evaluations: int
    seconds: float


def size(recipe: Recipe, options: Options) -> tuple[int, int, int, int]:
    """What the shrinker minimises, most important first: steps, input elements, parameters, options."""
    inputs = sum(math.prod(s) for s in recipe.inputs.values())
    return (
        len(recipe.steps) + len(recipe.outputs),
        inputs,
        sum(_param_size(s.params) for s in recipe.steps),
        len(options.simpler()),
    )


def _param_size(params: dict[str, Any]) -> int:
    total = 0
    for key, value in params.items():
        if key == "seed":
            continue
        values = value if isinstance(value, list) else [value]
        total += 1 + sum(min(abs(v), 64) for v in values if isinstance(v, int | bool))
    return total


def shrink(
    recipe: Recipe,
    options: Options,
    fails: Callable[[Recipe, Options], bool],
    max_evaluations: int = MAX_EVALUATIONS,
    max_seconds: float = MAX_SECONDS,
) -> Shrunk:
    """The smallest (recipe, options) found for which `fails` still holds: greedy, restarting from the
    most drastic candidates after every accepted change."""
    start = time.monotonic()
    best = (recipe, options)
    seen = {_key(*best)}
    evaluations = 0
    improved = True
    while improved and evaluations < max_evaluations and time.monotonic() - start < max_seconds:
        improved = False
        for candidate in candidates(*best):
            key = _key(*candidate)
            if key in seen or size(*candidate) >= size(*best):
                continue
            seen.add(key)
            evaluations += 1
            if fails(*candidate):
                best, improved = candidate, True
                break
            if evaluations >= max_evaluations or time.monotonic() - start >= max_seconds:
                break
    return Shrunk(best[0], best[1], evaluations, time.monotonic() - start)


def _key(recipe: Recipe, options: Options) -> str:
    return recipe.key() + repr(sorted(options.to_json().items(), key=str))


def candidates(recipe: Recipe, options: Options) -> Iterator[Candidate]:
    """Smaller variants of the case, most drastic first."""
    if not options.default_layers or options != Options(target=options.target):
        yield recipe, Options(target=options.target)
    for r in graph_candidates(recipe):
        yield r, options
    for o in options.simpler():
        yield recipe, o


def graph_candidates(recipe: Recipe) -> Iterator[Recipe]:
    if len(recipe.outputs) > 1:
        for out in recipe.outputs:
            yield replace(recipe, outputs=(out,)).without_dead_steps()
    trimmed = recipe.without_dead_steps()
    if trimmed != recipe:
        yield trimmed
    for index in reversed(range(len(recipe.steps))):
        yield from _without_step(recipe, index)
    yield from _cuts(recipe)
    yield from _smaller_inputs(recipe)
    for index, step in enumerate(recipe.steps):
        for params in simpler_params(step.params):
            steps = list(recipe.steps)
            steps[index] = replace(step, params=params)
            yield replace(recipe, steps=tuple(steps))


def _without_step(recipe: Recipe, index: int) -> Iterator[Recipe]:
    """The step removed, its readers reading one of its inputs instead."""
    step = recipe.steps[index]
    rest = replace(recipe, steps=recipe.steps[:index] + recipe.steps[index + 1 :])
    for source in dict.fromkeys(step.inputs):
        out = rest
        for value in step.outputs:
            out = out.renamed(value, source)
        yield out.without_dead_steps()


def _cuts(recipe: Recipe) -> Iterator[Recipe]:
    """A step's output made a graph input of its shape, dropping whatever only fed it."""
    try:
        shapes = value_shapes(recipe)
    except Invalid:
        return
    for step in recipe.steps:
        for value in step.outputs:
            name = f"in_{value}"
            cut = replace(recipe.renamed(value, name), inputs={**recipe.inputs, name: shapes[value]})
            trimmed = cut.without_dead_steps()
            if len(trimmed.steps) < len(recipe.steps):
                yield trimmed


def _smaller_inputs(recipe: Recipe) -> Iterator[Recipe]:
    for name, shape in recipe.inputs.items():
        for axis, n in enumerate(shape):
            for smaller in dict.fromkeys((1, (n + 1) // 2, n - 1)):
                if 1 <= smaller < n:
                    new = shape[:axis] + (smaller,) + shape[axis + 1 :]
                    yield replace(recipe, inputs={**recipe.inputs, name: new})


def simpler_params(params: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """Each parameter left at its default (removed), or made smaller."""
    for key, value in params.items():
        if key == "seed":
            continue
        yield {k: v for k, v in params.items() if k != key}
        for smaller in _smaller_values(value):
            yield params | {key: smaller}


def _smaller_values(value: Any) -> list[Any]:
    if isinstance(value, bool):
        return [False] if value else []
    if isinstance(value, int):
        return [v for v in dict.fromkeys((1, value // 2, 0)) if abs(v) < abs(value)]
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        out = [[1] * len(value), [0] * len(value), [v // 2 for v in value]]
        return [v for v in out if v != value]
    return []
