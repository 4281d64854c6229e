"""Per-layer pass parameters, `layers=conv1:4x2;conv2:3x3`: how a pipeline records what `--tune`
chose for each layer (register-block's block shapes, unroll's budgets, winograd's choices)."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import TypeVar

from ..errors import NncgError
from ..ir.graph import Graph
from ..ir.loops import Program

T = TypeVar("T")
LAYER_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def parse_layer_map(text: str, parse_value: Callable[[str], T], example: str) -> dict[str, T]:
    """`a:V;b:W` -> {"a": parse_value("V"), "b": parse_value("W")}; ValueError names the bad item."""
    out = {}
    for item in filter(None, (part.strip() for part in text.split(";"))):
        name, sep, value = item.partition(":")
        try:
            if not sep or not name:
                raise ValueError("no LAYER:VALUE")
            if not LAYER_NAME.fullmatch(name):
                raise ValueError("a layer name is a C identifier, as --print-ir-after-all shows it")
            out[name] = parse_value(value)
        except ValueError as exc:
            raise ValueError(f"'{item}' is not LAYER:VALUE as in {example} ({exc})") from None
    return out


def format_layer_map(values: dict[str, T], format_value: Callable[[T], str] = str) -> str:
    return ";".join(f"{name}:{format_value(value)}" for name, value in sorted(values.items()))


def check_layer_names(ir: Program | Graph, layers: dict, pass_name: str) -> None:
    """A per-layer choice for a layer the IR does not have is a typo: say which layers there are
    (kernels of a loop-nest program, nodes of a graph)."""
    known = [k.name for k in ir.kernels] if isinstance(ir, Program) else [n.name for n in ir.nodes]
    unknown = sorted(set(layers) - set(known))
    if unknown:
        names = ", ".join(known)
        raise NncgError(f"{pass_name}: no layer named {', '.join(unknown)}; the layers are: {names}")
