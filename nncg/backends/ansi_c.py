"""Backend: strict C89 plus math.h, scalar code (conditional moves for max/min/select): the scalar
printer with nothing added."""

from __future__ import annotations

from ..ir.target import Target
from .scalar import ScalarPrinter


class AnsiC(ScalarPrinter):
    target = Target("ansi-c", vector_widths=(), registers=16, fma=False)
    cflags = ()
    strict_cflags = ("-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror")
    includes = ("<math.h>",)
