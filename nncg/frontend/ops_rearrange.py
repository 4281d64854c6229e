"""ONNX front end (ONNX -> graph IR), step 3: convert the ops that rearrange or repeat elements at
positions known at compile time, as the IR's data-movement nodes:

- DepthToSpace and SpaceToDepth are Reshape -> Transpose -> Reshape, as their ONNX definitions say;
  the first Reshape and the Transpose lower to views, so the op is one copy;
- Tile is a Tile node (a broadcast copy); Expand is one too, after a Reshape (a view) that gives its
  input the output's rank, its size-1 dims repeated;
- Gather at constant indices is a Slice when the indices step evenly, else a Gather node (one copy
  per run of evenly stepping indices), then a Reshape (a view) to the indices' shape.
"""

from __future__ import annotations

import numpy as np

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.ops_data import int_values
from nncg.frontend.ops_shape import axis_index
from nncg.ir.graph import GatherAttrs, Node, ReshapeAttrs, Shape, SliceAttrs, TileAttrs, TransposeAttrs
from nncg.safe_text import shown

BLOCK_MODES = ("DCR", "CRD")
# Why a parameter computed at runtime is refused, and how to make it constant.
CONSTANT_HINT = (
    "NNCG needs it constant: give it as an initializer, or fix the input shapes (--input-shape) so that it "
    "folds at compile time"
)

# --- DepthToSpace, SpaceToDepth ------------------------------------------------------------------


