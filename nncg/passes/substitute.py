"""Splitting loops at their border checks: the mechanism under unrolling, vectorising and register
blocking (substituting a variable itself is nncg/ir/rename.py's)."""

from __future__ import annotations

from dataclasses import replace

from ..ir.loops import Affine, Bound, If, Let, Loop, Stmt, walk_stmts
from ..ir.rename import resolve_if, substitute_body


def prune_bounds(body: tuple[Stmt, ...], extents: dict[str, int] | None = None) -> tuple[Stmt, ...]:
    """Drops border checks that hold for every value the enclosing loops give their variables, and
    the guarded code that can never run."""
    extents = extents or {}
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop):
            out.append(replace(stmt, body=prune_bounds(stmt.body, extents | {stmt.var: stmt.extent})))
        elif isinstance(stmt, Let):
            out.append(replace(stmt, body=prune_bounds(stmt.body, extents)))
        elif isinstance(stmt, If):
            bounds = tuple(_needed_sides(b, extents) for b in stmt.bounds)
            if None in bounds:
                continue
            pruned = replace(stmt, bounds=tuple(b for b in bounds if b.lo is not None or b.hi is not None))
            resolved = resolve_if(pruned)
            inner = resolved.body if isinstance(resolved, If) else resolved
            inner = prune_bounds(inner, extents)
            out.extend((replace(resolved, body=inner),) if isinstance(resolved, If) else inner)
        else:
            out.append(stmt)
    return tuple(out)


def _needed_sides(bound: Bound, extents: dict[str, int]) -> Bound | None:
    """The bound without the sides that always hold; None when it can never hold."""
    if any(var not in extents for var in bound.expr.vars):
        return bound
    lo, hi = bound.expr.bounds(extents)
    if (bound.lo is not None and hi < bound.lo) or (bound.hi is not None and lo >= bound.hi):
        return None
    return Bound(
        bound.expr,
        None if bound.lo is None or lo >= bound.lo else bound.lo,
        None if bound.hi is None or hi < bound.hi else bound.hi,
    )


def interior(loop: Loop) -> tuple[int, int]:
    """[first, last) iterations of `loop` for which every border check that depends on its variable
    holds whatever the inner loops' variables are; (0, 0) if a check also depends on outer loops."""
    first, last = 0, loop.extent
    extents = {s.var: s.extent for s in walk_stmts(loop.body) if isinstance(s, Loop)}
    for stmt in walk_stmts(loop.body):
        if not isinstance(stmt, If):
            continue
        for bound in stmt.bounds:
            step = bound.expr.coeff(loop.var)
            if not step:
                continue
            rest = bound.expr - Affine.of(loop.var) * step
            if step < 0 or any(v not in extents for v in rest.vars):
                return 0, 0
            lo, hi = rest.bounds(extents)
            if bound.lo is not None:  # step*i + lo >= bound.lo
                first = max(first, -((lo - bound.lo) // step))
            if bound.hi is not None:  # step*i + hi < bound.hi
                last = min(last, (bound.hi - 1 - hi) // step + 1)
    return first, max(first, last)


def iterations(loop: Loop, start: int, stop: int, prune: bool = False) -> tuple[Stmt, ...]:
    """Iterations [start, stop) of loop, as a loop (or straight code for one iteration); with
    `prune`, their border checks are known to hold and are dropped."""
    count = stop - start
    if count <= 0:
        return ()
    if count == 1:
        body = substitute_body(loop.body, {loop.var: Affine.of(start)})
        return prune_bounds(body) if prune else body
    body = substitute_body(loop.body, {loop.var: Affine.of(loop.var) + start})
    body = prune_bounds(body, {loop.var: count}) if prune else body
    return (replace(loop, extent=count, body=body),)
