"""ONNX front end (ONNX -> graph IR), step 3: convert data-movement ops. Reshape, Flatten, Squeeze
and Unsqueeze become one IR Reshape with a static shape; Dropout and Identity become Identity.
"""

from __future__ import annotations

import math

import numpy as np

from nncg.errors import NncgError
from nncg.frontend.context import SHAPE_HINT, Context, OnnxOp
from nncg.ir.graph import Node, ReshapeAttrs, Shape
from nncg.safe_text import shown


def convert_identity(op: OnnxOp, ctx: Context) -> Node:
    return op.ir_node("Identity", [op.input(0)])


def convert_dropout(op: OnnxOp, ctx: Context) -> Node:
    """Inference Dropout is the identity; its ratio (attribute < 12, input >= 12) does not matter."""
    if ctx.is_used(op.output(1)):
        raise op.error(f"has its mask output {shown(op.output(1))} used; only the first output may be used")
    if op.input(2):
        mode = ctx.constant_input(op, 2, "training_mode", "NNCG compiles inference: make it a constant false")
        if bool(np.asarray(mode).reshape(-1)[0]):
            raise op.error("has training_mode=true; NNCG compiles inference: export the model in eval mode")
    return op.ir_node("Identity", [op.input(0)])


def convert_reshape(op: OnnxOp, ctx: Context) -> Node:
    target = ctx.constant_input(op, 1, "target shape", SHAPE_HINT)
    dims = [int(d) for d in np.asarray(target).reshape(-1)]
    shape = reshape_target(op, ctx.shape(op.input(0)), dims, bool(op.attr("allowzero", 0)))
    return _reshape(op, ctx, shape)


def convert_flatten(op: OnnxOp, ctx: Context) -> Node:
    in_shape = ctx.shape(op.input(0))
    rank, axis = len(in_shape), op.attr("axis", 1)
    if not -rank <= axis <= rank:  # axis == rank is allowed: [N, 1]-style output
        raise op.error(f"has axis {axis}, out of range for rank {rank}")
    axis = axis + rank if axis < 0 else axis
    return _reshape(op, ctx, (math.prod(in_shape[:axis]), math.prod(in_shape[axis:])))


def convert_squeeze(op: OnnxOp, ctx: Context) -> Node:
    in_shape = ctx.shape(op.input(0))
    axes = _axes(op, ctx, required=False)
    if axes is None:
        return _reshape(op, ctx, tuple(d for d in in_shape if d != 1))
    axes = {axis_index(op, a, len(in_shape)) for a in axes}
    if any(in_shape[a] != 1 for a in axes):
        raise op.error(f"squeezes axes {sorted(axes)} of shape {list(in_shape)}, but only size-1 dims can be squeezed")
    return _reshape(op, ctx, tuple(d for i, d in enumerate(in_shape) if i not in axes))


def convert_unsqueeze(op: OnnxOp, ctx: Context) -> Node:
    in_shape = ctx.shape(op.input(0))
    raw = _axes(op, ctx, required=True)
    rank = len(in_shape) + len(raw)
    axes = {axis_index(op, a, rank) for a in raw}  # axes index the output
    if len(axes) != len(raw):
        raise op.error(f"has repeated axes {list(raw)}")
    rest = iter(in_shape)
    return _reshape(op, ctx, tuple(1 if i in axes else next(rest) for i in range(rank)))


def reshape_target(op: OnnxOp, in_shape: Shape, dims: list[int], allowzero: bool) -> Shape:
    """Reshape's output shape: 0 copies the input dim (unless allowzero), one -1 is inferred."""
    total = math.prod(in_shape)

    def bad(reason: str) -> NncgError:
        return op.error(
            f"cannot reshape {list(in_shape)} ({total:,} elements) to {dims}: {reason}; a reshape keeps the "
            "element count: fix its shape input (0 copies the input's dim, one -1 takes what is left), or the "
            "--input-shape if the model was exported for another input size"
        )

    out = []
    for i, d in enumerate(dims):
        if d == 0 and not allowzero:
            if i >= len(in_shape):
                raise bad(f"its 0 at position {i} copies an input dim the rank-{len(in_shape)} input lacks")
            d = in_shape[i]
        out.append(d)
    if out.count(-1) > 1 or any(d < -1 for d in out):
        raise bad("it may have one -1 and no other negative dim")
    if -1 in out:
        known = math.prod(d for d in out if d != -1)
        if known == 0 or total % known:
            raise bad(f"the dims other than -1 make {known:,} elements, which do not divide {total:,}")
        out[out.index(-1)] = total // known
    if math.prod(out) != total:
        raise bad(f"that has {math.prod(out):,} elements")
    return tuple(out)


def _reshape(op: OnnxOp, ctx: Context, shape: Shape) -> Node:
    ctx.set_shape(op, op.node.output[0], shape)
    return op.ir_node("Reshape", [op.input(0)], ReshapeAttrs(tuple(int(d) for d in shape)))


def _axes(op: OnnxOp, ctx: Context, required: bool) -> list[int] | None:
    """Squeeze/Unsqueeze axes: an attribute before opset 13, an input from 13 on."""
    if ctx.opset < 13:
        axes = op.attr("axes")
    elif op.input(1):
        axes = ctx.constant_input(op, 1, "axes", SHAPE_HINT).reshape(-1).tolist()
    else:
        axes = None
    if axes is None and required:
        raise op.error(f"has no axes, which {op.type} requires: give the axes to insert")
    return None if axes is None else [int(a) for a in axes]


def axis_index(op: OnnxOp, axis: int, rank: int) -> int:
    """A possibly negative ONNX axis as an index in [0, rank)."""
    if not -rank <= axis < rank:
        raise op.error(f"has axis {axis}, out of range for rank {rank}")
    return axis % rank
