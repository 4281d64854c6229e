"""Backend: the C spelling of the loop-nest IR's leaves (float literals, affine indices), shared by
the printers and the file layer."""

from __future__ import annotations

import numpy as np

from ..errors import NncgError
from ..ir.loops import Affine

INDENT = "    "


def c_float(value: float) -> str:
    """The shortest float32 literal that reads back to the same float32 (C89: no INFINITY macro)."""
    v = np.float32(value)
    if np.isnan(v):
        raise NncgError("the model contains a NaN constant; NNCG cannot print it as a C literal")
    if np.isinf(v):
        return "(-(float)HUGE_VAL)" if v < 0 else "((float)HUGE_VAL)"
    text = np.format_float_positional(v, unique=True, trim="0")
    if len(text) > 12:
        text = np.format_float_scientific(v, unique=True, trim="0")
    return text + "f"


def c_int(value: int) -> str:
    """An integer literal; a negative one in parentheses (x - -1 is not x--1). INT32_MIN has no
    literal in C: -2147483647 - 1."""
    value = int(value)
    if value == -(2**31):
        return "(-2147483647 - 1)"
    return f"({value})" if value < 0 else str(value)


def c_affine(index: Affine) -> str:
    parts = [var if c == 1 else f"{c} * {var}" for var, c in index.terms]
    if index.const or not parts:
        parts.append(str(index.const))
    return " + ".join(parts).replace("+ -", "- ")


def unparen(text: str) -> str:
    """Drops one pair of parentheses that encloses the whole expression."""
    if not (text.startswith("(") and text.endswith(")")):
        return text
    depth = 0
    for i, ch in enumerate(text):
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if depth == 0 and i < len(text) - 1:
            return text
    return text[1:-1]
