"""Resize and Upsample for the generator: nearest with every nearest_mode and coordinate mode
(tf_half_pixel_for_nn where it exists: opset 11), linear, scales or sizes, axes (opset 18)."""

from __future__ import annotations

import numpy as np

from .build import StepContext
from .draw import Draw, Proposal

COORDINATE_MODES = ("half_pixel", "asymmetric", "pytorch_half_pixel", "align_corners", "tf_half_pixel_for_nn")
NEAREST_MODES = ("round_prefer_floor", "round_prefer_ceil", "floor", "ceil")


def _resized(c: StepContext, x: tuple[int, ...]) -> tuple[list[int], list[float] | None, list[int] | None]:
    """Output shape, per-axis scales (or None) and sizes (or None) of a Resize/Upsample step."""
    p = c.params
    axes = [c.axis(int(a), len(x)) for a in p["axes"]] if "axes" in p else list(range(len(x)))
    if "sizes" in p:
        sizes = [int(v) for v in p["sizes"]]
        if len(sizes) != len(axes) or min(sizes) < 1:
            raise c.invalid(f"sizes {sizes} do not fit axes {axes}")
        out = list(x)
        for a, s in zip(axes, sizes):
            out[a] = s
        return out, None, sizes
    scales = [float(np.float32(v)) for v in p.get("scales", [1.0] * len(axes))]
    if len(scales) != len(axes) or min(scales) <= 0:
        raise c.invalid(f"scales {scales} do not fit axes {axes}")
    out = list(x)
    for a, s in zip(axes, scales):
        out[a] = int(np.floor(np.float32(s) * np.float32(x[a])))
    return out, scales, None


def build_resize(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if c.opset < 10:
        raise c.invalid("Resize needs opset >= 10")
    if "axes" in p and c.opset < 18:
        raise c.invalid("Resize axes need opset >= 18")
    out, scales, sizes = _resized(c, x)
    if c.opset == 10:
        if scales is None or "axes" in p:
            raise c.invalid("Resize-10 takes full scales only")
        c.node("Resize", [c.input(), c.const(scales, role="scales")], [c.output()], mode=p.get("mode", "nearest"))
        return [tuple(out)]
    attrs = {k: p[k] for k in ("mode", "coordinate_transformation_mode", "nearest_mode") if k in p}
    if "axes" in p:
        attrs["axes"] = [int(a) for a in p["axes"]]
    empty = c.const(np.zeros(0, np.float32), role="empty") if c.opset < 13 else ""
    operands = [c.input(), empty]
    if sizes is None:
        operands.append(c.const(scales, role="scales"))
    else:
        operands += [empty, c.ints(sizes, "sizes")]
    c.node("Resize", operands, [c.output()], **attrs)
    return [tuple(out)]


def propose_resize(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    spatial = list(range(2, rank)) if rank >= 3 else list(range(rank))
    linear = rank == 4 and d.chance(0.45)
    params: dict = {"mode": "linear"} if linear else {"mode": "nearest"} if d.chance(0.5) else {}
    if d.opset >= 11:
        modes = [m for m in COORDINATE_MODES if m != "tf_half_pixel_for_nn" or (d.opset == 11 and not linear)]
        if d.chance(0.85):
            # tf_half_pixel_for_nn 3x as often where it exists: only opset 11's nearest Resize has it
            weights = [3.0 if m == "tf_half_pixel_for_nn" else 1.0 for m in modes]
            params["coordinate_transformation_mode"] = d.pick(modes, weights)
        if not linear and d.chance(0.8):
            params["nearest_mode"] = d.pick(NEAREST_MODES)
    resized = spatial if linear or d.chance(0.8) else list(range(rank))
    listed = list(range(rank))
    if d.opset >= 18 and d.chance(0.4):
        listed = sorted(int(a) for a in d.rng.choice(resized, size=d.int(1, len(resized)), replace=False))
        params["axes"] = listed
    factors = (0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 1.3)
    if d.opset >= 11 and d.chance(0.4):
        # sizes one off a multiple give ratios that do not repeat along the axis (no periodic pieces)
        grow = [max(1, round(shape[a] * d.pick(factors)) + d.pick((0, 1, -1))) for a in listed]
        params["sizes"] = [g if a in resized else shape[a] for a, g in zip(listed, grow)]
    else:
        params["scales"] = [float(d.pick(factors)) if a in resized else 1.0 for a in listed]
    return Proposal([x], params)


def build_upsample(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if c.opset > 9:
        raise c.invalid("Upsample is for opset <= 9")
    scales = [float(v) for v in p.get("scales", [1.0] * len(x))]
    if len(scales) != len(x) or min(scales) < 1:
        raise c.invalid(f"scales {scales} for rank {len(x)}")
    out = [int(np.floor(np.float32(s) * np.float32(n))) for s, n in zip(scales, x)]
    mode = p.get("mode", "nearest")
    if c.opset == 9:
        c.node("Upsample", [c.input(), c.const(scales, role="scales")], [c.output()], mode=mode)
    else:
        c.node("Upsample", [c.input()], [c.output()], mode=mode, scales=scales)
    return [tuple(out)]


def propose_upsample(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    linear = rank == 4 and d.chance(0.4)
    scales = [float(d.pick((1.0, 2.0, 3.0, 1.5))) if a >= 2 or rank < 3 else 1.0 for a in range(rank)]
    return Proposal([x], {"mode": "linear" if linear else "nearest", "scales": scales})
