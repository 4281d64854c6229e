"""Which buffers may share arena memory, whatever their lifetimes, and the typed regions that follows.

C's aliasing rule (C89 3.3, C99 6.5p7): an object is read or written only through its own type or a
character type. The arena holds float32, int16 and int32 buffers, so its memory is cut into regions
of one element type each: a float, an int16 and an int32 buffer never share a byte, even when their
lifetimes are disjoint (the compiler may move a float store past an int32 load of the same address).
int8 and uint8 buffers are read and written through character types, which may access any object,
so they reuse the memory of any region. The static arena is declared as a struct of one array per
region (c_file.py), so every typed access is to an object of its own type: defined C for every
compiler, at -O2 with strict aliasing too, and no slower than one float array (the pointers are the
same constant offsets)."""

from __future__ import annotations

from dataclasses import dataclass

from .kinds import BufferRole, DType

ARENA_DTYPES = (DType.FLOAT32, DType.INT8, DType.UINT8, DType.INT16, DType.INT32)  # what an arena buffer may hold
CHARACTER_DTYPES = (DType.INT8, DType.UINT8)  # C character types: may access any object


def kept_apart(a: DType, b: DType) -> bool:
    """Whether buffers of these dtypes may never share memory (two different non-character types)."""
    return a != b and a not in CHARACTER_DTYPES and b not in CHARACTER_DTYPES


@dataclass(frozen=True)
class Region:
    """`floats` float32 slots of the arena, from `start`, accessed as `dtype` only (character types aside)."""

    dtype: DType
    start: int
    floats: int


def arena_regions(program) -> tuple[Region, ...]:
    """The arena cut into maximal runs of one element type, in address order, covering all of it. A
    stretch only character buffers use (or none) goes to float32, the arena's type before int16 and
    int32 buffers came."""
    typed = sorted(
        (b.offset, b.offset + b.floats, b.dtype)
        for b in program.role(BufferRole.INTERNAL)
        if b.offset is not None and b.dtype not in CHARACTER_DTYPES and b.floats
    )
    regions: list[Region] = []

    def extend(dtype: DType, start: int, end: int) -> None:
        last = regions[-1] if regions else None
        if last is not None and last.dtype == dtype and last.start + last.floats >= start:
            regions[-1] = Region(dtype, last.start, max(last.start + last.floats, end) - last.start)
        elif end > start:
            regions.append(Region(dtype, start, end - start))

    for start, end, dtype in typed:
        covered = regions[-1].start + regions[-1].floats if regions else 0
        extend(DType.FLOAT32, covered, start)
        extend(dtype, start, end)
    covered = regions[-1].start + regions[-1].floats if regions else 0
    extend(DType.FLOAT32, covered, program.arena.floats)
    return tuple(regions)


def typed_arena(program) -> bool:
    """Whether the arena has int16 or int32 regions besides float ones (then it is not a float array)."""
    return any(r.dtype != DType.FLOAT32 for r in arena_regions(program))


def sharing_problems(program) -> list[str]:
    """Pairs of internal buffers whose dtypes are kept apart but whose arena memory overlaps."""
    placed = sorted(
        (b.offset, b.offset + b.floats, b.name, b.dtype)
        for b in program.role(BufferRole.INTERNAL)
        if b.offset is not None and b.dtype not in CHARACTER_DTYPES and b.floats
    )
    problems = []
    for i, (_, end, name, dtype) in enumerate(placed):
        for other_start, _, other, other_dtype in placed[i + 1 :]:
            if other_start >= end:
                break
            if kept_apart(dtype, other_dtype):
                problems.append(f"{dtype} buffer {name} and {other_dtype} buffer {other} share arena memory")
    return problems
