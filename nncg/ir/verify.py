"""Well-formedness checks of both IRs, run by the pass manager after every pass in tests."""

from __future__ import annotations

from ..ir.graph import Graph, Node
from ..ir.loops import (
    FUNCTIONS,
    Assign,
    Binary,
    Broadcast,
    Call,
    Expr,
    Fma,
    If,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Select,
    Stmt,
    Store,
    walk_exprs,
)
from ..ir.ops import IR_OPS
from .kinds import BufferRole


def verify_ir(ir: Graph | Program) -> list[str]:
    return verify_graph(ir) if isinstance(ir, Graph) else verify_program(ir)


def verify_graph(graph: Graph) -> list[str]:
    problems = []
    known = {v.name for v in graph.inputs} | set(graph.constants)
    for node in graph.nodes:
        problems += _node_op_problems(node)
        for name in node.inputs:
            if name not in known:
                problems.append(f"node {node.name} reads {name} before it is produced")
        for name in node.outputs:
            if name not in graph.shapes:
                problems.append(f"node {node.name}: output {name} has no shape")
        known |= set(node.outputs)
    problems += [f"graph output {v.name} is never produced" for v in graph.outputs if v.name not in known]
    return problems


def _node_op_problems(node: Node) -> list[str]:
    """An op of IR_OPS, carrying that op's attribute record."""
    op = IR_OPS.get(node.op)
    if op is None:
        return [f"node {node.name}: unknown op {node.op}"]
    expected = type(None) if op.attrs is None else op.attrs
    if isinstance(node.attrs, expected):
        return []
    return [f"node {node.name}: {node.op} carries {type(node.attrs).__name__}, not {expected.__name__}"]


def verify_program(program: Program) -> list[str]:
    problems: list[str] = []
    buffers = {b.name: b for b in program.buffers}
    for buf in program.role(BufferRole.CONSTANT):
        if buf.name not in program.constants or program.constants[buf.name].size != buf.size:
            problems.append(f"constant {buf.name} has no data of size {buf.size}")
    for kernel in program.kernels:
        _check_body(kernel.body, buffers, set(), {}, problems, kernel.name)
    return problems


def _check_body(body: tuple[Stmt, ...], buffers, loop_vars: set[str], locals_: dict[str, int], problems, where):
    for stmt in body:
        if isinstance(stmt, Loop):
            if stmt.var in loop_vars:
                problems.append(f"{where}: loop variable {stmt.var} shadows an outer loop")
            _check_body(stmt.body, buffers, loop_vars | {stmt.var}, locals_, problems, where)
            continue
        if isinstance(stmt, If):
            for bound in stmt.bounds:
                _check_vars(bound.expr.vars, loop_vars, problems, where)
            _check_body(stmt.body, buffers, loop_vars, locals_, problems, where)
            continue
        if isinstance(stmt, Let):
            _check_expr(stmt.init, buffers, loop_vars, locals_, problems, where)
            inner = locals_ | {stmt.name: stmt.init.lanes}
            _check_body(stmt.body, buffers, loop_vars, inner, problems, where)
            continue
        _check_expr(stmt.value, buffers, loop_vars, locals_, problems, where)
        if isinstance(stmt, Store):
            buf = buffers.get(stmt.buffer)
            if buf is None or buf.role not in ("internal", "output"):
                problems.append(f"{where}: store to {stmt.buffer}, which is not a writable buffer")
            _check_vars(stmt.index.vars, loop_vars, problems, where)
        elif isinstance(stmt, Assign):
            if locals_.get(stmt.name) != stmt.value.lanes:
                problems.append(f"{where}: assignment to {stmt.name} with {stmt.value.lanes} lanes, not declared so")


def _check_expr(expr: Expr, buffers, loop_vars, locals_, problems, where):
    for e in walk_exprs(expr):
        if isinstance(e, Load):
            if e.buffer not in buffers:
                problems.append(f"{where}: load from unknown buffer {e.buffer}")
            _check_vars(e.index.vars, loop_vars, problems, where)
        elif isinstance(e, LocalRef) and locals_.get(e.name) != e.lanes:
            problems.append(f"{where}: {e.name} read with {e.lanes} lanes, not declared so")
        elif isinstance(e, Binary) and e.a.lanes != e.b.lanes:
            problems.append(f"{where}: operands of {e.op} have {e.a.lanes} and {e.b.lanes} lanes")
        elif isinstance(e, Select) and len({x.lanes for x in (e.lhs, e.rhs, e.then, e.otherwise)}) != 1:
            problems.append(f"{where}: select operands differ in lanes")
        elif isinstance(e, Fma) and len({x.lanes for x in (e.a, e.b, e.c)}) != 1:
            problems.append(f"{where}: fma operands differ in lanes")
        elif isinstance(e, Broadcast) and e.value.lanes != 1:
            problems.append(f"{where}: broadcast of a vector")
        elif isinstance(e, Call) and e.fn not in FUNCTIONS:
            problems.append(f"{where}: call of unknown function {e.fn}")


def _check_vars(vars_, loop_vars, problems, where):
    for var in vars_:
        if var not in loop_vars:
            problems.append(f"{where}: index uses {var} outside its loop")
