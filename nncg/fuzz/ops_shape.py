"""Data-movement ops for the generator: Flatten, Reshape, Squeeze, Unsqueeze, Transpose, Slice, Pad,
Split, Concat, Dropout, Identity (Resize and Upsample are in ops_resize)."""

from __future__ import annotations

import math

import numpy as np

from .build import StepContext
from .draw import Draw, Proposal

PAD_MODES = ("constant", "reflect", "edge", "wrap")
INT64_MAX = (1 << 63) - 1


def shape_operand(c: StepContext, values, role: str) -> str:
    """An int64 operand as an initializer, or as a Constant node (folded by NNCG at import)."""
    if not c.params.get("constant_node"):
        return c.ints(values, role)
    return c.const_node(np.asarray(values, dtype=np.int64))


# --- reshaping ------------------------------------------------------------------------------------


def build_flatten(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    axis = c.axis(int(c.params.get("axis", 1)), len(x), allow_end=True)
    attrs = {"axis": int(c.params["axis"])} if "axis" in c.params else {}
    c.node("Flatten", [c.input()], [c.output()], **attrs)
    return [(math.prod(x[:axis]), math.prod(x[axis:]))]


def propose_flatten(d: Draw, x: str) -> Proposal:
    rank = len(d.shapes[x])
    return Proposal([x], {"axis": d.axis(d.int(0, rank), rank)} if d.chance(0.5) else {})


def reshape_dims(c: StepContext, tokens: list, x: tuple[int, ...]) -> tuple[list[int], tuple[int, ...]]:
    """The Reshape operand and the output shape for `tokens`: an int, "dI" (input dim I), "dI*dJ*..."
    (a product of input dims), "0" (ONNX: copy the dim at this position) or "-1" (the rest)."""
    operand, out = [], []
    for i, token in enumerate(tokens):
        if token in ("0", "-1"):
            if token == "0" and i >= len(x):
                raise c.invalid("0 past the input rank")
            operand.append(int(token))
            out.append(x[i] if token == "0" else -1)
            continue
        if isinstance(token, int):
            value = token
        else:
            dims = [int(part[1:]) for part in token.split("*")]
            if max(dims) >= len(x):
                raise c.invalid(f"{token} past the input rank {len(x)}")
            value = math.prod(x[j] for j in dims)
        operand.append(value)
        out.append(value)
    known = math.prod(v for v in out if v != -1)
    if out.count(-1) > 1 or known == 0 or math.prod(x) % known:
        raise c.invalid(f"cannot reshape {list(x)} to {tokens}")
    out = [math.prod(x) // known if v == -1 else v for v in out]
    if math.prod(out) != math.prod(x):
        raise c.invalid(f"cannot reshape {list(x)} to {out}")
    return operand, tuple(out)


def build_reshape(c: StepContext) -> list[tuple[int, ...]]:
    operand, out = reshape_dims(c, list(c.params.get("target", ["-1"])), c.shape())
    c.node("Reshape", [c.input(), shape_operand(c, operand, "shape")], [c.output()])
    return [out]


def propose_reshape(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    if rank == 0:
        return Proposal([x], {"target": d.pick(([1], [1, 1], ["-1"]))})
    kind = d.pick(("merge", "split", "flat", "rank2"))
    tokens: list = [f"d{i}" for i in range(rank)]
    if kind == "merge" and rank >= 2:
        i = d.int(0, rank - 2)
        tokens[i : i + 2] = [f"d{i}*d{i + 1}"]
    elif kind == "split":
        i = d.int(0, rank - 1)
        factors = [f for f in range(2, shape[i]) if shape[i] % f == 0]
        if factors:
            f = d.pick(factors)
            tokens[i : i + 1] = [f, shape[i] // f]
        else:
            tokens.insert(i, 1)
    elif kind == "flat":
        tokens = ["-1"]
    else:
        tokens = ["d0", "-1"] if rank > 1 else ["-1", 1]
    if d.chance(0.3):
        j = d.int(0, len(tokens) - 1)
        if isinstance(tokens[j], str) and tokens[j].startswith("d") and "-1" not in tokens:
            tokens[j] = "-1"
    if d.chance(0.2) and tokens and tokens[0] == "d0":
        tokens[0] = "0"
    return Proposal([x], {"target": tokens, "constant_node": d.chance(0.2)})


def build_squeeze(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    axes = c.params.get("axes")
    if axes is None:
        out = tuple(n for n in x if n != 1)
    else:
        chosen = {c.axis(int(a), len(x)) for a in axes}
        if any(x[a] != 1 for a in chosen) or len(chosen) != len(axes):
            raise c.invalid(f"cannot squeeze {axes} of {list(x)}")
        out = tuple(n for i, n in enumerate(x) if i not in chosen)
    _axes_node(c, "Squeeze", axes)
    return [out]


def _axes_node(c: StepContext, op: str, axes) -> None:
    if axes is None:
        c.node(op, [c.input()], [c.output()])
    elif c.opset >= 13:
        c.node(op, [c.input(), c.ints(axes, "axes")], [c.output()])
    else:
        c.node(op, [c.input()], [c.output()], axes=list(axes))


def propose_squeeze(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    ones = [i for i, n in enumerate(shape) if n == 1]
    if not ones:
        return None
    if d.chance(0.3):
        return Proposal([x], {})
    axes = sorted({d.pick(ones) for _ in range(2)})
    return Proposal([x], {"axes": [d.axis(a, len(shape)) for a in axes]})


def build_unsqueeze(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    axes = [int(a) for a in c.params.get("axes", [0])]
    rank = len(x) + len(axes)
    chosen = sorted(c.axis(a, rank) for a in axes)
    if len(set(chosen)) != len(chosen):
        raise c.invalid("repeated axes")
    out = list(x)
    for a in chosen:
        out.insert(a, 1)
    _axes_node(c, "Unsqueeze", axes)
    return [tuple(out)]


def propose_unsqueeze(d: Draw, x: str) -> Proposal | None:
    rank = len(d.shapes[x])
    if rank >= 5:
        return None
    count = d.pick((1, 1, 2)) if rank <= 3 else 1
    axes = sorted(int(a) for a in d.rng.choice(rank + count, size=count, replace=False))
    return Proposal([x], {"axes": [d.axis(a, rank + count) for a in axes]})


def build_transpose(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    perm = c.params.get("perm")
    if perm is not None and sorted(perm) != list(range(len(x))):
        raise c.invalid(f"perm {perm} is not a permutation of rank {len(x)}")
    order = list(perm) if perm is not None else list(range(len(x)))[::-1]
    attrs = {"perm": list(perm)} if perm is not None else {}
    c.node("Transpose", [c.input()], [c.output()], **attrs)
    return [tuple(x[i] for i in order)]


def propose_transpose(d: Draw, x: str) -> Proposal | None:
    rank = len(d.shapes[x])
    if rank < 2:
        return None
    if d.chance(0.15):
        return Proposal([x], {})
    if rank >= 4 and d.chance(0.5):  # NCHW <-> NHWC, what exporters from TensorFlow write
        perm = d.pick(([0, 2, 3, 1], [0, 3, 1, 2])) if rank == 4 else list(d.rng.permutation(rank))
    else:
        perm = [int(v) for v in d.rng.permutation(rank)]
    return Proposal([x], {"perm": [int(v) for v in perm]})


# --- Slice, Pad -----------------------------------------------------------------------------------


def build_slice(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    axes = [int(a) for a in p.get("axes", range(len(x)))]
    starts, ends = (
        [int(v) for v in p.get("starts", [0] * len(axes))],
        [int(v) for v in p.get("ends", [INT64_MAX] * len(axes))],
    )
    steps = [int(v) for v in p.get("steps", [1] * len(axes))]
    if not len(axes) == len(starts) == len(ends) == len(steps) or 0 in steps:
        raise c.invalid("starts, ends, axes, steps differ in length")
    out = list(x)
    for a, s, e, st in zip(axes, starts, ends, steps):
        i = c.axis(a, len(x))
        out[i] = len(range(*slice(s, e, st).indices(x[i])))
    if c.opset < 10:
        if any(st != 1 for st in steps):
            raise c.invalid("Slice-1 has no steps")
        c.node("Slice", [c.input()], [c.output()], starts=starts, ends=ends, axes=axes if "axes" in p else None)
    else:
        operands = [c.input(), c.ints(starts, "starts"), c.ints(ends, "ends")]
        operands += [c.ints(axes, "axes") if "axes" in p else "", c.ints(steps, "steps") if "steps" in p else ""]
        c.node("Slice", operands, [c.output()])
    return [tuple(out)]


def propose_slice(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    axes = sorted(int(a) for a in d.rng.choice(rank, size=d.int(1, rank), replace=False))
    starts, ends, steps = [], [], []
    for a in axes:
        n = shape[a]
        step = d.pick((1, 1, 1, 2, -1, -2)) if d.opset >= 10 else 1
        if step > 0:
            start = d.pick((0, d.int(0, n - 1), -d.int(1, n)))
            end = d.pick((n, INT64_MAX, -1 if n > 1 else n, d.int(1, n)))
        else:
            start = d.pick((n - 1, -1, INT64_MAX, d.int(0, n - 1)))
            end = d.pick((-INT64_MAX, -n - 1, d.int(-n - 1, n - 1)))
        starts.append(start), ends.append(end), steps.append(step)
    params: dict = {"starts": starts, "ends": ends}
    if len(axes) != rank or axes != list(range(rank)) or d.chance(0.5):
        params["axes"] = [d.axis(a, rank) for a in axes]
    if any(s != 1 for s in steps) or (d.opset >= 10 and d.chance(0.3)):
        params["steps"] = steps
    return Proposal([x], params)


def build_pad(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    mode = p.get("mode", "constant")
    if mode == "wrap" and c.opset < 19:
        raise c.invalid("wrap needs opset >= 19")
    axes = [int(a) for a in p["axes"]] if "axes" in p else list(range(len(x)))
    pads = [int(v) for v in p.get("pads", [0] * 2 * len(axes))]
    if len(pads) != 2 * len(axes) or ("axes" in p and c.opset < 18):
        raise c.invalid(f"pads {pads} do not fit axes {axes}")
    out = list(x)
    for k, a in enumerate(axes):
        i = c.axis(a, len(x))
        begin, end = pads[k], pads[k + len(axes)]
        limit = x[i] - 1 if mode == "reflect" else x[i]
        if mode != "constant" and (min(begin, end) < 0 or max(begin, end) > limit):
            raise c.invalid(f"{mode} pads {begin}, {end} for a dim of {x[i]}")
        out[i] += begin + end
    value = float(p.get("value", 0.0))
    if c.opset < 11:
        c.node("Pad", [c.input()], [c.output()], pads=pads, mode=mode, value=value if "value" in p else None)
    else:
        operands = [c.input(), c.ints(pads, "pads"), c.const(np.float32(value), role="value") if "value" in p else ""]
        operands += [c.ints(axes, "axes")] if "axes" in p else []
        attrs = {"mode": mode} if "mode" in p else {}
        c.node("Pad", operands, [c.output()], **attrs)
    return [tuple(out)]


def propose_pad(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    modes = [m for m in PAD_MODES if m != "wrap" or d.opset >= 19]
    mode = d.pick(modes)
    if d.opset >= 18 and d.chance(0.3):
        axes = sorted(int(a) for a in d.rng.choice(rank, size=d.int(1, rank), replace=False))
    else:
        axes = list(range(rank))
    spatial = set(range(2, rank)) if rank >= 3 else set(range(rank))

    def amount(a: int) -> int:
        if a not in spatial and (d.chance(0.7) or a == 0):
            return 0
        top = shape[a] - 1 if mode == "reflect" else shape[a] if mode == "wrap" else 3
        low = -1 if mode == "constant" and shape[a] > 2 and d.chance(0.1) else 0
        return d.int(low, max(min(top, 3), 0))

    pads = [amount(a) for a in axes] + [amount(a) for a in axes]
    params: dict = {"pads": pads}
    if mode != "constant" or d.chance(0.5):
        params["mode"] = mode
    if mode == "constant" and d.chance(0.5):
        params["value"] = d.pick((0.5, -1.0, 2.0))
    if axes != list(range(rank)):
        params["axes"] = axes
    return Proposal([x], params)


# --- Split, Concat --------------------------------------------------------------------------------


def build_split(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    axis = c.axis(int(p.get("axis", 0)), len(x))
    count = len(c.step.outputs)
    sizes = [int(v) for v in p["sizes"]] if "sizes" in p else None
    n = x[axis]
    if sizes is not None and (len(sizes) != count or sum(sizes) != n or min(sizes) < 1):
        raise c.invalid(f"split {sizes} does not cut {n} into {count}")
    attrs: dict = {"axis": int(p["axis"])} if "axis" in p else {}
    operands = [c.input()]
    if sizes is None:
        if c.opset >= 18:
            attrs["num_outputs"] = count
            chunk = -(-n // count)
            sizes = [chunk] * (count - 1) + [n - chunk * (count - 1)]
        else:
            sizes = [n // count] * count
            if n % count:
                raise c.invalid(f"{n} does not split evenly into {count}")
        if min(sizes) < 1:
            raise c.invalid(f"{n} does not split into {count} non-empty parts")
    elif c.opset >= 13:
        operands.append(c.ints(sizes, "split"))
    else:
        attrs["split"] = sizes
    c.node("Split", operands, list(c.step.outputs), **attrs)
    return [tuple(s if i == axis else d for i, d in enumerate(x)) for s in sizes]


def propose_split(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    axes = [a for a, n in enumerate(shape) if n >= 2]
    if not axes:
        return None
    axis = d.pick(axes)
    n = shape[axis]
    count = d.int(2, min(3, n))
    params: dict = {"axis": d.axis(axis, len(shape))}
    if d.chance(0.5) or (n % count and d.opset < 18):
        cuts = sorted(int(v) for v in d.rng.choice(np.arange(1, n), size=count - 1, replace=False))
        params["sizes"] = [b - a for a, b in zip([0, *cuts], [*cuts, n])]
    return Proposal([x], params, outputs=count)


def build_concat(c: StepContext) -> list[tuple[int, ...]]:
    shapes = [c.shape(i) for i in range(len(c.step.inputs))]
    p = c.params
    axis = c.axis(int(p.get("axis", 1)), len(shapes[0]))
    names = list(c.step.inputs)
    if "const_extent" in p:
        extent = int(p["const_extent"])
        shape = tuple(extent if i == axis else n for i, n in enumerate(shapes[0]))
        names.append(c.const(c.rng.standard_normal(shape).astype(np.float32), role="k"))
        shapes.append(shape)
    for s in shapes[1:]:
        if len(s) != len(shapes[0]) or any(a != b for i, (a, b) in enumerate(zip(s, shapes[0])) if i != axis):
            raise c.invalid(f"cannot concatenate {[list(s) for s in shapes]} on axis {axis}")
    c.node("Concat", names, [c.output()], axis=int(p.get("axis", 1)))
    return [tuple(sum(s[axis] for s in shapes) if i == axis else n for i, n in enumerate(shapes[0]))]


def propose_concat(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    rank = len(shape)
    axis = 1 if rank >= 2 and d.chance(0.6) else d.int(0, rank - 1)

    def fits(a, b) -> bool:
        return len(a) == len(b) and all(p == q for i, (p, q) in enumerate(zip(a, b)) if i != axis)

    inputs = [x]
    for _ in range(d.pick((1, 1, 2))):
        y = d.partner(x, fits)
        if y is not None:
            inputs.append(y)
    params: dict = {"axis": d.axis(axis, rank), "seed": d.seed()}
    if len(inputs) == 1 or d.chance(0.1):
        params["const_extent"] = d.pick((1, 2, 3))
    return Proposal(inputs, params)


# --- Dropout, Identity ----------------------------------------------------------------------------


def build_dropout(c: StepContext) -> list[tuple[int, ...]]:
    operands = [c.input()]
    attrs: dict = {}
    if "ratio" in c.params:
        if c.opset >= 12:
            operands.append(c.const(np.float32(c.params["ratio"]), role="ratio"))
        else:
            attrs["ratio"] = float(c.params["ratio"])
    outputs = [c.output()] + ([c.temp()] if c.params.get("mask") and c.opset >= 7 else [])
    c.node("Dropout", operands, outputs, **attrs)
    return [c.shape()]


def propose_dropout(d: Draw, x: str) -> Proposal:
    params: dict = {}
    if d.chance(0.5):
        params["ratio"] = d.pick((0.1, 0.5))
    if d.chance(0.3):
        params["mask"] = True
    return Proposal([x], params)


def build_identity(c: StepContext) -> list[tuple[int, ...]]:
    c.node("Identity", [c.input()], [c.output()])
    return [c.shape()]


def propose_identity(d: Draw, x: str) -> Proposal:
    return Proposal([x], {})
