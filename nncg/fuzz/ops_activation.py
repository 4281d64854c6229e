"""Pointwise ops for the generator beyond the `Unary` kind: one step kind per ONNX op (Abs, Neg, Exp,
Log, Sqrt, Reciprocal, Erf, Softplus, Softsign, Mish, Selu, Celu, ThresholdedRelu, Gelu) and Pow by a
constant exponent. Ops defined on part of the line only (Log, Sqrt, Reciprocal, Pow by a fractional
or negative exponent) read their input made positive first (`positive`), so a NaN or an infinity
never stands for a mismatch."""

from __future__ import annotations

import numpy as np

from .build import StepContext
from .draw import Draw, Proposal, broadcastable_to

ACTIVATIONS = (
    "Abs", "Neg", "Exp", "Log", "Sqrt", "Reciprocal", "Erf", "Softplus", "Softsign", "Mish", "Selu", "Celu",
    "ThresholdedRelu", "Gelu",
)  # fmt: skip
WEIGHTS = {"Gelu": 0.8, "Mish": 0.3}  # ops of newer opsets more often: fewer graphs have those opsets
MIN_OPSET = {"Erf": 9, "ThresholdedRelu": 10, "Celu": 12, "Mish": 18, "Gelu": 20}
POSITIVE_ONLY = ("Log", "Sqrt", "Reciprocal")
# How a value is made positive: each keeps it at least `floor` (a constant added) away from zero.
POSITIVE_FORMS = ("abs", "square", "sigmoid", "softplus", "exp_tanh")
POW_EXPONENTS = (2.0, 3.0, 0.5, -1.0, 1.0, 0.0, -2.0, 1.5, -0.5, 0.3, 4.0)


def build_activation(c: StepContext, op: str) -> list[tuple[int, ...]]:
    p = c.params
    x = positive(c, p["positive"], float(p.get("floor", 0.1))) if "positive" in p else c.input()
    if op == "Exp" and p.get("bounded"):  # 3 * tanh(x): exp stays in (0.05, 20)
        squashed, scaled = c.temp(), c.temp()
        c.node("Tanh", [x], [squashed])
        c.node("Mul", [squashed, c.const(np.float32(3.0), role="three")], [scaled])
        x = scaled
    attrs = {k: float(p[k]) for k in ("alpha", "gamma") if k in p}
    if op == "Gelu" and "approximate" in p:
        attrs["approximate"] = p["approximate"]
    c.node(op, [x], [c.output()], **attrs)
    return [c.shape()]


def propose_activation(d: Draw, x: str, op: str) -> Proposal:
    params: dict = {}
    if op in POSITIVE_ONLY:
        params.update(positive_params(d))
    if op == "Exp":
        params["bounded"] = d.chance(0.6)
    if op in ("Selu", "Celu", "ThresholdedRelu") and d.chance(0.6):
        params["alpha"] = d.pick({"Selu": (1.0, 1.5, 1.67326), "Celu": (0.5, 1.0, 2.0)}.get(op, (0.0, 0.5, 1.0, -0.5)))
    if op == "Selu" and d.chance(0.5):
        params["gamma"] = d.pick((1.0, 1.0507, 2.0))
    if op == "Gelu" and d.chance(0.7):
        params["approximate"] = d.pick(("none", "tanh", "tanh"))
    return Proposal([x], params)


def positive_params(d: Draw) -> dict:
    return {"positive": d.pick(POSITIVE_FORMS), "floor": d.pick((0.1, 0.5, 1.0))}


def positive(c: StepContext, form: str, floor: float) -> str:
    """The step's input made positive (at least `floor`): |x|, x * x, sigmoid(x), softplus(x) or
    exp(tanh(x)), plus the floor. The ops are those a model would have in front (a norm's variance,
    a distance)."""
    x, made = c.input(), c.temp()
    if form == "abs":
        c.node("Abs", [x], [made])
    elif form == "square":
        c.node("Mul", [x, x], [made])
    elif form == "sigmoid":
        c.node("Sigmoid", [x], [made])
    elif form == "softplus":
        c.node("Softplus", [x], [made])
    elif form == "exp_tanh":
        squashed = c.temp()
        c.node("Tanh", [x], [squashed])
        c.node("Exp", [squashed], [made])
    else:
        raise c.invalid(f"no positive form {form!r}")
    shifted = c.temp()
    c.node("Add", [made, c.const(np.float32(floor), role="floor")], [shifted])
    return shifted


# --- Pow --------------------------------------------------------------------------------------------


def build_pow(c: StepContext) -> list[tuple[int, ...]]:
    p, x_shape = c.params, c.shape()
    if "exponents" in p:
        exponent = np.asarray(p["exponents"], dtype=np.float32)
        if tuple(np.broadcast_shapes(exponent.shape, x_shape)) != x_shape:
            raise c.invalid(f"exponent {list(exponent.shape)} does not broadcast to {list(x_shape)}")
    else:
        exponent = np.float32(p.get("exponent", 2.0))
    needs_positive = bool(np.any((exponent != np.round(exponent)) | (exponent < 0)))
    if needs_positive and "positive" not in p:
        raise c.invalid("a fractional or negative exponent needs a positive base")
    x = positive(c, p["positive"], float(p.get("floor", 0.1))) if "positive" in p else c.input()
    c.node("Pow", [x, c.const(exponent, role="exponent")], [c.output()])
    return [x_shape]


def propose_pow(d: Draw, x: str) -> Proposal:
    shape = d.shapes[x]
    params: dict = {}
    if shape and d.chance(0.3):  # an exponent per element (or per broadcast slice)
        exponent_shape = broadcastable_to(d, shape)
        exponents = d.rng.choice(POW_EXPONENTS, size=exponent_shape)
        params["exponents"] = exponents.tolist()
    else:
        params["exponent"] = float(d.pick(POW_EXPONENTS))
        exponents = np.asarray([params["exponent"]])
    if np.any((exponents != np.round(exponents)) | (exponents < 0)) or d.chance(0.2):
        params.update(positive_params(d))
    return Proposal([x], params)
