"""Windowed ops for the generator: Conv (1-D to 3-D, pads or auto_pad, strides, dilations, groups,
depthwise, runtime weights), ConvTranspose, MaxPool, AveragePool and the global pools."""

from __future__ import annotations

import math

from .build import StepContext
from .draw import Draw, Proposal

AUTO_PADS = ("SAME_UPPER", "SAME_LOWER", "VALID")


def window_extent(kernel: int, dilation: int) -> int:
    return (kernel - 1) * dilation + 1


def _dims(c: StepContext, key: str, default: int) -> list[int]:
    d = len(c.shape()) - 2
    values = [int(v) for v in c.params.get(key, [default] * d)]
    if len(values) != d or min(values, default=1) < (0 if key == "pads" else 1):
        raise c.invalid(f"{key} {values} do not fit a rank-{d + 2} input")
    return values


def _pads(c: StepContext) -> list[int]:
    d = len(c.shape()) - 2
    pads = [int(v) for v in c.params.get("pads", [0] * 2 * d)]
    if len(pads) != 2 * d or min(pads, default=0) < 0:
        raise c.invalid(f"pads {pads} do not fit a rank-{d + 2} input")
    return pads


def _spatial(c: StepContext) -> tuple[list[int], list[int], list[int], list[int]]:
    """Input sizes, kernel, strides, dilations of a windowed step."""
    x = c.shape()
    if len(x) < 3:
        raise c.invalid(f"needs a rank >= 3 input, got {list(x)}")
    return list(x[2:]), _dims(c, "kernel", 1), _dims(c, "strides", 1), _dims(c, "dilations", 1)


