"""Loop pass `plan-memory{align=N,weights=auto|embed|bin}`: places activations and weights.

Weights stay `static const` arrays in the C file (embed) or move into one binary blob, NAME.weights,
that the caller passes by pointer (bin); auto picks bin above WEIGHTS_FILE_THRESHOLD bytes, where
the C literals would make the source slow to compile. Either way each array is aligned.

Every internal activation buffer goes into one arena, counted in floats: an int8 buffer takes a
quarter of the floats its elements would (Buffer.floats). Float32, int16 and int32 buffers never share
memory, whatever their lifetimes (C's aliasing rule, ir/arena.py); int8 and uint8 ones share any.

A buffer lives from the first kernel that touches it to the last (a Reshape alias shares its
buffer, so later readers extend the lifetime). Buffers whose lifetimes do not overlap share memory:
largest first, each goes to the lowest aligned offset that is free of every buffer live at the same
time (the greedy-by-size placement of TFLite's arena planner). Before that, an elementwise kernel
whose input dies there computes in place: its output buffer is renamed to the input's, so the two
never need separate memory and no kernel ever sees two overlapping pointers."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..errors import NncgError
from ..ir.arena import kept_apart
from ..ir.kinds import BufferRole, DType
from ..ir.loops import (
    ArenaPlan,
    Buffer,
    Kernel,
    Load,
    Program,
    Store,
    map_body,
    map_stmt_exprs,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)

FLOAT_BYTES = 4
WEIGHTS_FILE_THRESHOLD = 4 << 20
WEIGHTS_MODES = ("auto", "embed", "bin")


def plan_memory(program: Program, align: int = 64, reuse: bool = True, weights: str = "auto") -> Program:
    """`align` is in bytes; `reuse=False` lays the buffers out back to back (no sharing)."""
    align_floats = max(1, align // FLOAT_BYTES)
    activation_floats = sum(b.floats for b in program.role(BufferRole.INTERNAL))
    if reuse:
        program = _compute_in_place(program)
    offsets, size = _place(program, align_floats, reuse)
    weights_floats = 0
    if _weights_in_blob(program, weights):
        constants = list(program.role(BufferRole.CONSTANT))
        constant_offsets, weights_floats = _back_to_back(constants, align_floats)
        offsets.update(constant_offsets)
    buffers = tuple(replace(b, offset=offsets[b.name]) if b.name in offsets else b for b in program.buffers)
    arena = ArenaPlan(size, activation_floats, align_floats, weights_floats)
    return replace(program, buffers=buffers, arena=arena)


def _weights_in_blob(program: Program, mode: str) -> bool:
    """The blob is float32 words: integer weights (the int8 path) stay in the C file."""
    integer = any(b.dtype != DType.FLOAT32 for b in program.role(BufferRole.CONSTANT))
    if mode == "auto":
        return (
            not integer
            and sum(b.floats for b in program.role(BufferRole.CONSTANT)) * FLOAT_BYTES > WEIGHTS_FILE_THRESHOLD
        )
    if mode == "bin" and integer:
        raise NncgError("--weights bin takes float weights only; an int8 model keeps its weights in the C file (embed)")
    return mode == "bin"


def parse_weights(text: str) -> str:
    if text not in WEIGHTS_MODES:
        raise ValueError(f"weights is one of {', '.join(WEIGHTS_MODES)}")
    return text


def format_bool(value: bool) -> str:
    return "true" if value else "false"


def parse_bool(text: str) -> bool:
    """A boolean parameter: true or false."""
    if text not in ("true", "false"):
        raise ValueError("the value is true or false")
    return text == "true"


def parse_align(text: str) -> int:
    align = int(text)
    if align < FLOAT_BYTES or align & (align - 1):
        raise ValueError("align is a power of two >= 4 (bytes)")
    return align


# ---------------------------------------------------------------------------- lifetimes


@dataclass(frozen=True)
class Access:
    """The buffers one kernel reads and writes."""

    reads: frozenset[str]
    writes: frozenset[str]

    @property
    def touched(self) -> frozenset[str]:
        return self.reads | self.writes

    def renamed(self, old: str, new: str) -> Access:
        def swap(names: frozenset[str]) -> frozenset[str]:
            return frozenset(new if n == old else n for n in names)

        return Access(swap(self.reads), swap(self.writes))


def kernel_access(kernel: Kernel) -> Access:
    stmts = list(walk_stmts(kernel.body))
    reads = {e.buffer for s in stmts for top in stmt_exprs(s) for e in walk_exprs(top) if isinstance(e, Load)}
    writes = {s.buffer for s in stmts if isinstance(s, Store)}
    return Access(frozenset(reads), frozenset(writes))


def lifetimes(program: Program, accesses: list[Access] | None = None) -> dict[str, tuple[int, int]]:
    """Internal buffer -> (first, last) index of the kernels that touch it."""
    internal = {b.name for b in program.role(BufferRole.INTERNAL)}
    spans: dict[str, tuple[int, int]] = {}
    for i, access in enumerate(accesses or [kernel_access(k) for k in program.kernels]):
        for name in access.touched & internal:
            first, _ = spans.get(name, (i, i))
            spans[name] = (first, i)
    return spans


# ---------------------------------------------------------------------------- in place


def _compute_in_place(program: Program) -> Program:
    """Renames each elementwise kernel's output to its dying input, kernel by kernel."""
    accesses = [kernel_access(k) for k in program.kernels]
    spans = lifetimes(program, accesses)
    sizes = {b.name: (b.size, b.dtype) for b in program.role(BufferRole.INTERNAL)}
    renames: dict[str, str] = {}
    for i, kernel in enumerate(program.kernels):
        pair = _in_place_pair(kernel, i, accesses[i], spans, sizes, renames)
        if pair is None:
            continue
        out, src = pair
        renames[out] = src
        spans[src] = (spans[src][0], spans.pop(out)[1])
        accesses[i:] = [a.renamed(out, src) for a in accesses[i:]]
    return _rename(program, renames) if renames else program


