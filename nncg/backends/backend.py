"""Backend: a target as `emit` sees it — the hardware facts and compiler flags of its printer, and
the .c and .h it prints for a program, legalised for the target first."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ..ir.loops import Program
from ..ir.target import Target
from . import c_file, c_header
from .legalize import fuse_multiply_add
from .scalar import ScalarPrinter


@dataclass(frozen=True)
class Backend:
    printer: ScalarPrinter

    @property
    def target(self) -> Target:
        return self.printer.target

    @property
    def name(self) -> str:
        return self.target.name

    @property
    def vector_widths(self) -> tuple[int, ...]:
        """The vector widths the printer has, widest first; () for scalar C."""
        return self.target.vector_widths

    @property
    def lanes(self) -> int:
        """The widest vector width: 1 for scalar C."""
        return self.target.lanes

    @property
    def registers(self) -> int:
        """Vector (or float) registers, for register blocking."""
        return self.target.registers

    @property
    def cflags(self) -> tuple[str, ...]:
        return self.printer.cflags

    @property
    def strict_cflags(self) -> tuple[str, ...]:
        return self.printer.strict_cflags

    def source(self, program: Program, first_line: str, header_name: str, profile: bool = False) -> str:
        """The .c file. `profile` adds per-layer timers (POSIX clock_gettime; for --profile only)."""
        program = fuse_multiply_add(program, self.target)
        return c_file.source(self.printer, program, first_line, header_name, profile)

    def header(
        self,
        program: Program,
        first_line: str,
        input_layout: str | None = None,
        io_quantization: Mapping[str, tuple[float, int]] | None = None,
    ) -> str:
        """The .h file; `input_layout` (nchw, nhwc) is what its comments say of the 4-D inputs;
        `io_quantization` the scale and zero point of integer inputs and outputs (by ONNX name)."""
        return c_header.header(program, first_line, input_layout, io_quantization)
