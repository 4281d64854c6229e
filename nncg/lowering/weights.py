"""Weight operands of Conv, ConvTranspose and Dense, constant or computed at runtime.

A lowering names the logical dims it reads a weight in as a view of the ONNX-shaped tensor
(`permuted`, `split`). A constant weight is packed in that order, row-major, so the innermost
dim (output channels) is contiguous and vectorises; a runtime weight (a graph input or computed)
is read in place through the same view, a strided TensorRef over the caller's buffer. The loop
nest is the same in both cases; only the strides differ."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..ir.loops import Affine, Loop, Stmt
from .context import LoweringContext, TensorRef, row_major

View = Callable[[TensorRef], TensorRef]


def permuted(ref: TensorRef, perm: tuple[int, ...]) -> TensorRef:
    """The same memory with logical dim j being dim perm[j] of ref."""
    shape = tuple(ref.shape[d] for d in perm)
    order = tuple(perm.index(d) for d in ref.order)
    return TensorRef(ref.buffer, shape, order)


def split(ref: TensorRef, dim: int, outer: int) -> TensorRef:
    """The same memory with dim `dim` split into (outer, shape[dim] // outer), outer first."""
    inner = ref.shape[dim] // outer
    shape = (*ref.shape[:dim], outer, inner, *ref.shape[dim + 1 :])
    order: list[int] = []
    for d in ref.order:  # the halves stay adjacent in memory, outer before inner
        order += [dim, dim + 1] if d == dim else [d + (d > dim)]
    return TensorRef(ref.buffer, shape, tuple(order))


def weight_operand(ctx: LoweringContext, value: str, name: str, view: View = lambda ref: ref) -> TensorRef:
    """`value` as the loop nest reads it: logical dims view(ONNX-shaped ref). A constant becomes
    a packed array `name` in that order; a runtime value is viewed where it lives."""
    if not ctx.graph.is_constant(value):
        return view(ctx.ref(value))
    data = np.ascontiguousarray(ctx.graph.constants[value], dtype=np.float32)
    layout = view(TensorRef("", data.shape, row_major(data.ndim)))
    strides = tuple(s * data.itemsize for s in layout.strides)
    return ctx.add_constant(name, np.lib.stride_tricks.as_strided(data, layout.shape, strides))


def by_panels(
    ctx: LoweringContext,
    name: str,
    columns: int,
    panel: int,
    pack: Callable[[int, int, int], np.ndarray],
    nests: Callable[[TensorRef, Affine, Affine, int], tuple[Stmt, ...]],
) -> tuple[Stmt, ...]:
    """A layer computed `panel` output columns at a time (the cache-block pass chose it): the full
    panels in a loop `p` over one packed array `name`, then the rest from `name_rest`.
    pack(start, stop, panels) packs columns [start, stop) as that many panels; nests(w, panel index,
    first column, width) are one panel's nests."""
    full, rest = divmod(columns, panel)
    body: list[Stmt] = []
    if full:
        w = ctx.add_constant(name, pack(0, full * panel, full))
        p = Affine.of("p") if full > 1 else Affine()
        stmts = nests(w, p, p * panel, panel)
        # Serial: the panels share no data, but register-block would jam panels, not pixels or rows.
        body += [Loop("p", full, stmts)] if full > 1 else list(stmts)
    if rest:
        w = ctx.add_constant(f"{name}_rest", pack(full * panel, columns, 1))
        body += nests(w, Affine(), Affine.of(full * panel), rest)
    return tuple(body)