def convert_depth_to_space(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    n, c, h, w = _image_shape(op, ctx)
    b = _blocksize(op)
    if c % (b * b):
        raise op.error(f"has {c} channels, which do not make blocks of {b}x{b}: give it a multiple of {b * b}")
    depth = c // (b * b)
    if _mode(op) == "DCR":
        split, perm = (n, b, b, depth, h, w), (0, 3, 4, 1, 5, 2)
    else:
        split, perm = (n, depth, b, b, h, w), (0, 1, 4, 2, 5, 3)
    return _rearranged(op, ctx, split, perm, (n, depth, h * b, w * b))


def convert_space_to_depth(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    n, c, h, w = _image_shape(op, ctx)
    b = _blocksize(op)
    if h % b or w % b:
        raise op.error(f"has height {h} and width {w}, which blocks of {b}x{b} do not tile: give it multiples of {b}")
    perm = (0, 3, 5, 1, 2, 4) if _mode(op) == "DCR" else (0, 1, 3, 5, 2, 4)
    return _rearranged(op, ctx, (n, c, h // b, b, w // b, b), perm, (n, c * b * b, h // b, w // b))


def _rearranged(op: OnnxOp, ctx: Context, split: Shape, perm: Shape, out: Shape) -> tuple[Node, ...]:
    """x reshaped to `split`, transposed by `perm`, reshaped to `out`."""
    blocks = ctx.intermediate(op, "blocks", split)
    moved = ctx.intermediate(op, "moved", tuple(split[p] for p in perm))
    ctx.set_shape(op, op.node.output[0], out)
    return (
        op.ir_step("Reshape", "blocks", [op.input(0)], blocks, ReshapeAttrs(split)),
        op.ir_step("Transpose", "moved", [blocks], moved, TransposeAttrs(perm)),
        op.ir_node("Reshape", [moved], ReshapeAttrs(out)),
    )


def _image_shape(op: OnnxOp, ctx: Context) -> Shape:
    shape = ctx.shape(op.input(0))
    if len(shape) != 4:
        raise op.error(f"has an input of shape {list(shape)}; {op.type} needs a 4-D input [N, C, H, W]")
    return shape


def _blocksize(op: OnnxOp) -> int:
    blocksize = op.attr("blocksize")
    if blocksize is None or int(blocksize) < 1:
        raise op.error(f"has blocksize {blocksize}; {op.type} needs a blocksize of at least 1")
    return int(blocksize)


def _mode(op: OnnxOp) -> str:
    mode = op.attr("mode", "DCR")
    if mode not in BLOCK_MODES:
        raise op.error(f"has mode {shown(mode)}; NNCG supports {' and '.join(BLOCK_MODES)}")
    return mode


# --- Tile, Expand --------------------------------------------------------------------------------


def convert_tile(op: OnnxOp, ctx: Context) -> Node:
    shape = ctx.shape(op.input(0))
    repeats = int_values(op, ctx.constant_input(op, 1, "repeats", CONSTANT_HINT), "repeats").tolist()
    if len(repeats) != len(shape):
        raise op.error(f"has {len(repeats)} repeats for an input of rank {len(shape)}; it needs one per dim")
    if min(repeats, default=1) < 1:
        raise op.error(f"has repeats {repeats}; NNCG needs every repeat >= 1 (0 makes an empty tensor)")
    return _repeated(op, ctx, op.input(0), tuple(repeats))


def convert_expand(op: OnnxOp, ctx: Context) -> tuple[Node, ...]:
    shape = ctx.shape(op.input(0))
    target = int_values(op, ctx.constant_input(op, 1, "shape", CONSTANT_HINT), "shape").tolist()
    try:
        out = np.broadcast_shapes(shape, tuple(target))
    except ValueError:
        raise op.error(
            f"expands shape {list(shape)} by {target}, which do not broadcast (NumPy rules: aligned right, each "
            "pair of dims equal or one of them 1): fix the shape input"
        ) from None
    if min(out, default=1) < 1:
        raise op.error(f"expands {list(shape)} to the empty shape {list(out)}; NNCG cannot compile empty tensors")
    return broadcast_to(op, ctx, op.input(0), out)


def broadcast_to(op: OnnxOp, ctx: Context, value: str, out: Shape) -> tuple[Node, ...]:
    """IR nodes computing op's output, `value` NumPy-broadcast to the shape `out`: a Reshape (a view)
    to out's rank where value has fewer dims, then a Tile of its size-1 dims."""
    shape = ctx.shape(value)
    nodes = ()
    if len(shape) < len(out):
        shape = (1,) * (len(out) - len(shape)) + shape
        ranked = ctx.intermediate(op, "ranked", shape)
        nodes = (op.ir_step("Reshape", "ranked", [value], ranked, ReshapeAttrs(shape)),)
        value = ranked
    return (*nodes, _repeated(op, ctx, value, tuple(o // n for o, n in zip(out, shape))))


def _repeated(op: OnnxOp, ctx: Context, value: str, repeats: Shape) -> Node:
    """value repeated `repeats` times along each dim; without a repeat, a view of it."""
    out = tuple(n * r for n, r in zip(ctx.shape(value), repeats))
    ctx.set_shape(op, op.node.output[0], out)
    if all(r == 1 for r in repeats):
        return op.ir_node("Reshape", [value], ReshapeAttrs(out))
    return op.ir_node("Tile", [value], TileAttrs(repeats))


# --- Gather --------------------------------------------------------------------------------------


def convert_gather(op: OnnxOp, ctx: Context) -> Node | tuple[Node, Node]:
    shape = ctx.shape(op.input(0))
    axis = axis_index(op, int(op.attr("axis", 0)), len(shape))
    indices = ctx.constant_input(op, 1, "indices", CONSTANT_HINT)
    flat = int_values(op, indices, "indices").tolist()
    extent = shape[axis]
    outside = [i for i in flat if not -extent <= i < extent]
    if outside:
        raise op.error(
            f"has index {outside[0]} outside axis {axis} of size {extent} (valid: {-extent} to {extent - 1})"
        )
    if not flat:
        raise op.error("has no indices; NNCG cannot compile empty tensors")
    flat = [i % extent for i in flat]
    gathered = (*shape[:axis], len(flat), *shape[axis + 1 :])
    out = (*shape[:axis], *indices.shape, *shape[axis + 1 :])
    ctx.set_shape(op, op.node.output[0], out)
    kind, attrs = _gather_op(axis, flat, len(shape))
    if gathered == out:
        return op.ir_node(kind, [op.input(0)], attrs)
    value = ctx.intermediate(op, "gathered", gathered)
    return op.ir_step(kind, "gathered", [op.input(0)], value, attrs), op.ir_node("Reshape", [value], ReshapeAttrs(out))


def _gather_op(axis: int, indices: list[int], rank: int) -> tuple[str, SliceAttrs | GatherAttrs]:
    """A Slice where the indices step evenly (one index, or a constant step other than 0), else a Gather."""
    step = indices[1] - indices[0] if len(indices) > 1 else 1
    if step and all(b - a == step for a, b in zip(indices, indices[1:])):
        starts = tuple(indices[0] if d == axis else 0 for d in range(rank))
        return "Slice", SliceAttrs(starts, tuple(step if d == axis else 1 for d in range(rank)))
    return "Gather", GatherAttrs(axis, tuple(indices))
