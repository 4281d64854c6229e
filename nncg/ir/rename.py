"""Renaming and substituting loop variables in the loop-nest IR: used by loop passes (register
blocking suffixes locals, unrolling and vectorising substitute), by the band lowering (a layer's
rows become a band's) and by the C file layer (locals that would shadow a buffer's pointer)."""

from __future__ import annotations

from dataclasses import replace

from .loops import Affine, Assign, Bound, Expr, If, Let, Load, LocalRef, Loop, Stmt, Store, map_body, map_stmt_exprs


def rename_variables(body: tuple[Stmt, ...], names: dict[str, str]) -> tuple[Stmt, ...]:
    """body with loop variables and locals renamed (old -> new); nothing else changes."""
    env = {old: Affine.of(new) for old, new in names.items()}

    def in_expr(e: Expr) -> Expr:
        if isinstance(e, Load):
            return replace(e, index=e.index.substitute(env))
        if isinstance(e, LocalRef):
            return replace(e, name=names.get(e.name, e.name))
        return e

    def in_stmt(stmt: Stmt) -> Stmt:
        stmt = map_stmt_exprs(stmt, in_expr)
        if isinstance(stmt, Store):
            return replace(stmt, index=stmt.index.substitute(env))
        if isinstance(stmt, If):
            return replace(stmt, bounds=tuple(Bound(b.expr.substitute(env), b.lo, b.hi) for b in stmt.bounds))
        if isinstance(stmt, Loop):
            return replace(stmt, var=names.get(stmt.var, stmt.var))
        if isinstance(stmt, Let | Assign):
            return replace(stmt, name=names.get(stmt.name, stmt.name))
        return stmt

    return map_body(body, in_stmt)


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
