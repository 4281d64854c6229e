"""Reductions and normalisations for the generator: ReduceSum, ReduceMax, ReduceMin, ReduceL1,
ReduceL2, ReduceSumSquare, ReduceLogSum, ReduceLogSumExp (ReduceMean is in ops_math), ArgMax and
ArgMin, InstanceNormalization, GroupNormalization (opset 21's) and LayerNormalization.

ArgMax/ArgMin give int64 indices: the builder marks them (ModelBuilder.index_values), declares them
int64 graph outputs and refuses any step reading them (NNCG converts no op that reads int64)."""

from __future__ import annotations

import math

import numpy as np

from .build import StepContext
from .draw import Draw, Proposal
from .ops_activation import positive, positive_params

# ReduceSum takes its axes as an input from opset 13, the others from opset 18.
AXES_INPUT_OPSET = {"ReduceSum": 13}


def build_reduce(c: StepContext, op: str) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    keep = int(p.get("keepdims", 1))
    axes = p.get("axes")
    axes_input = c.opset >= AXES_INPUT_OPSET.get(op, 18)
    noop = int(p.get("noop_with_empty_axes", 0))
    if axes is not None and not axes and not axes_input:
        raise c.invalid("empty axes need the axes input")
    chosen = set(range(len(x))) if not axes else {c.axis(int(a), len(x)) for a in axes}
    if axes and len(chosen) != len(axes):
        raise c.invalid("repeated axes")
    attrs: dict = {"keepdims": keep} if "keepdims" in p else {}
    if noop and axes_input:
        attrs["noop_with_empty_axes"] = 1
    source = positive(c, p["positive"], float(p.get("floor", 0.1))) if "positive" in p else c.input()
    inputs = [source]
    if axes is not None:
        if axes_input:
            inputs.append(c.ints(axes, "axes"))
        else:
            attrs["axes"] = list(axes)
    c.node(op, inputs, [c.output()], **attrs)
    if noop and axes_input and not axes:
        return [x]  # nothing reduced
    out = (
        [1 if i in chosen else n for i, n in enumerate(x)] if keep else [n for i, n in enumerate(x) if i not in chosen]
    )
    return [tuple(out)]


def propose_reduce(d: Draw, x: str, op: str) -> Proposal:
    rank = len(d.shapes[x])
    params: dict = {}
    axes_input = d.opset >= AXES_INPUT_OPSET.get(op, 18)
    if axes_input and d.chance(0.08):
        params["axes"] = []  # no axes: all of them, or (noop_with_empty_axes) none
        params["noop_with_empty_axes"] = d.pick((0, 1))
    elif d.chance(0.85):
        count = d.int(1, rank)
        axes = sorted(int(a) for a in d.rng.choice(rank, size=count, replace=False))
        params["axes"] = [d.axis(a, rank) for a in axes]
    if d.chance(0.6):
        params["keepdims"] = d.pick((0, 1))
    if op == "ReduceLogSum":  # the log of a positive sum
        params.update(positive_params(d))
    return Proposal([x], params)


# --- ArgMax, ArgMin -------------------------------------------------------------------------------


def build_arg_extreme(c: StepContext, op: str) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    if not x:
        raise c.invalid(f"{op} needs a tensor")
    axis = c.axis(int(p.get("axis", 0)), len(x))
    keep = int(p.get("keepdims", 1))
    attrs: dict = {k: int(p[k]) for k in ("axis", "keepdims") if k in p}
    if p.get("select_last_index"):
        if c.opset < 12:
            raise c.invalid("select_last_index needs opset >= 12")
        attrs["select_last_index"] = 1
    c.node(op, [c.input()], [c.output()], **attrs)
    c.builder.index_values.add(c.output())
    return [tuple(1 if i == axis else n for i, n in enumerate(x) if keep or i != axis)]


def propose_arg_extreme(d: Draw, x: str) -> Proposal | None:
    rank = len(d.shapes[x])
    if not rank:
        return None
    params: dict = {}
    if d.chance(0.8):
        params["axis"] = d.axis(d.int(0, rank - 1), rank)
    if d.chance(0.5):
        params["keepdims"] = d.pick((0, 1))
    if d.opset >= 12 and d.chance(0.6):
        params["select_last_index"] = d.pick((0, 1, 1))
    return Proposal([x], params)