def window_output(
    n: int, k: int, s: int, dil: int, begin: int, end: int, auto_pad: str, ceil: bool = False, drop_last: bool = True
) -> int:
    """Output size along one axis as onnxruntime computes it (ceil_mode drops a window starting in the
    end pad; not with `drop_last` False, as onnx's shape inference computes it)."""
    ext = window_extent(k, dil)
    if auto_pad in ("SAME_UPPER", "SAME_LOWER"):
        return -(-n // s)
    if auto_pad == "VALID":
        begin = end = 0
    span = n + begin + end - ext
    if span < 0:
        return 0
    if not ceil:
        return span // s + 1
    out = -(-span // s) + 1
    return out - 1 if drop_last and (out - 1) * s >= n + begin else out


def _window_attrs(c: StepContext) -> dict:
    """strides, dilations, pads / auto_pad attributes as the params give them (absent: ONNX defaults)."""
    p = c.params
    attrs = {k: [int(v) for v in p[k]] for k in ("strides", "dilations") if k in p}
    if "auto_pad" in p:
        attrs["auto_pad"] = p["auto_pad"]
    elif "pads" in p:
        attrs["pads"] = [int(v) for v in p["pads"]]
    return attrs


def _out_sizes(c: StepContext, ceil: bool = False, drop_last: bool = True) -> list[int]:
    sizes, kernel, strides, dilations = _spatial(c)
    pads, auto_pad = _pads(c), c.params.get("auto_pad", "NOTSET")
    d = len(sizes)
    out = [
        window_output(n, k, s, dil, pads[i], pads[i + d], auto_pad, ceil, drop_last)
        for i, (n, k, s, dil) in enumerate(zip(sizes, kernel, strides, dilations))
    ]
    if min(out) < 1:
        raise c.invalid(f"window {kernel} does not fit {sizes}")
    return out


# --- Conv -----------------------------------------------------------------------------------------


def build_conv(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    out = _out_sizes(c)
    _, kernel, _, _ = _spatial(c)
    c_in = x[1]
    depthwise = p.get("group") == "depthwise"
    group = c_in if depthwise else int(p.get("group", 1))
    c_out = c_in * int(p.get("multiplier", 1)) if depthwise else int(p.get("c_out", 1))
    if group < 1 or c_in % group or c_out % group or c_out < 1:
        raise c.invalid(f"group {group} does not divide {c_in} input and {c_out} output channels")
    w = c.weights(c_out, c_in // group, *kernel)
    inputs = [c.input(), c.weight_operand(w, bool(p.get("runtime_w")))]
    if p.get("bias"):
        inputs.append(c.weight_operand(c.weights(c_out, fan_in=4), bool(p.get("runtime_b")), "b"))
    attrs = _window_attrs(c)
    if p.get("kernel_attr"):
        attrs["kernel_shape"] = kernel
    if group != 1 or "group" in p:
        attrs["group"] = group
    c.node("Conv", inputs, [c.output()], **attrs)
    return [(x[0], c_out, *out)]


def _propose_window(d: Draw, sizes, kernel_max: int = 3, pads: bool = True, dilation: bool = True) -> dict:
    """Kernel, strides, dilations and padding for a window over `sizes` (output size >= 1 mostly;
    the builder refuses the rest)."""
    n = len(sizes)
    square = d.chance(0.6)
    k0 = d.int(1, kernel_max)
    kernel = [k0 if square else d.int(1, kernel_max) for _ in range(n)]
    params: dict = {"kernel": kernel}
    if d.chance(0.4):
        params["strides"] = [d.pick((1, 2, 2, 3)) for _ in range(n)]
    if dilation and d.chance(0.2):
        params["dilations"] = [d.pick((1, 2, 2, 3)) for _ in range(n)]
    if d.chance(0.25):
        params["auto_pad"] = d.pick(AUTO_PADS)
        if params["auto_pad"] != "VALID":
            params.pop("dilations", None)  # onnxruntime: no dilations with SAME padding
    elif pads and d.chance(0.7):
        params["pads"] = [d.int(0, max(k - 1, 0) if d.chance(0.8) else k) for k in kernel * 2]
    return params


def propose_conv(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    if len(shape) < 3:
        return None
    params = _propose_window(d, shape[2:], kernel_max=3 if len(shape) != 3 else 5)
    params["seed"] = d.seed()
    c_in = shape[1]
    roll = d.rng.random()
    if roll < 0.15 and c_in > 1:
        params["group"] = "depthwise"
        params["multiplier"] = d.pick((1, 1, 2))
    elif roll < 0.25:
        divisors = [g for g in range(2, c_in + 1) if c_in % g == 0]
        if divisors:
            g = d.pick(divisors)
            params["group"] = g
            params["c_out"] = g * d.int(1, 3)
    if "c_out" not in params and params.get("group") != "depthwise":
        params["c_out"] = d.channels()
    if d.chance(0.3) and len(shape) == 4 and "auto_pad" not in params:  # Winograd's case: 3x3, stride 1
        params.update(kernel=[3, 3], pads=[1, 1, 1, 1])
        params.pop("strides", None), params.pop("dilations", None)
    params["bias"] = d.chance(0.7)
    params["kernel_attr"] = d.chance(0.5)
    if d.chance(0.06):
        params["runtime_w"] = True
    if params["bias"] and d.chance(0.04):
        params["runtime_b"] = True
    return Proposal([x], params)


# --- ConvTranspose --------------------------------------------------------------------------------


def build_conv_transpose(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    sizes, kernel, strides, dilations = _spatial(c)
    c_in, group = x[1], int(p.get("group", 1))
    c_out = group * int(p.get("c_out_per_group", 1))
    if c_in % group:
        raise c.invalid(f"group {group} does not divide {c_in} channels")
    out_pad = _dims(c, "output_padding", 0) if "output_padding" in p else [0] * len(sizes)
    if any(op >= s for op, s in zip(out_pad, strides)):  # onnxruntime: below the stride (the spec: or dilation)
        raise c.invalid(f"output_padding {out_pad} not below the strides {strides}")
    attrs = _window_attrs(c)
    if "output_padding" in p:
        attrs["output_padding"] = out_pad
    if "output_shape" in p:
        out = [int(v) for v in p["output_shape"]]
        if len(out) != len(sizes):
            raise c.invalid("output_shape has the wrong rank")
        attrs = {k: v for k, v in attrs.items() if k not in ("pads",)}
        attrs["output_shape"] = out
    else:
        out = _transpose_sizes(c, sizes, kernel, strides, dilations, out_pad)
    if min(out) < 1:
        raise c.invalid(f"output {out}")
    full = [
        s * (n - 1) + op + window_extent(k, dil) for n, k, s, dil, op in zip(sizes, kernel, strides, dilations, out_pad)
    ]
    if any(o > f for o, f in zip(out, full)):
        raise c.invalid(f"output_shape {out} larger than the full transposed window {full}")
    w = c.weights(c_in, c_out // group, *kernel, fan_in=(c_in // group) * math.prod(kernel))
    inputs = [c.input(), c.weight_operand(w, bool(p.get("runtime_w")))]
    if p.get("bias"):
        inputs.append(c.const(c.weights(c_out, fan_in=4), role="b"))
    if group != 1:
        attrs["group"] = group
    if p.get("kernel_attr"):
        attrs["kernel_shape"] = kernel
    c.node("ConvTranspose", inputs, [c.output()], **attrs)
    return [(x[0], c_out, *out)]


def _transpose_sizes(c, sizes, kernel, strides, dilations, out_pad) -> list[int]:
    auto_pad = c.params.get("auto_pad", "NOTSET")
    if auto_pad in ("SAME_UPPER", "SAME_LOWER"):
        return [n * s for n, s in zip(sizes, strides)]
    pads = [0] * 2 * len(sizes) if auto_pad == "VALID" else _pads(c)
    d = len(sizes)
    return [
        s * (n - 1) + op + window_extent(k, dil) - pads[i] - pads[i + d]
        for i, (n, k, s, dil, op) in enumerate(zip(sizes, kernel, strides, dilations, out_pad))
    ]


def propose_conv_transpose(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    if len(shape) < 3:
        return None
    params = _propose_window(d, shape[2:], kernel_max=4)
    params["seed"] = d.seed()
    if d.chance(0.3):
        params["output_padding"] = [d.int(0, s - 1) for s in params.get("strides", [1] * (len(shape) - 2))]
    if d.chance(0.25) and "auto_pad" not in params:
        params["output_shape"] = [n * d.int(1, 2) + d.int(0, 1) for n in shape[2:]]
        params.pop("pads", None)
    groups = [g for g in (1, 1, 1, 2, 3, shape[1]) if shape[1] % g == 0]
    params["group"] = d.pick(groups)
    params["c_out_per_group"] = d.pick((1, 2, 3, 4, 8)) if params["group"] > 1 else d.channels(33)
    params["bias"] = d.chance(0.6)
    params["kernel_attr"] = d.chance(0.5)
    if d.chance(0.05):
        params["runtime_w"] = True
    return Proposal([x], params)


# --- pools ----------------------------------------------------------------------------------------


def _window_in_padding(c: StepContext, out: list[int]) -> bool:
    """Whether some output window of a pool reads padding only."""
    sizes, kernel, strides, dilations = _spatial(c)
    auto_pad, pads = c.params.get("auto_pad", "NOTSET"), _pads(c)
    for i, (n, k, s, dil, o) in enumerate(zip(sizes, kernel, strides, dilations, out)):
        begin = pads[i]
        if auto_pad == "VALID":
            begin = 0
        elif auto_pad.startswith("SAME"):
            total = max(0, (o - 1) * s + window_extent(k, dil) - n)
            begin = total // 2 if auto_pad == "SAME_UPPER" else total - total // 2
        for j in range(o):
            if all(not 0 <= j * s - begin + t * dil < n for t in range(k)):
                return True
    return False


def build_pool(c: StepContext, op: str) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    ceil = bool(p.get("ceil_mode"))
    if ceil and c.opset < 10:
        raise c.invalid("ceil_mode needs opset >= 10")
    if "dilations" in p and c.opset < (10 if op == "MaxPool" else 19):
        raise c.invalid(f"{op} dilations need a newer opset")
    _, kernel, _, _ = _spatial(c)
    if len(kernel) > 3:
        raise c.invalid("onnxruntime pools 1 to 3 spatial dims")
    pads = _pads(c)
    d = len(kernel)
    if any(pads[i] >= kernel[i] or pads[i + d] >= kernel[i] for i in range(d)):
        raise c.invalid("pool pads must be smaller than the kernel")
    out = _out_sizes(c, ceil)
    if ceil and out != _out_sizes(c, ceil, drop_last=False):
        # onnx's shape inference keeps the window starting in the end pad that onnxruntime drops: the
        # generator reads this value no more (a later op checking the inferred shape fails in onnxruntime)
        c.builder.dead_ends.add(c.output())
    if p.get("auto_pad", "").startswith("SAME"):
        sizes, _, strides, dilations = _spatial(c)
        needed = [
            (o - 1) * s + window_extent(k, dl) - n for o, s, k, dl, n in zip(out, strides, kernel, dilations, sizes)
        ]
        if min(needed) < 0:  # onnxruntime refuses the negative padding SAME gives when stride > kernel
            raise c.invalid(f"SAME padding {needed} is negative")
    if op == "MaxPool" and _window_in_padding(c, out):
        c.builder.dead_ends.add(c.output())  # it gives -FLT_MAX there: x * x or a sum of two overflows
    attrs = _window_attrs(c)
    attrs["kernel_shape"] = kernel
    if ceil:
        attrs["ceil_mode"] = 1
    if op == "AveragePool" and "count_include_pad" in p:
        attrs["count_include_pad"] = int(p["count_include_pad"])
    c.node(op, [c.input()], [c.output()], **attrs)
    return [(x[0], x[1], *out)]


def propose_pool(d: Draw, x: str, op: str) -> Proposal | None:
    shape = d.shapes[x]
    if not 3 <= len(shape) <= 5:  # onnxruntime pools 1 to 3 spatial dims
        return None
    dilation = d.opset >= (10 if op == "MaxPool" else 19)
    params = _propose_window(d, shape[2:], kernel_max=3, pads=False, dilation=dilation)
    if "auto_pad" not in params and d.chance(0.6):
        params["pads"] = [d.int(0, k - 1) for k in params["kernel"] * 2]
    if d.opset >= 10 and d.chance(0.3):
        params["ceil_mode"] = 1
    if op == "AveragePool" and d.chance(0.5):
        params["count_include_pad"] = d.pick((0, 1))
    return Proposal([x], params)


def build_global_pool(c: StepContext, op: str) -> list[tuple[int, ...]]:
    x = c.shape()
    if len(x) < 3:
        raise c.invalid("global pools need rank >= 3")
    c.node(op, [c.input()], [c.output()])
    return [(x[0], x[1], *([1] * (len(x) - 2)))]


def propose_global_pool(d: Draw, x: str) -> Proposal | None:
    return Proposal([x], {}) if len(d.shapes[x]) >= 3 else None
