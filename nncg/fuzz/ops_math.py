"""Arithmetic ops for the generator: activations, PRelu, broadcasting binary and variadic ops,
Softmax/LogSoftmax, ReduceMean, BatchNormalization, LRN, Gemm and MatMul."""

from __future__ import annotations

import numpy as np

from .build import StepContext
from .draw import SMALL_ELEMENTS, Draw, Proposal, broadcast_shape, broadcastable_to, numel

UNARY = ("Relu", "LeakyRelu", "Clip", "Sigmoid", "Tanh", "HardSigmoid", "HardSwish", "Elu")
BINARY = ("Add", "Sub", "Mul", "Div")
VARIADIC = ("Sum", "Max", "Min")


# --- activations ----------------------------------------------------------------------------------


def build_unary(c: StepContext) -> list[tuple[int, ...]]:
    p, op = c.params, c.params.get("op", "Relu")
    if op == "HardSwish" and c.opset < 14:
        raise c.invalid("HardSwish needs opset >= 14")
    attrs = {k: float(p[k]) for k in ("alpha", "beta") if k in p and op in ("LeakyRelu", "HardSigmoid", "Elu")}
    inputs = [c.input()]
    if op == "Clip":
        low, high = p.get("min"), p.get("max")
        if low is not None and high is not None and low > high:
            raise c.invalid("Clip min > max")
        if c.opset < 11:
            attrs = {k: float(v) for k, v in (("min", low), ("max", high)) if v is not None}
        else:
            inputs += ["" if low is None else c.const(np.float32(low), role="min")]
            inputs += [] if high is None else [c.const(np.float32(high), role="max")]
    c.node(op, inputs, [c.output()], **attrs)
    return [c.shape()]


def propose_unary(d: Draw, x: str) -> Proposal | None:
    ops = [op for op in UNARY if op != "HardSwish" or d.opset >= 14]
    op = d.pick(ops)
    params: dict = {"op": op}
    if op == "LeakyRelu" and d.chance(0.7):
        params["alpha"] = round(float(d.pick((0.01, 0.1, 0.3, -0.5, 1.5))), 3)
    if op == "HardSigmoid" and d.chance(0.7):
        params["alpha"], params["beta"] = d.pick((0.2, 0.5, 1 / 6)), d.pick((0.5, 0.3))
    if op == "Elu" and d.chance(0.6):
        params["alpha"] = d.pick((0.5, 1.0, 2.0))
    if op == "Clip":
        bounds = d.pick(((0.0, 6.0), (-1.0, 1.0), (None, 0.5), (-0.5, None), (0.0, None), (None, None)))
        params.update({k: v for k, v in zip(("min", "max"), bounds) if v is not None})
    return Proposal([x], params)