def _in_place_pair(kernel, index, access, spans, sizes, renames) -> tuple[str, str] | None:
    """(output, input) when the output can take the input's memory: both internal, of one size and dtype,
    the input dead after this kernel, the output born in it, and the kernel elementwise between them.
    `access` and `spans` use the new names; the kernel body still has the original ones."""
    if kernel.overlapping_stores:
        return None
    for out in sorted(access.writes & spans.keys()):
        if spans[out][0] != index or out in access.reads:
            continue
        for src in sorted(access.reads & spans.keys()):
            if spans[src][1] == index and sizes[src] == sizes[out] and _elementwise(kernel, src, out, renames):
                return out, src
    return None


def _resolve(name: str, renames: dict[str, str]) -> str:
    while name in renames:
        name = renames[name]
    return name


def _elementwise(kernel: Kernel, src: str, out: str, renames: dict[str, str]) -> bool:
    """Every read of src is inside a store to out at the same index and width: each element of src
    is read only by the statement that overwrites it (the kernel writes each element once)."""
    for stmt in walk_stmts(kernel.body):
        for top in stmt_exprs(stmt):
            for e in walk_exprs(top):
                if isinstance(e, Load) and _resolve(e.buffer, renames) == src:
                    same_element = (
                        isinstance(stmt, Store)
                        and stmt.buffer == out
                        and stmt.index == e.index
                        and e.lanes == stmt.value.lanes
                    )
                    if not same_element:
                        return False
    return True


def _rename(program: Program, renames: dict[str, str]) -> Program:
    def rename_expr(e):
        return replace(e, buffer=_resolve(e.buffer, renames)) if isinstance(e, Load) else e

    def rename_stmt(s):
        s = map_stmt_exprs(s, rename_expr)
        return replace(s, buffer=_resolve(s.buffer, renames)) if isinstance(s, Store) else s

    kernels = tuple(replace(k, body=map_body(k.body, rename_stmt)) for k in program.kernels)
    buffers = tuple(b for b in program.buffers if b.name not in renames)
    values = tuple(replace(v, buffer=_resolve(v.buffer, renames)) for v in program.values)
    return replace(program, kernels=kernels, buffers=buffers, values=values)


# ---------------------------------------------------------------------------- placement


def _place(program: Program, align: int, reuse: bool) -> tuple[dict[str, int], int]:
    """Buffer -> offset (floats) and the arena size, both multiples of `align`."""
    spans = lifetimes(program)
    internal = [b for b in program.role(BufferRole.INTERNAL) if b.name in spans]
    if not reuse:
        return _back_to_back(internal, align)
    order = sorted(internal, key=lambda b: (-b.floats, spans[b.name][0], b.name))
    placed: list[tuple[int, int, Buffer]] = []  # (offset, end, buffer)
    offsets: dict[str, int] = {}
    for buf in order:
        first, last = spans[buf.name]
        busy = sorted(
            (start, end)
            for start, end, other in placed
            if spans[other.name][0] <= last and first <= spans[other.name][1] or kept_apart(buf.dtype, other.dtype)
        )
        offset = 0
        for start, end in busy:
            if offset + buf.floats <= start:
                break
            offset = max(offset, _round_up(end, align))
        offsets[buf.name] = offset
        placed.append((offset, offset + buf.floats, buf))
    size = max((_round_up(end, align) for _, end, _ in placed), default=0)
    return offsets, size


def _back_to_back(buffers: list[Buffer], align: int) -> tuple[dict[str, int], int]:
    offsets, offset = {}, 0
    for buf in buffers:
        offsets[buf.name] = offset
        offset += _round_up(buf.floats, align)
    return offsets, offset


def _round_up(n: int, align: int) -> int:
    return -(-n // align) * align
