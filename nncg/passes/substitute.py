"""Substituting loop variables in the loop-nest IR: the mechanism under unrolling and vectorising."""

from __future__ import annotations

from dataclasses import replace

from ..ir.loops import Affine, Bound, Expr, If, Load, Stmt, Store, map_body, map_stmt_exprs


def substitute_body(body: tuple[Stmt, ...], env: dict[str, Affine]) -> tuple[Stmt, ...]:
    """body with every variable in env replaced; border checks that became constant are resolved."""

    def in_expr(e: Expr) -> Expr:
        return replace(e, index=e.index.substitute(env)) if isinstance(e, Load) else e

    def in_stmt(stmt: Stmt) -> Stmt | tuple[Stmt, ...]:
        stmt = map_stmt_exprs(stmt, in_expr)
        if isinstance(stmt, Store):
            return replace(stmt, index=stmt.index.substitute(env))
        if isinstance(stmt, If):
            return resolve_if(
                replace(stmt, bounds=tuple(Bound(b.expr.substitute(env), b.lo, b.hi) for b in stmt.bounds))
            )
        return stmt

    return map_body(body, in_stmt)


def resolve_if(stmt: If) -> If | tuple[Stmt, ...]:
    """Drops bounds known to hold; the whole statement goes when one is known to fail."""
    known = [b.holds() for b in stmt.bounds]
    if False in known:
        return ()
    remaining = tuple(b for b, k in zip(stmt.bounds, known) if k is None)
    return replace(stmt, bounds=remaining) if remaining else stmt.body
