"""Backends print the loop-nest IR as C for one target. A target is a printer class with a `target`
attribute in a module of this package, found by scanning it: a new ISA is one new file."""

from __future__ import annotations

import importlib
import pkgutil

from ..errors import NncgError
from ..ir.target import Target
from .backend import Backend
from .scalar import ScalarPrinter


def _printers() -> dict[str, type[ScalarPrinter]]:
    """The printer classes that declare a target, by target name (sorted)."""
    found = {}
    for module_info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{module_info.name}")
        for cls in vars(module).values():
            if isinstance(cls, type) and issubclass(cls, ScalarPrinter) and "target" in vars(cls):
                found[cls.target.name] = cls
    return dict(sorted(found.items()))


BACKENDS: dict[str, type[ScalarPrinter]] = _printers()


def get_target(name: str) -> Target:
    """The hardware facts of the target `name`, for PassManager(pipeline, target=...)."""
    return get_backend(name).target


def get_backend(name: str) -> Backend:
    try:
        return Backend(BACKENDS[name]())
    except KeyError:
        raise NncgError(f"unknown target '{name}'; targets: {', '.join(BACKENDS)}") from None
