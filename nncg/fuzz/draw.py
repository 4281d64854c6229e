"""Random choices for the generator's op proposers: a seeded numpy Generator, the opset and the
values built so far (name -> shape), which multi-input ops pick partners from."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from .recipe import Shape

T = TypeVar("T")

CHANNELS = (1, 3, 5, 7, 16, 17, 21, 33)  # odd counts stress vector tails, 16 fills vectors exactly
SPATIAL = (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 13, 16)
SMALL_ELEMENTS = 1 << 14  # the generator keeps every value below this (the builder's hard cap is higher)


@dataclass
class Proposal:
    """An op's choice: the values it reads, its parameters, how many values it defines."""

    inputs: list[str]
    params: dict[str, Any]
    outputs: int = 1


@dataclass
class Draw:
    rng: np.random.Generator
    opset: int
    shapes: dict[str, Shape] = field(default_factory=dict)

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def pick(self, items: Sequence[T], weights: Sequence[float] | None = None) -> T:
        if weights is None:
            return items[int(self.rng.integers(len(items)))]
        w = np.asarray(weights, dtype=float)
        return items[int(self.rng.choice(len(items), p=w / w.sum()))]

    def int(self, low: int, high: int) -> int:
        """Uniform in [low, high] (both included)."""
        return int(self.rng.integers(low, high + 1))

    def axis(self, axis: int, rank: int) -> int:
        """The axis, or now and then the same axis counted from the end (negative axes: opset >= 11)."""
        return axis - rank if self.opset >= 11 and self.chance(0.3) else axis

    def seed(self) -> int:
        return int(self.rng.integers(1 << 31))

    def channels(self, cap: int = 64) -> int:
        return self.pick([c for c in CHANNELS if c <= cap] or [1])

    def partner(self, x: str, fits: Callable[[Shape, Shape], bool]) -> str | None:
        """Another value (or x itself, rarely) whose shape fits x's shape, recent values first."""
        names = [n for n in self.shapes if n != x and fits(self.shapes[x], self.shapes[n])]
        if not names:
            return x if fits(self.shapes[x], self.shapes[x]) and self.chance(0.3) else None
        return self.pick(names[::-1], [0.6**i for i in range(len(names))])


def broadcast_shape(a: Shape, b: Shape) -> Shape | None:
    """NumPy broadcasting of two shapes, or None when they do not broadcast."""
    try:
        return tuple(np.broadcast_shapes(tuple(a), tuple(b)))
    except ValueError:
        return None


def broadcastable_to(d: Draw, shape: Shape) -> list[int]:
    """A random shape that broadcasts to `shape` without growing it: trailing dims, each kept or 1."""
    keep = d.int(0, len(shape))
    tail = shape[len(shape) - keep :]
    out = [n if d.chance(0.5) else 1 for n in tail]
    return out if out else [1]


def numel(shape: Sequence[int]) -> int:
    return math.prod(shape)
