"""Per-layer pass parameters, `layers=conv1:4x2;conv2:3x3`: how a pipeline records what `--tune`
chose for each layer (register-block's block shapes, unroll's budgets)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from ..errors import NncgError
from ..ir.loops import Program

T = TypeVar("T")


def parse_layer_map(text: str, parse_value: Callable[[str], T], example: str) -> dict[str, T]:
    """`a:V;b:W` -> {"a": parse_value("V"), "b": parse_value("W")}; ValueError names the bad item."""
    out = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        name, sep, value = item.partition(":")
        try:
            if not sep or not name:
                raise ValueError("no LAYER:VALUE")
            out[name] = parse_value(value)
        except ValueError as exc:
            raise ValueError(f"'{item}' is not LAYER:VALUE as in {example} ({exc})") from None
    return out


def format_layer_map(values: dict[str, T], format_value: Callable[[T], str] = str) -> str:
    return ";".join(f"{name}:{format_value(value)}" for name, value in sorted(values.items()))


def check_layer_names(program: Program, layers: dict, pass_name: str) -> None:
    """A per-layer choice for a layer the program does not have is a typo: say which layers there are."""
    unknown = sorted(set(layers) - {k.name for k in program.kernels})
    if unknown:
        names = ", ".join(k.name for k in program.kernels)
        raise NncgError(f"{pass_name}: no layer named {', '.join(unknown)}; the layers are: {names}")
