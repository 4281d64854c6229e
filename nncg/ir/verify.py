"""Well-formedness checks of both IRs, run by the pass manager after every pass (on by default;
`verify=False` skips them)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..ir.graph import Graph, Node
from ..ir.loops import (
    Affine,
    Binary,
    Broadcast,
    Buffer,
    Call,
    Cast,
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
    walk_exprs,
)
from ..ir.ops import IR_OPS
from .arena import ARENA_DTYPES, sharing_problems
from .dtypes import buffer_dtypes, expr_dtype
from .graph_dtypes import OUTPUT_DTYPES, graph_dtype_problems
from .kinds import BufferRole, DType, LoopKind

FLOAT32, INT32 = DType.FLOAT32, DType.INT32
VECTOR_WIDTHS = (1, 2, 4, 8, 16)  # lanes a loop or expression may have


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
    return problems + graph_dtype_problems(graph)


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
    for buf in program.buffers:
        if buf.role == BufferRole.OUTPUT and buf.dtype not in OUTPUT_DTYPES:
            problems.append(f"output buffer {buf.name} is {buf.dtype}: outputs are {', '.join(OUTPUT_DTYPES)}")
        elif buf.role not in (BufferRole.CONSTANT, BufferRole.OUTPUT) and buf.dtype not in ARENA_DTYPES:
            problems.append(
                f"{buf.role} buffer {buf.name} is {buf.dtype}: only {', '.join(ARENA_DTYPES)} live in memory"
            )
        data = program.constants.get(buf.name)
        if data is not None and data.dtype.name != buf.dtype:
            problems.append(f"constant {buf.name} is {buf.dtype} but its data is {data.dtype.name}")
    problems += sharing_problems(program)
    scope = _Scope(buffers, {}, frozenset(), {}, buffer_dtypes(program))
    for kernel in program.kernels:
        _check_body(kernel.body, scope, problems, kernel.name)
    return problems


@dataclass(frozen=True)
class _Scope:
    """What a statement sees: the buffers, the enclosing loops' extents, the loop variables an
    enclosing border check constrains, the declared locals with their lanes, and the dtypes of
    the buffers and the locals."""

    buffers: dict[str, Buffer]
    extents: dict[str, int]
    guarded: frozenset[str]
    locals_: dict[str, int]
    dtypes: dict[str, DType]


def _check_body(body: tuple[Stmt, ...], scope: _Scope, problems: list[str], where: str) -> None:
    for stmt in body:
        if isinstance(stmt, Loop):
            _check_loop(stmt, problems, where, scope)
            inner = replace(scope, extents=scope.extents | {stmt.var: stmt.extent})
            _check_body(stmt.body, inner, problems, where)
        elif isinstance(stmt, If):
            for bound in stmt.bounds:
                _check_vars(bound.expr.vars, scope.extents, problems, where)
            guarded = scope.guarded | {v for bound in stmt.bounds for v in bound.expr.vars}
            _check_body(stmt.body, replace(scope, guarded=guarded), problems, where)
        elif isinstance(stmt, Let):
            _check_expr(stmt.init, scope, problems, where)
            dtype = expr_dtype(stmt.init, scope.dtypes, scope.dtypes)
            inner = replace(
                scope, locals_=scope.locals_ | {stmt.name: stmt.init.lanes}, dtypes=scope.dtypes | {stmt.name: dtype}
            )
            _check_body(stmt.body, inner, problems, where)
        else:
            _check_expr(stmt.value, scope, problems, where)
            if isinstance(stmt, Store):
                buf = scope.buffers.get(stmt.buffer)
                if buf is None or buf.role not in (BufferRole.INTERNAL, BufferRole.OUTPUT):
                    problems.append(f"{where}: store to {stmt.buffer}, which is not a writable buffer")
                _check_access(stmt.buffer, stmt.index, stmt.value.lanes, scope, problems, where)
                _check_stored_type(
                    stmt.buffer, expr_dtype(stmt.value, scope.dtypes, scope.dtypes), scope, problems, where
                )
            elif scope.locals_.get(stmt.name) != stmt.value.lanes:
                problems.append(f"{where}: assignment to {stmt.name} with {stmt.value.lanes} lanes, not declared so")
            elif expr_dtype(stmt.value, scope.dtypes, scope.dtypes) != scope.dtypes.get(stmt.name):
                problems.append(f"{where}: assignment of another type to {stmt.name}")


def _check_loop(loop: Loop, problems: list[str], where: str, scope: _Scope) -> None:
    if loop.var in scope.extents:
        problems.append(f"{where}: loop variable {loop.var} shadows an outer loop")
    if loop.extent < 1:
        problems.append(f"{where}: loop {loop.var} has extent {loop.extent}")
    if loop.lanes not in VECTOR_WIDTHS:
        problems.append(f"{where}: loop {loop.var} has {loop.lanes} lanes, not one of {VECTOR_WIDTHS}")
    if loop.kind == LoopKind.VECTORIZED and not 1 < loop.lanes <= loop.extent:
        problems.append(f"{where}: loop {loop.var} is vectorised with {loop.lanes} lanes over {loop.extent}")
    if loop.kind == LoopKind.UNROLLED and loop.lanes != 1:
        problems.append(f"{where}: unrolled loop {loop.var} has {loop.lanes} lanes")


def _check_access(buffer: str, index: Affine, lanes: int, scope: _Scope, problems: list[str], where: str) -> None:
    """The index uses enclosing loop variables only, and stays inside the buffer for every value of
    them (an access under a border check on one of its variables is exempt: the check keeps it in)."""
    _check_vars(index.vars, scope.extents, problems, where)
    buf = scope.buffers.get(buffer)
    if buf is None or not set(index.vars) <= scope.extents.keys() or scope.guarded & set(index.vars):
        return
    lo, hi = index.bounds(scope.extents)
    if lo < 0 or hi + lanes > buf.size:
        problems.append(f"{where}: {buffer}[{index}] reaches [{lo}, {hi + lanes}) outside its {buf.size} elements")


def _check_expr(expr: Expr, scope: _Scope, problems: list[str], where: str) -> None:
    for e in walk_exprs(expr):
        if isinstance(e, Load):
            if e.buffer not in scope.buffers:
                problems.append(f"{where}: load from unknown buffer {e.buffer}")
            _check_access(e.buffer, e.index, e.lanes, scope, problems, where)
        elif isinstance(e, Lookup) and e.table not in scope.buffers:
            problems.append(f"{where}: lookup in unknown table {e.table}")
        elif isinstance(e, LocalRef) and scope.locals_.get(e.name) != e.lanes:
            problems.append(f"{where}: {e.name} read with {e.lanes} lanes, not declared so")
        elif isinstance(e, Binary) and e.a.lanes != e.b.lanes:
            problems.append(f"{where}: operands of {e.op} have {e.a.lanes} and {e.b.lanes} lanes")
        elif isinstance(e, Select) and len({x.lanes for x in (e.lhs, e.rhs, e.then, e.otherwise)}) != 1:
            problems.append(f"{where}: select operands differ in lanes")
        elif isinstance(e, Fma) and len({x.lanes for x in (e.a, e.b, e.c)}) != 1:
            problems.append(f"{where}: fma operands differ in lanes")
        elif isinstance(e, Broadcast) and e.value.lanes != 1:
            problems.append(f"{where}: broadcast of a vector")
        problems += [f"{where}: {p}" for p in _type_problems(e, scope.dtypes)]


def _check_stored_type(buffer: str, dtype: DType, scope: _Scope, problems: list[str], where: str) -> None:
    """A float buffer takes float32 values; an integer buffer an integer value (Requantize and Cast
    narrow to it, and a copy moves the buffer's own type)."""
    buf = scope.buffers.get(buffer)
    if buf is not None and (buf.dtype == FLOAT32) != (dtype == FLOAT32):
        problems.append(f"{where}: store of a {dtype} value to {buf.dtype} buffer {buffer}")


def _type_problems(e: Expr, dtypes: dict[str, DType]) -> list[str]:
    """The operands of one node have the types it computes on."""

    def dtype(x: Expr) -> DType:
        return expr_dtype(x, dtypes, dtypes)

    if isinstance(e, Binary):
        a, b = dtype(e.a), dtype(e.b)
        if a != b:
            return [f"operands of {e.op} are {a} and {b}"]
        if a.is_integer and (a != INT32 or e.op == "/"):
            return [f"{e.op} on {a}: integer arithmetic is int32 +, -, *, max and min"]
    elif isinstance(e, Select):
        if dtype(e.lhs) != dtype(e.rhs) or dtype(e.then) != dtype(e.otherwise):
            return ["select compares or picks values of different types"]
    elif isinstance(e, Call | Fma):
        operands = (e.arg,) if isinstance(e, Call) else (e.a, e.b, e.c)
        if any(dtype(x) != FLOAT32 for x in operands):
            return ["math on a value that is not float32"]
    elif isinstance(e, Cast):
        if not dtype(e.value).is_integer and e.dtype.is_integer:
            return [f"cast of {dtype(e.value)} to {e.dtype}: float to integer is a Requantize"]
    elif isinstance(e, Requantize | RequantizeFixed):
        return _requantize_problems(e, dtype)
    elif isinstance(e, Dot):
        lanes = e.w.lanes // len(e.x)  # x: shared scalars, or a depthwise's per-lane taps
        weights = dtype(e.w) in (DType.INT8, DType.INT16)
        if any(dtype(x) != INT32 or x.lanes not in (1, lanes) for x in e.x) or not weights:
            return ["dot of values that are not int32 scalars or vectors and int8 or int16 weights"]
        if e.w.lanes % len(e.x):
            return [f"dot of {len(e.x)} channels reads {e.w.lanes} weights"]
    elif isinstance(e, Lookup) and dtype(e.index) != INT32:
        return [f"lookup at a {dtype(e.index)} index, not int32"]
    return []


def _requantize_problems(e: Requantize | RequantizeFixed, dtype) -> list[str]:
    problems = []
    operands = (e.value,) if isinstance(e, Requantize) else (e.value, e.multiplier, e.shift)
    expected = (FLOAT32,) if isinstance(e, Requantize) else (INT32, INT32, INT32)
    if tuple(dtype(x) for x in operands) != expected:
        problems.append(f"requantize of {', '.join(dtype(x) for x in operands)}, not {', '.join(expected)}")
    low, high = e.dtype.range if e.dtype.is_integer else (1, 0)
    if not low <= e.low <= e.high <= high:
        problems.append(f"requantize to {e.dtype} in [{e.low}, {e.high}]")
    return problems


def _check_vars(vars_, extents: dict[str, int], problems: list[str], where: str) -> None:
    for var in vars_:
        if var not in extents:
            problems.append(f"{where}: index uses {var} outside its loop")
