"""Loop pass `unroll{level=K,budget=N,total=M,layers=NAME:N;...}`: the paper's unroll levels (principle 1).

Level K keeps the K outermost loops of each kernel's nest and unrolls all loops inside them; level 0
unrolls everything; `none` unrolls nothing; `auto` unrolls every loop that expands to at most
`budget` statements, wherever it is. With a `budget`, a loop whose expansion would exceed
that many statements stays a loop; `total` bounds the whole program the same way. Choice and
mechanism are apart: `mark_unroll` decides (a tuner may mark loops its own way), `expand_unrolled`
materialises whatever is marked. Border checks that unrolling made redundant are pruned."""

from __future__ import annotations

from dataclasses import replace

from ..ir.analysis import is_accumulator
from ..ir.kinds import LoopKind
from ..ir.loops import Affine, If, Let, Loop, Program, Stmt, walk_stmts
from ..ir.target import Target
from .per_layer import check_layer_names, parse_layer_map
from .substitute import prune_bounds, substitute_body

# Defaults of nncg.compile and nncg-onnx: statements per unrolled loop nest, and in the whole program
# (big models get smaller nests). Keeps gcc -O2 under a minute on ResNet-50; the paper's networks
# and the MLPerf-Tiny models stay below both.
NEST_BUDGET = 8192
CODE_BUDGET = 16384
# Level auto: a loop is unrolled when it expands to at most this many statements. Register-blocked
# layers keep their reduction loops (straight-line reductions spill), tiny loops go (measured on the
# paper's networks: 64 beats 16 and 256 on SSE and AVX-512).
AUTO_BUDGET = 64
TUNED_BUDGETS = (AUTO_BUDGET, 0, 16, 256)  # what --tune times per layer, the default first


def unroll(
    program: Program,
    level: int | str | None = 1,
    budget: int | None = None,
    total: int | None = None,
    layers: dict[str, int] | None = None,
) -> Program:
    """`budget` caps each unrolled loop nest; `total` caps the program's statements after unrolling
    by halving the nest budget until the program fits (or nothing is unrolled any more); `layers`
    gives some layers their own budget (what --tune measured), which the halving leaves alone."""
    if level == "auto" and budget is None:
        budget = AUTO_BUDGET
    budget = budget if budget is not None or total is None else total
    layers = layers or {}
    check_layer_names(program, layers, "unroll")

    def marked_with(budget):
        return [mark_unroll(k.body, level, layers.get(k.name, budget)) for k in program.kernels]

    marked = marked_with(budget)
    while total is not None and budget > 1 and sum(emitted_size(b) for b in marked) > total:
        budget //= 2
        marked = marked_with(budget)
    kernels = tuple(replace(k, body=prune_bounds(expand_unrolled(body))) for k, body in zip(program.kernels, marked))
    return replace(program, kernels=kernels)


def parse_budget(text: str) -> int:
    if not text.isdigit():
        raise ValueError("a budget is a number of statements >= 0")
    return int(text)


def parse_layer_budgets(text: str) -> dict[str, int]:
    """`conv1:256;conv2:0` -> {"conv1": 256, "conv2": 0}."""
    return parse_layer_map(text, parse_budget, "conv1:64")


def emitted_size(body: tuple[Stmt, ...]) -> int:
    """Statements printed for a marked body: unrolled loops are copied, the others appear once."""
    total = 0
    for stmt in body:
        if isinstance(stmt, Loop) and stmt.kind == LoopKind.UNROLLED:
            total += stmt.extent * emitted_size(stmt.body)
        elif isinstance(stmt, Loop | Let | If):
            total += 1 + emitted_size(stmt.body)
        else:
            total += 1
    return total


def mark_unroll(
    body: tuple[Stmt, ...], level: int | str | None, budget: int | None = None, depth: int = 0
) -> tuple[Stmt, ...]:
    """Marks every loop at nesting depth >= level (counted in loops, from 0; any depth for `auto`)
    as unrolled, unless its expansion would exceed `budget` statements: then it stays a loop and its
    inner loops are considered instead (so wide layers of big models keep their code size bounded)."""
    if level is None:
        return body
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop):
            inner = mark_unroll(stmt.body, level, budget, depth + 1)
            deep = level == "auto" or depth >= level
            fits = deep and (budget is None or unrolled_size((stmt,)) <= budget)
            stmt = replace(stmt, body=inner, kind=LoopKind.UNROLLED if fits else stmt.kind)
        elif isinstance(stmt, Let | If):
            stmt = replace(stmt, body=mark_unroll(stmt.body, level, budget, depth))
        out.append(stmt)
    return tuple(out)


def unrolled_size(body: tuple[Stmt, ...]) -> int:
    """Statements left after unrolling every loop in body."""
    total = 0
    for stmt in body:
        if isinstance(stmt, Loop):
            total += stmt.extent * unrolled_size(stmt.body)
        elif isinstance(stmt, Let | If):
            total += 1 + unrolled_size(stmt.body)
        else:
            total += 1
    return total


def expand_unrolled(body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    """Replaces each loop marked unrolled by one copy of its body per iteration."""
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop | Let | If):
            stmt = replace(stmt, body=expand_unrolled(stmt.body))
        if isinstance(stmt, Loop) and stmt.kind == LoopKind.UNROLLED:
            for i in range(stmt.extent):
                out.extend(substitute_body(stmt.body, {stmt.var: Affine.of(i)}))
        else:
            out.append(stmt)
    return tuple(out)


def tuning_candidates(program: Program, target: Target) -> dict[str, tuple[int, ...]]:
    """For --tune: unroll budgets for each layer with a reduction (what register-block blocks)."""
    return {k.name: TUNED_BUDGETS for k in program.kernels if any(is_accumulator(s) for s in walk_stmts(k.body))}
