"""ONNX front end (ONNX -> graph IR): sliding-window arithmetic shared by Conv, ConvTranspose and
MaxPool (strides, dilations, pads from `pads` or auto_pad, pooled output sizes with ceil_mode,
transposed output sizes with output_padding and output_shape).
"""

from __future__ import annotations

import math

from nncg.frontend.context import OnnxOp
from nncg.ir.graph import PoolAttrs, Shape
from nncg.safe_text import shown


def window_steps(op: OnnxOp, n: int) -> tuple[Shape, Shape]:
    """strides and dilations over n spatial dims, both defaulting to 1."""
    strides = tuple(int(s) for s in op.attr("strides", [1] * n))
    dilations = tuple(int(d) for d in op.attr("dilations", [1] * n))
    if len(strides) != n or len(dilations) != n or min(strides + dilations, default=1) < 1:
        raise op.error(f"has strides {list(strides)} / dilations {list(dilations)}; expected {n} positive values each")
    return strides, dilations


def resolve_pads(op: OnnxOp, in_spatial: Shape, kernel: Shape, strides: Shape, dilations: Shape) -> tuple[Shape, Shape]:
    """pads_begin, pads_end from explicit `pads` or from auto_pad."""
    n = len(kernel)
    auto_pad = _auto_pad(op)
    if auto_pad == "NOTSET":
        return explicit_pads(op, n)
    if auto_pad == "VALID":
        return (0,) * n, (0,) * n
    totals = [same_total_pad(*dims) for dims in zip(in_spatial, kernel, strides, dilations, strict=True)]
    return split_pads(totals, auto_pad == "SAME_UPPER")


def _auto_pad(op: OnnxOp) -> str:
    auto_pad = op.attr("auto_pad", "NOTSET")
    if auto_pad not in ("NOTSET", "VALID", "SAME_UPPER", "SAME_LOWER"):
        raise op.error(f"has unknown auto_pad {shown(auto_pad)}; expected NOTSET, VALID, SAME_UPPER or SAME_LOWER")
    return auto_pad


def explicit_pads(op: OnnxOp, n: int) -> tuple[Shape, Shape]:
    pads = tuple(int(p) for p in op.attr("pads", [0] * 2 * n))
    if len(pads) != 2 * n or min(pads, default=0) < 0:
        raise op.error(f"has pads {list(pads)}; expected {2 * n} non-negative values")
    return pads[:n], pads[n:]


