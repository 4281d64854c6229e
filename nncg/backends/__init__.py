"""Backends print the loop-nest IR as C for one target; each is a class registered by name."""

from __future__ import annotations

from ..errors import NncgError
from ..ir.target import Target
from .avx import Avx2, Avx512
from .c import AnsiC
from .neon import Neon
from .ssse3 import Ssse3

BACKENDS: dict[str, type[AnsiC]] = {cls.name: cls for cls in (AnsiC, Ssse3, Avx2, Avx512, Neon)}


def get_target(name: str) -> Target:
    """The hardware facts of the target `name`, for PassManager(pipeline, target=...)."""
    return get_backend(name).target


def get_backend(name: str) -> AnsiC:
    try:
        return BACKENDS[name]()
    except KeyError:
        raise NncgError(f"unknown target '{name}'; targets: {', '.join(BACKENDS)}") from None