# --- InstanceNormalization, GroupNormalization, LayerNormalization --------------------------------


def build_instance_norm(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    if len(x) < 3:
        raise c.invalid("InstanceNormalization is generated for [N, C, D1, ...]")
    _check_group(c, math.prod(x[2:]))
    names = _scale_bias(c, (x[1],))
    c.node("InstanceNormalization", [c.input(), *names], [c.output()], **_epsilon(c))
    return [x]


def build_group_norm(c: StepContext) -> list[tuple[int, ...]]:
    x = c.shape()
    groups = int(c.params.get("num_groups", 1))
    if len(x) < 3 or x[1] % groups:
        raise c.invalid(f"{groups} groups do not divide {list(x)}'s channels")
    _check_group(c, x[1] // groups * math.prod(x[2:]))
    names = _scale_bias(c, (x[1],))  # per channel: opset 21's form
    c.node("GroupNormalization", [c.input(), *names], [c.output()], num_groups=groups, **_epsilon(c))
    return [x]


def build_layer_norm(c: StepContext) -> list[tuple[int, ...]]:
    x, p = c.shape(), c.params
    rank = len(x)
    if not rank:
        raise c.invalid("LayerNormalization needs a tensor")
    axis = c.axis(int(p.get("axis", -1)), rank)
    normalised = x[axis:]
    _check_group(c, math.prod(normalised))
    keep = [bool(k) for k in p.get("scale_dims", [True] * len(normalised))][-len(normalised) :]
    scale_shape = tuple(n if k else 1 for n, k in zip(normalised[len(normalised) - len(keep) :], keep))
    names = _scale_bias(c, scale_shape, bias=bool(p.get("bias", True)))
    attrs = _epsilon(c) | ({"axis": int(p["axis"])} if "axis" in p else {})
    outputs = [c.output(i) for i in range(len(c.step.outputs))]
    c.node("LayerNormalization", [c.input(), *names], outputs, **attrs)
    statistics = (*x[:axis], *(1,) * (rank - axis))
    return [x, statistics, statistics][: len(outputs)]


def _check_group(c: StepContext, elements: int) -> None:
    """Normalising one element gives the bias: exactly in NNCG and onnx.reference, but onnxruntime's
    x - mean rounds to some 1e-8, which 1 / sqrt(epsilon) blows up past the tolerance."""
    if elements < 2:
        raise c.invalid("normalises groups of one element")


def _scale_bias(c: StepContext, shape: tuple[int, ...], bias: bool = True) -> list[str]:
    scale = c.rng.uniform(0.5, 1.5, shape).astype(np.float32)
    names = [c.const(scale, role="scale")]
    if bias:
        names.append(c.const(c.rng.normal(0, 0.3, shape).astype(np.float32), role="bias"))
    return names


def _epsilon(c: StepContext) -> dict:
    return {"epsilon": float(c.params["epsilon"])} if "epsilon" in c.params else {}


def _norm_params(d: Draw) -> dict:
    params: dict = {"seed": d.seed()}
    if d.chance(0.4):
        params["epsilon"] = d.pick((1e-5, 1e-3, 0.1))
    return params


def propose_instance_norm(d: Draw, x: str) -> Proposal | None:
    return Proposal([x], _norm_params(d)) if len(d.shapes[x]) >= 3 else None


def propose_group_norm(d: Draw, x: str) -> Proposal | None:
    shape = d.shapes[x]
    if len(shape) < 3:
        return None
    divisors = [g for g in range(1, shape[1] + 1) if shape[1] % g == 0]
    return Proposal([x], _norm_params(d) | {"num_groups": d.pick(divisors)})


def propose_layer_norm(d: Draw, x: str) -> Proposal | None:
    rank = len(d.shapes[x])
    if not rank:
        return None
    params = _norm_params(d)
    if d.chance(0.7):
        params["axis"] = d.axis(d.int(0, rank - 1), rank) if d.chance(0.7) else -1
    axis = params.get("axis", -1) % rank
    count = rank - axis
    if d.chance(0.4):  # scale and bias over the trailing normalised dims, some of them 1
        params["scale_dims"] = [d.chance(0.6) for _ in range(d.int(1, count))]
    if d.chance(0.3):
        params["bias"] = False
    outputs = 3 if d.chance(0.15) else 1  # Mean and InvStdDev too
    return Proposal([x], params, outputs)
