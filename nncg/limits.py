"""The sizes the generated C can address. It indexes every tensor, the arena and the weights blob
with `int` (32 bits on every target NNCG supports) and declares static arrays, so no tensor, arena
or blob may need an element count or byte offset above INT32_MAX: such a model is refused here,
never printed as C whose index arithmetic overflows."""

from __future__ import annotations

import math

from .errors import NncgError
from .ir.loops import Program

INT32_MAX = 2**31 - 1
FLOAT_BYTES = 4
SHAPE_HINT = "give a smaller --input-shape (input_shapes in Python)"


def tensor_size_problem(shape: tuple[int, ...], itemsize: int = FLOAT_BYTES) -> str | None:
    """Why a tensor of `shape` does not fit int indexing, or None when it does."""
    elements = math.prod(shape)
    if elements <= INT32_MAX and elements * itemsize <= INT32_MAX:
        return None
    return (
        f"{elements:,} elements ({_bytes(elements * itemsize)}); the generated C indexes with 32-bit int, so a "
        f"tensor may have at most {INT32_MAX // itemsize:,} elements of {itemsize} bytes"
    )


def check_tensor_size(what: str, shape: tuple[int, ...], hint: str = SHAPE_HINT, itemsize: int = FLOAT_BYTES) -> None:
    """Refuse a tensor (`what` names it, e.g. "input 'x'") too large for int indexing."""
    problem = tensor_size_problem(tuple(shape), itemsize)
    if problem:
        raise NncgError(f"{what} of shape {list(shape)} has {problem}: {hint}")


def check_program_limits(program: Program) -> None:
    """The planned program fits int offsets: the arena (activations), the weights blob and every
    buffer, in elements and in bytes. Run on the program after plan-memory, before printing C."""
    if program.arena is not None:
        for what, floats in (
            ("activation arena", program.arena.floats),
            ("weights blob", program.arena.weights_floats),
        ):
            if floats * FLOAT_BYTES > INT32_MAX:
                raise NncgError(
                    f"the model needs a {what} of {_bytes(floats * FLOAT_BYTES)}, more than the {INT32_MAX:,} bytes "
                    f"32-bit int offsets in the generated C reach: {SHAPE_HINT}, or split the model"
                )
    for buf in program.buffers:
        end = buf.size + (buf.offset or 0)
        if end * FLOAT_BYTES > INT32_MAX:
            raise NncgError(
                f"buffer {buf.name} ({buf.role}, {buf.size:,} floats at offset {buf.offset or 0:,}) ends at "
                f"byte {_bytes(end * FLOAT_BYTES)}, beyond the 32-bit int offsets of the generated C: {SHAPE_HINT}"
            )


def _bytes(count: int) -> str:
    for unit, size in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if count >= size:
            return f"{count / size:.1f} {unit}"
    return f"{count} bytes"
