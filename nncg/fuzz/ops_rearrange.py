"""Ops for the generator that rearrange or repeat elements at constant positions: DepthToSpace,
SpaceToDepth, Tile, Expand, Gather (constant indices) and Where (constant condition)."""

from __future__ import annotations

import numpy as np

from .build import StepContext
from .draw import SMALL_ELEMENTS, Draw, Proposal, broadcast_shape, numel

# --- DepthToSpace, SpaceToDepth -------------------------------------------------------------------


def build_depth_to_space(c: StepContext) -> list[tuple[int, ...]]:
    n, ch, h, w = _image(c)
    b = int(c.params["blocksize"])
    if ch % (b * b):
        raise c.invalid(f"{ch} channels do not make {b}x{b} blocks")
    mode = c.params.get("mode") if c.opset >= 11 else None
    c.node("DepthToSpace", [c.input()], [c.output()], blocksize=b, mode=mode)
    return [(n, ch // (b * b), h * b, w * b)]


def build_space_to_depth(c: StepContext) -> list[tuple[int, ...]]:
    n, ch, h, w = _image(c)
    b = int(c.params["blocksize"])
    if h % b or w % b:
        raise c.invalid(f"{h}x{w} is not tiled by {b}x{b} blocks")
    mode = c.params.get("mode") if c.opset >= 28 else None  # SpaceToDepth has modes from opset 28
    c.node("SpaceToDepth", [c.input()], [c.output()], blocksize=b, mode=mode)
    return [(n, ch * b * b, h // b, w // b)]


def _image(c: StepContext) -> tuple[int, ...]:
    if len(c.shape()) != 4:
        raise c.invalid(f"{c.step.op} needs a 4-D input")
    return c.shape()


def propose_depth_to_space(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    sizes = [b for b in (2, 3) if len(shape) == 4 and shape[1] % (b * b) == 0]
    return _block_proposal(d, x, sizes)


def propose_space_to_depth(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    sizes = [b for b in (2, 3) if len(shape) == 4 and shape[2] % b == 0 and shape[3] % b == 0]
    return _block_proposal(d, x, sizes)


def _block_proposal(d: Draw, x: str, sizes: list[int]) -> Proposal | None:
    if not sizes:
        return None
    return Proposal([x], {"blocksize": d.pick(sizes), "mode": d.pick(("DCR", "CRD"))})


# --- Tile, Expand ---------------------------------------------------------------------------------


def build_tile(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    repeats = [int(r) for r in c.params["repeats"]]
    if len(repeats) != len(x):
        raise c.invalid(f"{len(repeats)} repeats for rank {len(x)}")
    c.node("Tile", [c.input(), c.ints(repeats, "repeats")], [c.output()])
    return [tuple(n * r for n, r in zip(x, repeats))]


def propose_tile(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    repeats = [d.pick((1, 1, 2, 3)) for _ in shape]
    if numel(shape) * numel(repeats) > SMALL_ELEMENTS:
        return None
    return Proposal([x], {"repeats": repeats})


def build_expand(c: StepContext) -> list[tuple[int, ...]]:
    target = [int(n) for n in c.params["shape"]]
    out = broadcast_shape(c.shape(), target)
    if out is None:
        raise c.invalid(f"{list(c.shape())} does not broadcast with {target}")
    c.node("Expand", [c.input(), c.ints(target, "shape")], [c.output()])
    return [out]


def propose_expand(d: Draw, x: str) -> Proposal | None:
    """Size-1 dims grow, others stay (or are given as 1); now and then a leading dim is added."""
    shape = d.shapes[x]
    target = [d.pick((2, 3, 5)) if n == 1 and d.chance(0.7) else n if d.chance(0.7) else 1 for n in shape]
    if d.chance(0.2):
        target.insert(0, d.pick((1, 2)))
    if numel(broadcast_shape(shape, target) or shape) > SMALL_ELEMENTS:
        return None
    return Proposal([x], {"shape": target})


# --- Gather, Where --------------------------------------------------------------------------------


def build_gather(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    axis = c.axis(int(c.params.get("axis", 0)), len(x))
    indices = np.asarray(c.params["indices"], dtype=np.int64)
    if indices.size == 0 or indices.min() < -x[axis] or indices.max() >= x[axis]:
        raise c.invalid(f"indices {indices.tolist()} outside axis {axis} of size {x[axis]}")
    if indices.min() < 0 and c.opset < 11:
        raise c.invalid("negative indices need opset >= 11")
    c.node(
        "Gather", [c.input(), c.const(indices, np.int64, "indices")], [c.output()], axis=int(c.params.get("axis", 0))
    )
    return [(*x[:axis], *indices.shape, *x[axis + 1 :])]


def propose_gather(d: Draw, x: str) -> Proposal | None:
    """Indices of any kind: one (a scalar), a run, shuffled, repeated, negative; 1-D or 2-D."""
    shape = d.shapes[x]
    if not shape:
        return None
    axis = d.int(0, len(shape) - 1)
    n = shape[axis]
    count = d.pick((1, 2, 3, 4))
    indices = [int(i) for i in d.rng.integers(0, n, size=count)]
    if d.opset >= 11 and d.chance(0.3):
        indices = [i - n if d.chance(0.5) else i for i in indices]
    form = d.pick(("scalar", "vector", "matrix")) if count == 1 else d.pick(("vector", "matrix"))
    values = indices[0] if form == "scalar" else [indices] if form == "matrix" else indices
    return Proposal([x], {"axis": d.axis(axis, len(shape)), "indices": values})


def build_where(c: StepContext) -> list[tuple[int, ...]]:
    p = c.params
    condition = np.asarray(p["condition"], dtype=bool)
    x = c.shape()
    if len(c.step.inputs) > 1:
        other, other_shape = c.input(1), c.shape(1)
    else:
        other_shape = tuple(int(n) for n in p["const_shape"])
        other = c.const(c.rng.standard_normal(other_shape).astype(np.float32), role="k")
    out = broadcast_shape(broadcast_shape(x, other_shape) or (), condition.shape)
    if out is None or broadcast_shape(x, other_shape) is None:
        raise c.invalid(f"{list(condition.shape)}, {list(x)} and {list(other_shape)} do not broadcast")
    operands = [c.input(), other][:: -1 if p.get("swap") else 1]
    c.node("Where", [c.const(condition, bool, "cond"), *operands], [c.output()])
    return [out]


def propose_where(d: Draw, x: str) -> Proposal | None:
    """A random mask of x's trailing dims (some of them 1); the other side a value of x's shape or a
    constant scalar."""
    shape = d.shapes[x]
    mask_shape = [n if d.chance(0.6) else 1 for n in shape[len(shape) - d.int(0, len(shape)) :]]
    params: dict = {"condition": (d.rng.random(mask_shape) < 0.5).tolist(), "swap": d.chance(0.5), "seed": d.seed()}
    y = d.partner(x, lambda a, b: a == b) if d.chance(0.5) else None
    if y is None:
        params["const_shape"] = []
        return Proposal([x], params)
    return Proposal([x, y], params)
