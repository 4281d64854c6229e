"""ONNX front end (ONNX -> graph IR), step 3: InstanceNormalization, GroupNormalization and
LayerNormalization (inference; statistics in float32, whatever LayerNormalization's stash_type)."""

from __future__ import annotations

from nncg.frontend.context import Context, OnnxOp
from nncg.ir.graph import Node, NormAttrs, Shape
from nncg.safe_text import shown


def convert_instance_norm(op: OnnxOp, ctx: Context) -> Node:
    """Per (n, c) over the spatial dims: a GroupNormalization with one group per channel."""
    shape = _checked_input(op, ctx)
    _check_parameters(op, ctx, (shape[1],), "one per channel")
    attrs = NormAttrs(_epsilon(op), groups=shape[1])
    return op.ir_node("InstanceNormalization", [op.input(i) for i in range(3)], attrs)


def convert_group_norm(op: OnnxOp, ctx: Context) -> Node:
    """Opset 21's: scale and bias per channel. Opsets 18 to 20 had them per group, a form onnx has
    deprecated and its checker refuses (load_model reports it)."""
    shape = _checked_input(op, ctx)
    groups = op.attr("num_groups")
    if not isinstance(groups, int) or groups < 1 or shape[1] % groups:
        raise op.error(f"has num_groups={groups}; it must divide the {shape[1]} channels")
    _check_parameters(op, ctx, (shape[1],), "one per channel")
    attrs = NormAttrs(_epsilon(op), groups=groups)
    return op.ir_node("GroupNormalization", [op.input(i) for i in range(3)], attrs)


def convert_layer_norm(op: OnnxOp, ctx: Context) -> Node:
    """Over the dims from `axis` on; scale and the optional bias broadcast to them. The Mean and
    InvStdDev outputs, where used, are written too."""
    x = op.input(0)
    shape = ctx.shape(x)
    rank = len(shape)
    axis = op.attr("axis", -1)
    if not -rank <= axis < rank:
        raise op.error(f"has axis {axis}; it must be in [-{rank}, {rank}) for its rank-{rank} input")
    axis %= rank
    inputs = [x, op.input(1)] + ([op.input(2)] if op.input(2) else [])
    for name in inputs[1:]:
        if not _broadcasts_to(ctx.shape(name), shape[axis:]):
            raise op.error(
                f"has scale or bias {shown(name)} of shape {list(ctx.shape(name))}, which does not broadcast "
                f"to the normalised dims {list(shape[axis:])}"
            )
    ctx.set_shape(op, op.node.output[0], shape)
    statistics = [op.output(i) if ctx.is_used(op.output(i)) else None for i in (1, 2)]
    for name in filter(None, statistics):
        ctx.set_shape(op, name, (*shape[:axis], *(1,) * (rank - axis)))
    attrs = NormAttrs(_epsilon(op), axis, mean_output=bool(statistics[0]), inv_std_output=bool(statistics[1]))
    outputs = (op.node.output[0], *filter(None, statistics))
    return Node("LayerNormalization", op.name, tuple(inputs), outputs, attrs)


def _checked_input(op: OnnxOp, ctx: Context) -> Shape:
    shape = ctx.shape(op.input(0))
    if len(shape) < 2:
        raise op.error(f"has a rank-{len(shape)} input; it needs [N, C, D1, ...]")
    ctx.set_shape(op, op.node.output[0], shape)
    return shape


def _check_parameters(op: OnnxOp, ctx: Context, expected: Shape, what: str) -> None:
    for index, role in ((1, "scale"), (2, "bias")):
        if op.input(index) is None:
            raise op.error(f"has no {role}; {op.type} needs scale and bias")
        found = ctx.shape(op.input(index))
        if found != expected:
            raise op.error(f"has {role} of shape {list(found)}; expected {list(expected)} ({what})")


def _broadcasts_to(shape: Shape, target: Shape) -> bool:
    """Whether `shape` broadcasts to `target` (NumPy rules, aligned right) without changing it."""
    if len(shape) > len(target):
        return False
    return all(n in (1, t) for n, t in zip(reversed(shape), reversed(target)))


def _epsilon(op: OnnxOp) -> float:
    return float(op.attr("epsilon", 1e-5))