def split_pads(totals, odd_at_end: bool) -> tuple[Shape, Shape]:
    """Total pads split evenly between begin and end; an odd one goes to the end or the begin."""
    small = tuple(t // 2 for t in totals)
    big = tuple(t - t // 2 for t in totals)
    return (small, big) if odd_at_end else (big, small)


def same_total_pad(size: int, kernel: int, stride: int, dilation: int) -> int:
    """Total padding that makes a SAME window produce ceil(size / stride) outputs."""
    return max((math.ceil(size / stride) - 1) * stride + (kernel - 1) * dilation + 1 - size, 0)


def conv_transpose_geometry(
    op: OnnxOp, in_spatial: Shape, kernel: Shape, strides: Shape, dilations: Shape
) -> tuple[Shape, Shape, Shape]:
    """pads_begin, pads_end and the output's spatial shape of a ConvTranspose.

    The full output is (in - 1)*stride + output_padding + (kernel - 1)*dilation + 1 and the pads crop
    it. With output_shape, or auto_pad SAME (output in*stride), the total crop is the difference,
    split as onnxruntime and the spec do: an odd one at the end for SAME_UPPER, else at the begin.
    Explicit pads are then ignored. An output_shape beyond the full output makes negative pads:
    outputs no input reaches, which get the bias."""
    n = len(kernel)
    output_padding = tuple(int(p) for p in op.attr("output_padding", [0] * n))
    if len(output_padding) != n or min(output_padding, default=0) < 0:
        raise op.error(f"has output_padding {list(output_padding)}; expected {n} non-negative values")
    dims = zip(in_spatial, strides, output_padding, kernel, dilations, strict=True)
    full = tuple((i - 1) * s + extra + (k - 1) * d + 1 for i, s, extra, k, d in dims)
    auto_pad = _auto_pad(op)
    if op.attr("output_shape") is not None:
        targets = tuple(int(t) for t in op.attr("output_shape"))
        if len(targets) != n or min(targets, default=1) < 1:
            raise op.error(f"has output_shape {list(targets)}; expected {n} positive spatial sizes")
    elif auto_pad in ("SAME_UPPER", "SAME_LOWER"):
        targets = tuple(i * s for i, s in zip(in_spatial, strides))
        if any(t > f for t, f in zip(targets, full)):  # onnxruntime then returns the full output
            raise op.error(
                f"has auto_pad {auto_pad} asking for output {list(targets)}, beyond the full transposed "
                f"convolution {list(full)}; onnxruntime and the ONNX spec disagree here: give output_shape"
            )
    else:
        begin, end = explicit_pads(op, n) if auto_pad == "NOTSET" else ((0,) * n, (0,) * n)
        out = tuple(f - b - e for f, b, e in zip(full, begin, end))
        if min(out) < 1:
            raise op.error(f"has pads {[*begin, *end]} that crop away its whole output {list(full)}")
        return begin, end, out
    begin, end = split_pads([f - t for f, t in zip(full, targets)], auto_pad == "SAME_UPPER")
    return begin, end, targets


def pool_attrs(op: OnnxOp, in_shape: Shape) -> PoolAttrs:
    kernel = tuple(int(k) for k in op.attr("kernel_shape", ()))
    strides, dilations = window_steps(op, len(kernel))
    begin, end = resolve_pads(op, in_shape[2:], kernel, strides, dilations)
    # ceil_mode applies with auto_pad too: onnxruntime and ONNX shape inference both treat VALID as
    # zero pads under the ceil rule (the spec's VALID formula disagrees; implementations win).
    return PoolAttrs(kernel, strides, dilations, begin, end, bool(op.attr("ceil_mode", 0)))


def pool_output_shape(attrs: PoolAttrs, in_shape: Shape) -> Shape:
    dims = zip(
        in_shape[2:], attrs.kernel, attrs.strides, attrs.dilations, attrs.pads_begin, attrs.pads_end, strict=True
    )
    return tuple(in_shape[:2]) + tuple(pool_output_size(*d, attrs.ceil_mode) for d in dims)


def checked_pool_output_shape(op: OnnxOp, attrs: PoolAttrs, in_shape: Shape) -> Shape:
    """pool_output_shape, refusing a window larger than the padded input: the spec's output is then
    empty (onnxruntime's integer division makes it one window reaching past the padding instead)."""
    out = pool_output_shape(attrs, in_shape)
    for axis, (size, extent) in enumerate(zip(in_shape[2:], window_extents(attrs))):
        padded = size + attrs.pads_begin[axis] + attrs.pads_end[axis]
        if out[2 + axis] < 1:
            raise op.error(
                f"has a window of {extent} along spatial axis {axis}, larger than its padded input ({size} + pads "
                f"{attrs.pads_begin[axis]} + {attrs.pads_end[axis]} = {padded}): the ONNX spec makes the output "
                "empty, which NNCG does not support (onnxruntime computes one window reaching past the padding): "
                "pad the input so the window fits, or set ceil_mode=1 to keep that one clipped window"
            )
    return out


def check_window_fits(op: OnnxOp, in_spatial: Shape, kernel: Shape, dilations: Shape, begin: Shape, end: Shape) -> None:
    """A convolution window must fit its padded input: the spec's output is empty otherwise (ONNX
    shape inference says one position, and onnxruntime refuses the model)."""
    for axis, (size, k, d, b, e) in enumerate(zip(in_spatial, kernel, dilations, begin, end)):
        extent = (k - 1) * d + 1
        if extent > size + b + e:
            raise op.error(
                f"has a window of {extent} along spatial axis {axis}, larger than its padded input ({size} + pads "
                f"{b} + {e}); its output would be empty (onnxruntime refuses the model): pad the input so the "
                "window fits, or give a larger --input-shape"
            )


def window_extents(attrs: PoolAttrs) -> Shape:
    return tuple((k - 1) * d + 1 for k, d in zip(attrs.kernel, attrs.dilations))


def pool_output_size(size: int, kernel: int, stride: int, dilation: int, begin: int, end: int, ceil_mode: bool) -> int:
    span = size + begin + end - ((kernel - 1) * dilation + 1)
    out = (-(-span // stride) if ceil_mode else span // stride) + 1
    if ceil_mode and (out - 1) * stride >= size + begin:
        out -= 1  # the ONNX spec drops a last window that would start in the end padding
    return out
