"""Readable text form of both IRs, printed between passes (--print-ir-after-all)."""

from __future__ import annotations

from dataclasses import fields, is_dataclass

import numpy as np

from ..safe_text import capped, escaped
from .graph import Activation, Graph
from .kinds import DType, LoopKind
from .loops import (
    Assign,
    Binary,
    Broadcast,
    Call,
    Cast,
    Const,
    Dot,
    Expr,
    Fma,
    If,
    Let,
    Load,
    LocalRef,
    Lookup,
    Loop,
    Program,
    Requantize,
    RequantizeFixed,
    Select,
    Stmt,
    Store,
)


def graph_to_text(graph: Graph) -> str:
    """Value names as the model has them, made printable and capped (the text goes to a terminal)."""

    def typed(n: str) -> str:
        dtype = graph.dtype(n)
        return f"{_name(n)}{'' if dtype == DType.FLOAT32 else ' ' + dtype}"

    def sig(names):
        return ", ".join(
            f"{typed(n)}: const{list(graph.shape(n))}" if graph.is_constant(n) else f"{typed(n)}{list(graph.shape(n))}"
            for n in names
        )

    inputs, outputs = sig(v.name for v in graph.inputs), sig(v.name for v in graph.outputs)
    lines = [f"graph {_name(graph.name)}({inputs}) -> ({outputs}) {{"]
    for node in graph.nodes:
        attrs = attrs_to_text(node.attrs) if node.attrs is not None else ""
        attrs = f" {{{attrs}}}" if attrs else ""
        results = ", ".join(map(typed, node.outputs))
        lines.append(f"  {results} = {node.op}({sig(node.inputs)}){attrs}  # {_name(node.name)}")
    lines.append("}")
    return "\n".join(lines)


def _name(name: str) -> str:
    return capped(escaped(name))


def attrs_to_text(attrs) -> str:
    """The fields that differ from their defaults, e.g. `kernel=3x3, pads_begin=1x1, activation=relu`."""
    if not is_dataclass(attrs) or isinstance(attrs, Activation):
        return str(attrs)
    parts = []
    for f in fields(attrs):
        value = getattr(attrs, f.name)
        if value == f.default or (f.name in ("strides", "dilations") and set(value) == {1}):
            continue
        parts.append(f"{f.name}={'x'.join(map(str, value)) if isinstance(value, tuple) else value}")
    return ", ".join(parts)


def program_to_text(program: Program) -> str:
    lines = [f"program {program.name} {{"]
    if program.arena:
        arena = program.arena
        lines.append(
            f"  arena {arena.floats} floats  # activations {arena.activation_floats}, align {arena.align_floats}"
        )
    for buf in program.buffers:
        shape = "x".join(map(str, buf.shape))
        place = f" @ arena+{buf.offset}" if buf.offset is not None else ""
        dtype = f" {buf.dtype}" if buf.dtype != DType.FLOAT32 else ""
        lines.append(f"  {buf.role}{dtype} {buf.name}[{buf.size}]{place}  # {shape} {buf.layout}".rstrip())
    for kernel in program.kernels:
        overlap = " overlapping-stores" if kernel.overlapping_stores else ""
        lines.append(f"  kernel {kernel.name} ({kernel.op}){overlap} {{")
        lines.extend(_stmts(kernel.body, 2))
        lines.append("  }")
    lines.append("}")
    return "\n".join(lines)