def build_prelu(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    slope = [int(v) for v in c.params.get("slope_shape", [1])]
    if broadcast_shape(x, slope) != x:
        raise c.invalid(f"slope {slope} does not broadcast to {list(x)}")
    values = c.rng.uniform(-0.5, 0.5, slope).astype(np.float32)
    c.node("PRelu", [c.input(), c.const(values, role="slope")], [c.output()])
    return [x]


def propose_prelu(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    if len(shape) >= 2 and d.chance(0.6):
        slope = [shape[1]] + [1] * (len(shape) - 2)  # per channel, as exporters write it
    else:
        slope = broadcastable_to(d, shape)
    return Proposal([x], {"slope_shape": slope, "seed": d.seed()})


# --- broadcasting arithmetic ----------------------------------------------------------------------


def build_binary(c: StepContext) -> list[tuple[int, ...]]:
    p, op = c.params, c.params.get("op", "Add")
    x = c.shape()
    if len(c.step.inputs) > 1:
        other, other_shape = c.input(1), c.shape(1)
        if op == "Div":  # a runtime divisor kept away from zero: sigmoid(v) + 0.5 is in (0.5, 1.5)
            squashed, shifted = c.temp(), c.temp()
            c.node("Sigmoid", [other], [squashed])
            c.node("Add", [squashed, c.const(np.float32(0.5), role="half")], [shifted])
            other = shifted
    else:
        other_shape = tuple(int(v) for v in p.get("b_shape", [1]))
        values = c.rng.standard_normal(other_shape).astype(np.float32)
        if op == "Div":
            values = (np.sign(values) + (values == 0)) * c.rng.uniform(0.5, 2.0, other_shape).astype(np.float32)
        other = c.const(values, role="b")
    out = broadcast_shape(x, other_shape)
    if out is None:
        raise c.invalid(f"{list(x)} and {list(other_shape)} do not broadcast")
    operands = [other, c.input()] if p.get("swap") and op != "Div" else [c.input(), other]
    c.node(op, operands, [c.output()])
    return [out]


def propose_binary(d: Draw, x: str) -> Proposal | None:
    op = d.pick(BINARY)
    shape = d.shapes[x]
    params: dict = {"op": op, "seed": d.seed(), "swap": d.chance(0.3)}
    if d.chance(0.55):
        y = d.partner(x, lambda a, b: _small(broadcast_shape(a, b)))
        if y is not None:
            return Proposal([x, y], params)
    params["b_shape"] = broadcastable_to(d, shape)
    return Proposal([x], params)


def _small(shape) -> bool:
    return shape is not None and numel(shape) <= SMALL_ELEMENTS


def build_variadic(c: StepContext) -> list[tuple[int, ...]]:
    out: tuple[int, ...] | None = c.shape(0)
    for i in range(1, len(c.step.inputs)):
        out = broadcast_shape(out, c.shape(i)) if out is not None else None
    if out is None:
        raise c.invalid("inputs do not broadcast")
    c.node(c.params.get("op", "Sum"), list(c.step.inputs), [c.output()])
    return [out]


def propose_variadic(d: Draw, x: str) -> Proposal:
    inputs = [x]
    for _ in range(d.pick((0, 1, 1, 2))):
        y = d.partner(inputs[-1], lambda a, b: _small(broadcast_shape(a, b)) and b != a or d.chance(0.2))
        if y is not None and _small(broadcast_shape(d.shapes[inputs[-1]], d.shapes[y])):
            inputs.append(y)
    return Proposal(inputs, {"op": d.pick(VARIADIC)})


# --- normalisation, softmax, reduction ------------------------------------------------------------


def build_softmax(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    c.axis(int(c.params.get("axis", -1 if c.opset >= 13 else 1)), len(x))
    attrs = {"axis": int(c.params["axis"])} if "axis" in c.params else {}
    c.node(c.params.get("op", "Softmax"), [c.input()], [c.output()], **attrs)
    return [x]


def propose_softmax(d: Draw, x: str) -> Proposal:
    rank = len(d.shapes[x])
    params: dict = {"op": d.pick(("Softmax", "LogSoftmax"))}
    if d.chance(0.7):
        params["axis"] = d.axis(d.int(0, rank - 1), rank)
    return Proposal([x], params)


def build_reduce_mean(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    keep = int(p.get("keepdims", 1))
    axes = p.get("axes")
    if axes is not None and not axes:
        raise c.invalid("empty axes")
    chosen = set(range(len(x))) if axes is None else {c.axis(int(a), len(x)) for a in axes}
    if axes is not None and len(chosen) != len(axes):
        raise c.invalid("repeated axes")
    attrs: dict = {"keepdims": keep} if "keepdims" in p else {}
    inputs = [c.input()]
    if axes is not None:
        if c.opset >= 18:
            inputs.append(c.ints(axes, "axes"))
        else:
            attrs["axes"] = list(axes)
    c.node("ReduceMean", inputs, [c.output()], **attrs)
    out = (
        [1 if i in chosen else n for i, n in enumerate(x)] if keep else [n for i, n in enumerate(x) if i not in chosen]
    )
    return [tuple(out)]


def propose_reduce_mean(d: Draw, x: str) -> Proposal:
    rank = len(d.shapes[x])
    params: dict = {}
    if d.chance(0.85):
        count = d.int(1, rank)
        axes = sorted(int(a) for a in d.rng.choice(rank, size=count, replace=False))
        params["axes"] = [d.axis(a, rank) for a in axes]
    if d.chance(0.6):
        params["keepdims"] = d.pick((0, 1))
    return Proposal([x], params)


def build_batchnorm(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    if len(x) < 2:
        raise c.invalid("BatchNormalization needs rank >= 2")
    ch = x[1]
    scale = c.rng.uniform(0.5, 1.5, ch)
    bias, mean = c.rng.normal(0, 0.3, ch), c.rng.normal(0, 0.3, ch)
    var = c.rng.uniform(0.5, 1.5, ch)
    names = [c.const(v, role=r) for v, r in ((scale, "g"), (bias, "beta"), (mean, "mu"), (var, "var"))]
    attrs = {"epsilon": float(c.params["epsilon"])} if "epsilon" in c.params else {}
    c.node("BatchNormalization", [c.input(), *names], [c.output()], **attrs)
    return [x]


def propose_batchnorm(d: Draw, x: str) -> Proposal | None:
    if len(d.shapes[x]) < 2:
        return None
    params: dict = {"seed": d.seed()}
    if d.chance(0.4):
        params["epsilon"] = d.pick((1e-5, 1e-3, 0.1))
    return Proposal([x], params)


def build_lrn(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if len(x) != 4:
        raise c.invalid("LRN is generated for rank-4 inputs")
    attrs = {k: float(p[k]) for k in ("alpha", "beta", "bias") if k in p}
    c.node("LRN", [c.input()], [c.output()], size=int(p.get("size", 1)), **attrs)
    return [x]


def propose_lrn(d: Draw, x: str) -> Proposal | None:
    if len(d.shapes[x]) != 4:
        return None
    params: dict = {"size": d.pick((1, 3, 5))}  # onnxruntime takes odd sizes only
    for key, values in (("alpha", (1e-4, 1e-2, 0.5)), ("beta", (0.5, 0.75, 1.0)), ("bias", (1.0, 2.0))):
        if d.chance(0.5):
            params[key] = d.pick(values)
    return Proposal([x], params)


# --- Gemm, MatMul ---------------------------------------------------------------------------------


def build_gemm(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if len(x) != 2:
        raise c.invalid("Gemm needs a rank-2 input")
    trans_a, trans_b = int(p.get("transA", 0)), int(p.get("transB", 0))
    m, k = (x[1], x[0]) if trans_a else x
    n = int(p.get("n", 1))
    w = c.weights(*((n, k) if trans_b else (k, n)), fan_in=k)
    inputs = [c.input(), c.weight_operand(w, bool(p.get("runtime_b")), "B")]
    bias = p.get("c", "none")
    if bias == "none" and c.opset < 11:
        raise c.invalid("Gemm needs its C input before opset 11")
    if bias != "none":
        shapes = {"vector": (n,), "row": (1, n), "scalar": (), "one": (1,)}
        inputs.append(c.const(c.weights(*shapes[bias], fan_in=4) if shapes[bias] else np.float32(0.3), role="C"))
    attrs = {k_: v for k_, v in (("transA", trans_a), ("transB", trans_b)) if v}
    attrs |= {k_: float(p[k_]) for k_ in ("alpha", "beta") if k_ in p}
    c.node("Gemm", inputs, [c.output()], **attrs)
    return [(m, n)]


def propose_gemm(d: Draw, x: str) -> Proposal | None:
    if len(d.shapes[x]) != 2:
        return None
    params: dict = {"n": d.pick((1, 3, 7, 10, 16, 17, 33)), "seed": d.seed()}
    params["transB"] = d.pick((0, 1))
    if d.chance(0.3):
        params["transA"] = 1
    if d.chance(0.3):
        params["alpha"] = d.pick((0.5, 2.0))
    if d.chance(0.2):
        params["beta"] = d.pick((0.0, 0.5, 2.0))
    biases = ("none", "vector", "vector", "row", "scalar", "one") if d.opset >= 11 else ("vector", "row", "one")
    params["c"] = d.pick(biases)  # C is optional from opset 11 on
    if d.chance(0.06):
        params["runtime_b"] = True
    return Proposal([x], params)


def build_matmul(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if len(x) < 2:
        raise c.invalid("MatMul is generated for rank >= 2")
    if len(c.step.inputs) > 1:
        y = c.shape(1)
        a, b, names = x, y, [c.input(), c.input(1)]
    elif p.get("const_a"):
        a = (int(p.get("m", 1)), x[-2])
        b, names = x, [c.const(c.weights(*a, fan_in=x[-2]), role="A"), c.input()]
    else:
        batch = tuple(int(v) for v in p.get("batch", []))
        b = (*batch, x[-1], int(p.get("n", 1)))
        a, names = x, [c.input(), c.weight_operand(c.weights(*b, fan_in=x[-1]), bool(p.get("runtime_b")), "B")]
    if len(b) < 2 or a[-1] != b[-2]:
        raise c.invalid(f"cannot multiply {list(a)} by {list(b)}")
    batch_out = broadcast_shape(a[:-2], b[:-2])
    if batch_out is None:
        raise c.invalid(f"batch dims of {list(a)} and {list(b)} do not broadcast")
    c.node("MatMul", names, [c.output()])
    return [(*batch_out, a[-2], b[-1])]


def propose_matmul(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    if len(shape) < 2:
        return None
    params: dict = {"seed": d.seed()}
    if d.chance(0.15):
        y = d.partner(x, lambda a, b: len(b) >= 2 and b[-2] == a[-1] and _small(broadcast_shape(a[:-2], b[:-2])))
        if y is not None:
            return Proposal([x, y], params)
    if d.chance(0.2):
        params.update(const_a=True, m=d.pick((1, 3, 8, 17)))
        return Proposal([x], params)
    params["n"] = d.pick((1, 3, 4, 8, 16, 17))
    if len(shape) > 2 and d.chance(0.4):
        params["batch"] = broadcastable_to(d, shape[:-2])
    if d.chance(0.05):
        params["runtime_b"] = True
    return Proposal([x], params)
