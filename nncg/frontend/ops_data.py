"""ONNX front end (ONNX -> graph IR), step 3: convert the ops that move elements without arithmetic
(Concat, Split, Slice, Transpose, Pad) and the resampling ops (Resize, Upsample).

Every index parameter (split sizes, slice bounds, pads, scales, sizes) must be a compile-time
constant. It is resolved here — negative axes, clamped slice bounds, pads as begin/end per dim,
scales per dim — so the lowerings see only static numbers in the IR's attribute records.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np

from nncg.errors import NncgError
from nncg.frontend.context import SHAPE_HINT, Context, OnnxOp
from nncg.frontend.ops_shape import axis_index
from nncg.ir.graph import (
    ConcatAttrs,
    Node,
    PadAttrs,
    ResizeAttrs,
    Shape,
    SliceAttrs,
    SplitAttrs,
    TransposeAttrs,
)
from nncg.safe_text import shown

PAD_MODES = ("constant", "reflect", "edge", "wrap")
COORDINATE_MODES = (
    "half_pixel",
    "half_pixel_symmetric",
    "pytorch_half_pixel",
    "align_corners",
    "asymmetric",
    "tf_half_pixel_for_nn",
    "tf_crop_and_resize",
)
NEAREST_MODES = ("round_prefer_floor", "round_prefer_ceil", "floor", "ceil")
RESIZE_MODES = ("nearest", "linear", "cubic")

# --- Concat, Split -------------------------------------------------------------------------------


def convert_concat(op: OnnxOp, ctx: Context) -> Node:
    return concat_node(op, ctx, [name for name in op.node.input if name])


def concat_node(op: OnnxOp, ctx: Context, inputs: list[str]) -> Node:
    """The Concat of `inputs` along op's axis attribute (Concat's, or QLinearConcat's)."""
    shapes = [ctx.shape(name) for name in inputs]
    if op.attr("axis") is None:
        raise op.error("has no axis attribute, which Concat requires: add the axis to concatenate along")
    rank = len(shapes[0])
    axis = axis_index(op, int(op.attr("axis")), rank)
    for shape in shapes:
        if len(shape) != rank or any(a != b for d, (a, b) in enumerate(zip(shape, shapes[0])) if d != axis):
            raise op.error(f"concatenates shapes {[list(s) for s in shapes]} that differ outside axis {axis}")
    out = list(shapes[0])
    out[axis] = sum(shape[axis] for shape in shapes)
    if out[axis] == 0:
        raise op.error("concatenates only empty tensors; NNCG cannot compile an empty output")
    ctx.set_shape(op, op.node.output[0], tuple(out))
    kept = [name for name, shape in zip(inputs, shapes) if shape[axis]]  # empty inputs add nothing
    return op.ir_node("Concat", kept, ConcatAttrs(axis))


def convert_split(op: OnnxOp, ctx: Context) -> Node:
    """One IR node with one output per used ONNX output; unused outputs are not computed."""
    shape = ctx.shape(op.input(0))
    axis = axis_index(op, int(op.attr("axis", 0)), len(shape))
    sizes = _split_sizes(op, ctx, shape[axis])
    starts = itertools.accumulate([0, *sizes[:-1]])
    outputs, used_starts = [], []
    for name, start, size in zip(op.node.output, starts, sizes):
        if not ctx.is_used(name):
            continue
        if size == 0:
            raise op.error(f"has its empty output {shown(name)} used; NNCG cannot compile empty tensors")
        ctx.set_shape(op, name, tuple(size if d == axis else n for d, n in enumerate(shape)))
        outputs.append(name)
        used_starts.append(start)
    return Node("Split", op.name, (op.input(0),), tuple(outputs), SplitAttrs(axis, tuple(used_starts)))


