"""ONNX front end (ONNX -> graph IR): sliding-window arithmetic shared by Conv and MaxPool
(strides, dilations, pads from `pads` or auto_pad, pooled output sizes with ceil_mode).
"""

from __future__ import annotations

import math

from nncg.frontend.context import OnnxOp
from nncg.ir.graph import PoolAttrs, Shape


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
    auto_pad = op.attr("auto_pad", "NOTSET")
    if auto_pad == "NOTSET":
        pads = tuple(int(p) for p in op.attr("pads", [0] * 2 * n))
        if len(pads) != 2 * n or min(pads, default=0) < 0:
            raise op.error(f"has pads {list(pads)}; expected {2 * n} non-negative values")
        return pads[:n], pads[n:]
    if auto_pad == "VALID":
        return (0,) * n, (0,) * n
    if auto_pad not in ("SAME_UPPER", "SAME_LOWER"):
        raise op.error(f"has unknown auto_pad '{auto_pad}'; expected NOTSET, VALID, SAME_UPPER or SAME_LOWER")
    totals = [same_total_pad(*dims) for dims in zip(in_spatial, kernel, strides, dilations, strict=True)]
    small = tuple(t // 2 for t in totals)
    big = tuple(t - t // 2 for t in totals)
    return (small, big) if auto_pad == "SAME_UPPER" else (big, small)


def same_total_pad(size: int, kernel: int, stride: int, dilation: int) -> int:
    """Total padding that makes a SAME window produce ceil(size / stride) outputs."""
    return max((math.ceil(size / stride) - 1) * stride + (kernel - 1) * dilation + 1 - size, 0)


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


def pool_output_size(size: int, kernel: int, stride: int, dilation: int, begin: int, end: int, ceil_mode: bool) -> int:
    span = size + begin + end - ((kernel - 1) * dilation + 1)
    out = (-(-span // stride) if ceil_mode else span // stride) + 1
    if ceil_mode and (out - 1) * stride >= size + begin:
        out -= 1  # the ONNX spec drops a last window that would start in the end padding
    return out