def _stmts(body: tuple[Stmt, ...], depth: int) -> list[str]:
    pad = "  " * depth
    out: list[str] = []
    for stmt in body:
        if isinstance(stmt, Loop):
            tags = [stmt.kind] if stmt.kind != LoopKind.SERIAL else []
            tags += ["parallel"] if stmt.parallel else []
            tags += [f"lanes={stmt.lanes}"] if stmt.lanes > 1 else []
            tag = f" [{', '.join(tags)}]" if tags else ""
            out.append(f"{pad}for {stmt.var} in 0..{stmt.extent}{tag} {{")
            out.extend(_stmts(stmt.body, depth + 1))
            out.append(f"{pad}}}")
        elif isinstance(stmt, Let):
            out.append(f"{pad}let {stmt.name} = {expr_to_text(stmt.init)} {{")
            out.extend(_stmts(stmt.body, depth + 1))
            out.append(f"{pad}}}")
        elif isinstance(stmt, If):
            conds = " and ".join(
                f"{'' if b.lo is None else f'{b.lo} <= '}{b.expr}{'' if b.hi is None else f' < {b.hi}'}"
                for b in stmt.bounds
            )
            out.append(f"{pad}if {conds} {{")
            out.extend(_stmts(stmt.body, depth + 1))
            out.append(f"{pad}}}")
        elif isinstance(stmt, Store):
            out.append(f"{pad}{stmt.buffer}[{stmt.index}] = {expr_to_text(stmt.value)}")
        elif isinstance(stmt, Assign):
            out.append(f"{pad}{stmt.name} = {expr_to_text(stmt.value)}")
    return out


def expr_to_text(expr: Expr) -> str:
    if isinstance(expr, Const) and expr.dtype != DType.FLOAT32:
        values = ", ".join(str(v) for v in expr.values)
        return f"{expr.dtype}({values})" if expr.lanes == 1 else f"{expr.dtype}<{values}>"
    if isinstance(expr, Cast):
        return f"{expr.dtype}({expr_to_text(expr.value)})"
    if isinstance(expr, Requantize):
        return f"requantize_{expr.dtype}({expr_to_text(expr.value)}, zp={expr.zero_point}, {expr.low}..{expr.high})"
    if isinstance(expr, RequantizeFixed):
        operands = ", ".join(expr_to_text(e) for e in (expr.value, expr.multiplier, expr.shift))
        return f"requantize_fixed_{expr.dtype}({operands}, zp={expr.zero_point}, {expr.low}..{expr.high})"
    if isinstance(expr, Const):
        vals = [f"{np.float32(v)!r}".removeprefix("np.float32(").removesuffix(")") for v in expr.values]
        return (
            vals[0]
            if expr.is_splat and expr.lanes == 1
            else (f"splat{expr.lanes}({vals[0]})" if expr.is_splat else f"<{', '.join(vals)}>")
        )
    if isinstance(expr, Load):
        lanes = f":{expr.lanes}" if expr.lanes > 1 else ""
        return f"{expr.buffer}[{expr.index}{lanes}]"
    if isinstance(expr, Lookup):
        return f"{expr.table}[{expr_to_text(expr.index)}]"
    if isinstance(expr, LocalRef):
        return expr.name
    if isinstance(expr, Broadcast):
        return f"broadcast{expr.lanes}({expr_to_text(expr.value)})"
    if isinstance(expr, Binary):
        if expr.op in ("max", "min"):
            return f"{expr.op}({expr_to_text(expr.a)}, {expr_to_text(expr.b)})"
        return f"({expr_to_text(expr.a)} {expr.op} {expr_to_text(expr.b)})"
    if isinstance(expr, Select):
        parts = [expr_to_text(e) for e in (expr.lhs, expr.rhs, expr.then, expr.otherwise)]
        return f"({parts[0]} {expr.cmp} {parts[1]} ? {parts[2]} : {parts[3]})"
    if isinstance(expr, Call):
        return f"{expr.fn}({expr_to_text(expr.arg)})"
    if isinstance(expr, Dot):
        return f"dot({', '.join(expr_to_text(x) for x in expr.x)}; {expr_to_text(expr.w)})"
    if isinstance(expr, Fma):
        return f"fma({expr_to_text(expr.a)}, {expr_to_text(expr.b)}, {expr_to_text(expr.c)})"
    raise TypeError(f"not a loop-IR expression: {expr!r}")