def _split_sizes(op: OnnxOp, ctx: Context, dim: int) -> list[int]:
    """Split sizes: attribute `split` before opset 13, input from 13; else equal parts (opset 18:
    `num_outputs` parts of ceil(dim / num_outputs), the last one smaller)."""
    count = len(op.node.output)
    if ctx.opset < 13:
        split = op.attr("split")
    elif op.input(1):
        split = int_values(op, ctx.constant_input(op, 1, "split", SHAPE_HINT), "split").tolist()
    else:
        split = None
    if split is not None:
        sizes = [int(s) for s in split]
        if len(sizes) != count or any(s < 0 for s in sizes) or sum(sizes) != dim:
            raise op.error(f"has split {sizes}, which does not cut a dim of {dim} into {count} outputs")
        return sizes
    if ctx.opset >= 18:
        parts = int(op.attr("num_outputs", count))
        if parts != count:
            raise op.error(f"has num_outputs={parts} but {count} outputs: make them agree (or drop num_outputs)")
        chunk = -(-dim // count)
        last = dim - chunk * (count - 1)
        if last < 0:
            raise _uneven(op, dim)
        return [chunk] * (count - 1) + [last]
    if dim % count:
        raise _uneven(op, dim)
    return [dim // count] * count


def _uneven(op: OnnxOp, dim: int) -> NncgError:
    return op.error(f"splits a dim of {dim} into {len(op.node.output)} equal outputs, which is impossible")


# --- Slice, Transpose ----------------------------------------------------------------------------


def convert_slice(op: OnnxOp, ctx: Context) -> Node:
    shape = ctx.shape(op.input(0))
    rank = len(shape)
    starts, ends, axes, steps = _slice_params(op, ctx)
    if axes is None:
        axes = list(range(len(starts)))
    if steps is None:
        steps = [1] * len(starts)
    if not len(starts) == len(ends) == len(axes) == len(steps):
        raise op.error("has starts, ends, axes and steps of different lengths; the model is invalid")
    axes = [axis_index(op, a, rank) for a in axes]
    if len(set(axes)) != len(axes):
        raise op.error(f"has repeated axes {axes}")
    first, step, out = [0] * rank, [1] * rank, list(shape)
    for axis, start, end, stride in zip(axes, starts, ends, steps):
        if stride == 0:
            raise op.error(f"has step 0 on axis {axis}")
        # Python's slice clamps out-of-range starts and ends exactly as ONNX Slice does.
        picked = range(*slice(start, end, stride).indices(shape[axis]))
        if not picked:
            raise op.error(f"selects nothing on axis {axis}; NNCG cannot compile empty tensors")
        first[axis], step[axis], out[axis] = picked.start, picked.step, len(picked)
    ctx.set_shape(op, op.node.output[0], tuple(out))
    return op.ir_node("Slice", [op.input(0)], SliceAttrs(tuple(first), tuple(step)))


def _slice_params(op: OnnxOp, ctx: Context) -> tuple[list[int], list[int], list[int] | None, list[int] | None]:
    """starts, ends, axes, steps: attributes in opset 1 (no steps), constant inputs from opset 10."""
    if ctx.opset < 10:
        if op.attr("starts") is None or op.attr("ends") is None:
            raise op.error("has no starts or ends attribute, which Slice before opset 10 requires: add both")
        axes = op.attr("axes")
        return list(op.attr("starts")), list(op.attr("ends")), None if axes is None else list(axes), None
    params = []
    for index, role in enumerate(("starts", "ends", "axes", "steps"), start=1):
        given = op.input(index) is not None
        params.append(int_values(op, ctx.constant_input(op, index, role, SHAPE_HINT), role).tolist() if given else None)
    return params[0], params[1], params[2], params[3]


def convert_transpose(op: OnnxOp, ctx: Context) -> Node:
    shape = ctx.shape(op.input(0))
    perm = op.attr("perm")
    perm = list(range(len(shape)))[::-1] if perm is None else [int(p) for p in perm]
    if sorted(perm) != list(range(len(shape))):
        raise op.error(f"has perm {perm}, not a permutation of the {len(shape)} dims of its input")
    ctx.set_shape(op, op.node.output[0], tuple(shape[p] for p in perm))
    return op.ir_node("Transpose", [op.input(0)], TransposeAttrs(tuple(perm)))


# --- Pad -----------------------------------------------------------------------------------------


def convert_pad(op: OnnxOp, ctx: Context) -> Node:
    shape = ctx.shape(op.input(0))
    mode = op.attr("mode", "constant")
    if mode not in PAD_MODES:
        raise op.error(f"has mode {shown(mode)}; NNCG supports {', '.join(PAD_MODES)}")
    pads, value, axes = _pad_params(op, ctx, len(shape))
    if len(pads) != 2 * len(axes):
        raise op.error(f"has {len(pads)} pads for {len(axes)} axes; it needs two per axis")
    begin, end = [0] * len(shape), [0] * len(shape)
    for axis, b, e in zip(axes, pads[: len(axes)], pads[len(axes) :]):
        begin[axis], end[axis] = b, e
    out = tuple(n + b + e for n, b, e in zip(shape, begin, end))
    if min(out) < 1:
        raise op.error(f"pads {list(shape)} to {list(out)}; NNCG cannot compile empty tensors")
    if mode in ("reflect", "wrap"):
        _check_border_source(op, mode, shape, begin, end)
    ctx.set_shape(op, op.node.output[0], out)
    attrs = PadAttrs(tuple(begin), tuple(end), mode, 0.0 if isinstance(value, str) else value)
    return op.ir_node("Pad", [op.input(0), *([value] if isinstance(value, str) else [])], attrs)


def _pad_params(op: OnnxOp, ctx: Context, rank: int) -> tuple[list[int], float | str, list[int]]:
    """pads, the constant value and the padded axes: attributes before opset 11, constant inputs
    from 11 (axes from 18), but for a constant value computed at run time: its value's name."""
    if ctx.opset < 11:
        if op.attr("pads") is None:
            raise op.error("has no pads attribute, which Pad before opset 11 requires: add the pads")
        return [int(p) for p in op.attr("pads")], float(op.attr("value", 0.0)), list(range(rank))
    pads = int_values(op, ctx.constant_input(op, 1, "pads", SHAPE_HINT), "pads").tolist()
    value = 0.0
    if op.input(2) and ctx.const(op.input(2)) is None:
        if math.prod(ctx.shape(op.input(2))) != 1:
            raise op.error(f"has a constant_value of shape {list(ctx.shape(op.input(2)))}; it must be one float")
        value = op.input(2)
    elif op.input(2):
        constant = ctx.const(op.input(2))
        if constant.size != 1 or constant.dtype not in (np.float32, np.float64, np.float16, np.int8, np.uint8):
            raise op.error(
                f"has constant_value of type {constant.dtype.name} and size {constant.size}; it must be one float "
                "(or one int8 or uint8, padding integers)"
            )
        value = float(constant.reshape(-1)[0])
    axes = list(range(rank))
    if op.input(3):
        raw = int_values(op, ctx.constant_input(op, 3, "axes", SHAPE_HINT), "axes").tolist()
        axes = [axis_index(op, a, rank) for a in raw]
        if len(set(axes)) != len(axes):
            raise op.error(f"has repeated axes {raw}")
    return pads, value, axes


def _check_border_source(op: OnnxOp, mode: str, shape: Shape, begin: list[int], end: list[int]) -> None:
    """Reflect mirrors and wrap repeats the (cropped) input once at most, so pads must not exceed it."""
    for axis, (n, b, e) in enumerate(zip(shape, begin, end)):
        kept = n - max(0, -b) - max(0, -e)
        limit = kept - 1 if mode == "reflect" else kept
        if max(b, e) > limit:
            raise op.error(
                f"pads axis {axis} of size {kept} by {max(b, e)} in {mode} mode; at most {limit} is possible"
            )


# --- Resize, Upsample ----------------------------------------------------------------------------


def convert_resize(op: OnnxOp, ctx: Context) -> Node:
    shape = ctx.shape(op.input(0))
    mode = _resize_mode(op, RESIZE_MODES if ctx.opset >= 11 else RESIZE_MODES[:2])
    if ctx.opset < 11:  # Resize-10: inputs X, scales; asymmetric coordinates, legacy rounding
        scales = _scales_input(op, ctx, 1, len(shape), None)
        if scales is None:
            raise op.error("has an empty scales input; Resize-10 needs one scale per input dim: give them")
        return _resize(op, ctx, ResizeAttrs(tuple(scales), mode, "asymmetric", "simple"))
    coordinates = op.attr("coordinate_transformation_mode", "half_pixel")
    if coordinates not in COORDINATE_MODES:
        raise op.error(
            f"has coordinate_transformation_mode {shown(coordinates)}; NNCG supports {', '.join(COORDINATE_MODES)}"
        )
    nearest = op.attr("nearest_mode", "round_prefer_floor")
    if mode == "nearest" and nearest not in NEAREST_MODES:
        raise op.error(f"has nearest_mode {shown(nearest)}; NNCG supports {', '.join(NEAREST_MODES)}")
    axes = op.attr("axes")
    axes = None if axes is None else [axis_index(op, int(a), len(shape)) for a in axes]
    scales = _scales_input(op, ctx, 2, len(shape), axes) if op.input(2) else None
    sizes = _sizes_input(op, ctx, len(shape), axes) if op.input(3) else None
    if (scales is None) == (sizes is None):
        raise op.error(
            f"has {'both' if scales is not None else 'neither'} scales and sizes; give exactly one of them "
            "(the other empty, or left out)"
        )
    if sizes is not None:
        scales, sizes = _sizes_and_scales(op, shape, sizes, axes)
    attrs = ResizeAttrs(
        tuple(scales),
        mode,
        coordinates,
        nearest if mode == "nearest" else "round_prefer_floor",
        cubic_coeff_a=float(np.float32(op.attr("cubic_coeff_a", -0.75))),
        exclude_outside=bool(op.attr("exclude_outside", 0)),
        antialias=_antialias(op, mode),
        roi=_roi(op, ctx, len(shape), axes) if coordinates == "tf_crop_and_resize" else (),
        extrapolation_value=float(np.float32(op.attr("extrapolation_value", 0.0))),
    )
    return _resize(op, ctx, attrs, sizes)


def convert_upsample(op: OnnxOp, ctx: Context) -> Node:
    """Upsample (opset 7 to 9) is Resize-10: asymmetric coordinates, legacy nearest rounding."""
    rank = len(ctx.shape(op.input(0)))
    mode = _resize_mode(op, RESIZE_MODES[:2])
    if op.input(1):
        scales = _scales_input(op, ctx, 1, rank, None)
    elif op.attr("scales") is not None:
        scales = _checked_scales(op, [float(s) for s in op.attr("scales")], rank)
    else:
        raise op.error("has no scales (neither an input nor an attribute); give one scale per input dim")
    if min(scales) < 1:
        raise op.error(f"has scales {scales}; Upsample needs scales >= 1")
    return _resize(op, ctx, ResizeAttrs(tuple(scales), mode, "asymmetric", "simple"))


def _resize(op: OnnxOp, ctx: Context, attrs: ResizeAttrs, sizes: list[int] | None = None) -> Node:
    """The IR node; the output shape is `sizes` when given, else floor(in * scale) in float32, as
    onnxruntime computes it."""
    in_shape = ctx.shape(op.input(0))
    if sizes is not None:
        out = tuple(sizes)
    else:
        out = tuple(int(np.floor(np.float32(s) * np.float32(n))) for s, n in zip(attrs.scales, in_shape))
    if min(out) < 1:
        raise op.error(f"resizes {list(in_shape)} to {list(out)}; NNCG cannot compile empty tensors")
    ctx.set_shape(op, op.node.output[0], out)
    if attrs.mode != "nearest":  # nearest_mode means nothing there: one spelling for equal resizes
        attrs = replace(attrs, nearest_mode="round_prefer_floor")
    return op.ir_node("Resize", [op.input(0)], attrs)


def _resize_mode(op: OnnxOp, modes: tuple[str, ...] = RESIZE_MODES) -> str:
    mode = op.attr("mode", "nearest")
    if mode not in modes:
        raise op.error(f"has mode {shown(mode)}; {op.type} here supports {', '.join(modes)}")
    return mode


def _sizes_and_scales(op: OnnxOp, shape: Shape, sizes: list[int], axes: list[int] | None) -> tuple[list, list]:
    """Scales out/in in float32 for `stretch`; with keep_aspect_ratio_policy not_larger (not_smaller)
    the smallest (largest) of the listed axes' scales for all of them, and sizes round(in * scale)
    (ONNX shape inference has refused any other policy)."""
    scales = [float(np.float32(o) / np.float32(n)) for o, n in zip(sizes, shape)]
    policy = op.attr("keep_aspect_ratio_policy", "stretch")
    if policy == "stretch":
        return scales, sizes
    listed = range(len(shape)) if axes is None else axes
    pick = min if policy == "not_larger" else max
    scale = np.float32(pick(scales[d] for d in listed))
    scales = [float(scale) if d in listed else 1.0 for d in range(len(shape))]
    sizes = [
        int(np.float32(scale) * np.float32(n) + np.float32(0.5)) if d in listed else n for d, n in enumerate(shape)
    ]
    return scales, sizes


def _antialias(op: OnnxOp, mode: str) -> bool:
    antialias = bool(op.attr("antialias", 0))
    if antialias and mode == "nearest":
        raise op.error("has antialias=1 with mode nearest; antialias applies to linear and cubic only")
    return antialias


def _roi(op: OnnxOp, ctx: Context, rank: int, axes: list[int] | None) -> tuple[tuple[float, float], ...]:
    """tf_crop_and_resize's region per dim: (start, end) as fractions of the input length (dims not
    in `axes` keep the whole length)."""
    roi = ctx.constant_input(op, 1, "roi", SHAPE_HINT) if op.input(1) else np.zeros(0, np.float32)
    listed = list(range(rank)) if axes is None else axes
    if roi.dtype.kind != "f" or roi.size != 2 * len(listed):
        raise op.error(
            f"has a roi of {roi.size} values; tf_crop_and_resize needs {2 * len(listed)} floats "
            "(the starts, then the ends, of the resized axes)"
        )
    values = roi.astype(np.float32).reshape(-1).tolist()
    region = [(0.0, 1.0)] * rank
    for i, axis in enumerate(listed):
        region[axis] = (values[i], values[len(listed) + i])
    return tuple(region)


def _scales_input(op: OnnxOp, ctx: Context, index: int, rank: int, axes: list[int] | None) -> list[float] | None:
    """The scales input, one per dim (dims not in `axes` keep scale 1); None when it is empty (a
    placeholder next to sizes in opset 11)."""
    scales = ctx.constant_input(op, index, "scales", SHAPE_HINT)
    if scales.dtype.kind != "f":
        raise op.error(f"has scales of type {scales.dtype.name}; they must be floats")
    if scales.size == 0:
        return None
    return _checked_scales(op, _per_dim(op, scales.astype(np.float32).reshape(-1).tolist(), rank, axes, 1.0), rank)


def _sizes_input(op: OnnxOp, ctx: Context, rank: int, axes: list[int] | None) -> list[int]:
    sizes = int_values(op, ctx.constant_input(op, 3, "sizes", SHAPE_HINT), "sizes").tolist()
    in_shape = ctx.shape(op.input(0))
    full = _per_dim(op, sizes, rank, axes, None)
    return [n if s is None else int(s) for s, n in zip(full, in_shape)]


def _per_dim(op: OnnxOp, values: list, rank: int, axes: list[int] | None, default) -> list:
    axes = list(range(rank)) if axes is None else axes
    if len(values) != len(axes):
        raise op.error(f"has {len(values)} scales or sizes for {len(axes)} axes")
    full = [default] * rank
    for axis, v in zip(axes, values):
        full[axis] = v
    return full


def _checked_scales(op: OnnxOp, scales: list[float], rank: int) -> list[float]:
    if len(scales) != rank or not all(s > 0 and math.isfinite(s) for s in scales):
        raise op.error(f"has scales {scales}; it needs {rank} positive scales")
    return [float(np.float32(s)) for s in scales]


def int_values(op: OnnxOp, array: np.ndarray, role: str) -> np.ndarray:
    if array.dtype.kind not in "iu":
        raise op.error(f"has {role} of type {array.dtype.name}; they must be integers")
    return array.astype(np.int64).reshape(-1)
