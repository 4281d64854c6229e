"""Fresh names for graph values and nodes, shared by the ONNX front end and the graph passes.
(C identifiers have their own rules: nncg/ir/c_names.py.)"""

from __future__ import annotations

from collections.abc import Container


def fresh_name(base: str, *taken: Container[str]) -> str:
    """`base`, or `base_1`, `base_2`, ...: the first name that none of the `taken` collections holds."""
    name, k = base, 0
    while any(name in names for names in taken):
        k += 1
        name = f"{base}_{k}"
    return name
