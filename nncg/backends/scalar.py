"""Backend: the scalar C printer. Prints a kernel's statements and float expressions as C89, max/min
and select as conditional moves, and the helpers of the math functions C89 lacks (scalar_math.py)
that the program calls; the SIMD printer (simd.py) extends it, c_file.py prints the file."""

from __future__ import annotations

from ..errors import NncgError
from ..ir.dtypes import buffer_dtypes, expr_dtype
from ..ir.kinds import DType, LoopKind
from ..ir.loops import (
    Affine,
    Assign,
    Binary,
    Bound,
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
    walk_stmts,
)
from ..ir.target import Target
from .c_integer import c_type, integer_preamble
from .c_text import INDENT, c_affine, c_float, c_int, unparen
from .scalar_math import HELPERS, helper_definitions, helper_name, scalar_calls


class ScalarPrinter:
    """Statements and scalar (1-lane) expressions. A backend subclass declares its `target` (the
    hardware facts, nncg/ir/target.py), `includes` and the compiler flags its code needs."""

    target: Target
    includes: tuple[str, ...] = ("<math.h>",)
    cflags: tuple[str, ...] = ()
    strict_cflags: tuple[str, ...] = ("-std=c89", "-pedantic", "-Wall", "-Wextra", "-Werror")
    scalar_type = "float"

    def __init__(self, math_calls: frozenset[str] = frozenset()) -> None:
        self.math_calls = math_calls  # the math functions scalar code calls, for their helpers
        self.dtypes: dict[str, DType] = {}  # buffer -> dtype, and the locals in scope while printing
        self.integer_lines: list[str] = []

    def for_program(self, program: Program) -> ScalarPrinter:
        """The printer for one program: the helpers it needs are collected here, before any code is
        printed."""
        return type(self)(scalar_calls(program)).typed_for(program)

    def typed_for(self, program: Program) -> ScalarPrinter:
        """This printer with the program's buffer dtypes and integer definitions."""
        self.dtypes = buffer_dtypes(program)
        self.integer_lines = integer_preamble(program)
        return self

    def preamble(self) -> list[str]:
        """Definitions the printed code calls, printed after the includes: the helpers of the math
        functions C89 lacks, when the program calls them, and the integer types and requantisation
        helpers of an int8 program."""
        return helper_definitions(self.math_calls) + self.integer_lines

    def function_body(self, body: tuple[Stmt, ...]) -> list[str]:
        """The lines inside a kernel's function: its loop variables, then its statements."""
        loop_vars = sorted({s.var for s in walk_stmts(body) if isinstance(s, Loop)})
        decls = [f"{INDENT}int {', '.join(loop_vars)};"] if loop_vars else []
        return decls + self.stmts(body, 1)

    # ------------------------------------------------------------------ statements

    def stmts(self, body: tuple[Stmt, ...], depth: int) -> list[str]:
        out: list[str] = []
        for stmt in body:
            out += getattr(self, f"_stmt_{type(stmt).__name__}")(stmt, depth)
        return out

    def _stmt_Loop(self, loop: Loop, depth: int) -> list[str]:
        if loop.kind != LoopKind.SERIAL:
            raise NncgError(f"loop '{loop.var}' is still marked {loop.kind}: run the pass that materialises it")
        pad = INDENT * depth
        head = f"{pad}for ({loop.var} = 0; {loop.var} < {loop.extent}; ++{loop.var}) {{"
        return [head, *self.stmts(loop.body, depth + 1), pad + "}"]

    def _stmt_Let(self, let: Let, depth: int) -> list[str]:
        """One block for a chain of Lets each of whose body is just the next Let: their scopes end
        together, so the declarations share a block (26 accumulators are not 26 nested blocks)."""
        pad = INDENT * depth
        chain = [let]
        while len(chain[-1].body) == 1 and isinstance(chain[-1].body[0], Let):
            inner = chain[-1].body[0]
            if any(inner.name == outer.name for outer in chain):
                break  # a shadowing declaration needs its own block
            chain.append(inner)
        outer = dict(self.dtypes)
        decls = []
        for v in chain:
            decls.append(f"{pad}{INDENT}{self.local_type(v.init)} {v.name} = {self.expr(v.init)};")
            self.dtypes[v.name] = expr_dtype(v.init, self.dtypes, self.dtypes)
        body = self.stmts(chain[-1].body, depth + 1)
        self.dtypes = outer
        return [pad + "{", *decls, *body, pad + "}"]

    def local_type(self, init: Expr) -> str:
        dtype = expr_dtype(init, self.dtypes, self.dtypes)
        return self.type_of(init.lanes) if dtype == DType.FLOAT32 else c_type(dtype)

    def _stmt_If(self, stmt: If, depth: int) -> list[str]:
        pad = INDENT * depth
        cond = " && ".join(_bound(b) for b in stmt.bounds)
        return [f"{pad}if ({cond}) {{", *self.stmts(stmt.body, depth + 1), pad + "}"]

    def _stmt_Store(self, store: Store, depth: int) -> list[str]:
        return [INDENT * depth + self.store(store.buffer, store.index, store.value) + ";"]

    def _stmt_Assign(self, assign: Assign, depth: int) -> list[str]:
        return [INDENT * depth + self.assign(assign.name, assign.value) + ";"]

    # ------------------------------------------------------------------ hooks a SIMD printer extends

    def type_of(self, lanes: int) -> str:
        self.unsupported_lanes(lanes)
        return self.scalar_type

    def store(self, buffer: str, index: Affine, value: Expr) -> str:
        self.unsupported_lanes(value.lanes)
        return f"{buffer}[{c_affine(index)}] = {unparen(self.expr(value))}"

    def assign(self, name: str, value: Expr) -> str:
        # acc = acc + e reads better as acc += e
        if isinstance(value, Binary) and value.op in "+-*/" and value.a == LocalRef(name, value.lanes):
            if value.lanes == 1:
                return f"{name} {value.op}= {unparen(self.expr(value.b))}"
        return f"{name} = {unparen(self.expr(value))}"

    def expr(self, e: Expr) -> str:
        self.unsupported_lanes(e.lanes)
        return getattr(self, f"_expr_{type(e).__name__}")(e)

    def unsupported_lanes(self, lanes: int) -> None:
        """Refuses a vector width this printer has no spelling for."""
        if lanes != 1:
            widths = self.target.widths_text if self.target.vector_widths else "1 (or not at all)"
            name = self.target.name
            raise NncgError(f"target {name} cannot print {lanes}-lane vectors; run vectorize with lanes={widths}")

    # ------------------------------------------------------------------ scalar expressions

    def _expr_Const(self, e: Const) -> str:
        if e.dtype == DType.FLOAT64:
            return repr(float(e.values[0]))
        return c_float(e.values[0]) if e.dtype == DType.FLOAT32 else c_int(e.values[0])

    def _expr_Cast(self, e: Cast) -> str:
        return f"(({c_type(e.dtype)}){self.expr(e.value)})"

    def _expr_Requantize(self, e: Requantize) -> str:
        return f"nncg_requantize({unparen(self.expr(e.value))}, {e.zero_point}, {e.low}, {e.high})"

    def _expr_RequantizeFixed(self, e: RequantizeFixed) -> str:
        args = ", ".join(unparen(self.expr(x)) for x in (e.value, e.multiplier, e.shift))
        return f"nncg_requantize_fixed({args}, {e.zero_point}, {e.low}, {e.high})"

    def _expr_Load(self, e: Load) -> str:
        return f"{e.buffer}[{c_affine(e.index)}]"

    def _expr_Lookup(self, e: Lookup) -> str:
        return f"{e.table}[{unparen(self.expr(e.index))}]"

    def _expr_LocalRef(self, e: LocalRef) -> str:
        return e.name

    def _expr_Broadcast(self, e: Broadcast) -> str:
        return self.expr(e.value)

    def _expr_Binary(self, e: Binary) -> str:
        a, b = self.expr(e.a), self.expr(e.b)
        if e.op == "max":  # the paper's conditional move
            return f"({a} > {b} ? {a} : {b})"
        if e.op == "min":
            return f"({a} < {b} ? {a} : {b})"
        return f"({a} {e.op} {b})"

    def _expr_Dot(self, e: Dot) -> str:
        return scalar_dot(self, e, lane=0)

    def _expr_Fma(self, e: Fma) -> str:
        # Scalar C has no fused multiply-add in C89, and the FMA legalisation forms one only on
        # vectors; one formed by hand still prints, as a multiply and an add (two roundings).
        return f"(({self.expr(e.a)} * {self.expr(e.b)}) + {self.expr(e.c)})"

    def _expr_Select(self, e: Select) -> str:
        lhs, rhs, then, other = (self.expr(x) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return f"({lhs} {e.cmp} {rhs} ? {then} : {other})"

    def _expr_Call(self, e: Call) -> str:
        if e.fn == "sigmoid":  # no sigmoid in math.h
            return self.expr(sigmoid_by_exp(e.arg))
        if e.fn in HELPERS:  # not in C89's math.h either
            return f"{helper_name(e.fn)}({self.expr(e.arg)})"
        return f"(float){C89_NAMES.get(e.fn, e.fn)}({self.expr(e.arg)})"  # C89 has only the double versions


def scalar_dot(printer: ScalarPrinter, e: Dot, lane: int) -> str:
    """Lane `lane` of a dot product as plain int32 products (channels that read 0 left out)."""
    k = len(e.x)
    terms = [
        f"{printer.expr(x)} * (({c_type(DType.INT32)}){e.w.buffer}[{c_affine(e.w.index + (lane * k + j))}])"
        for j, x in enumerate(e.x)
        if x != Const.integer(0)
    ]
    return f"({' + '.join(terms)})"


C89_NAMES = {"abs": "fabs"}  # math.h's name of a MathFunction, where it is not the same


def sigmoid_by_exp(x: Expr) -> Expr:
    """1 / (1 + exp(0 - x)): for very negative x, exp overflows to inf and the quotient is the exact 0."""
    one = Const.splat(1.0, x.lanes)
    return Binary("/", one, Binary("+", one, Call("exp", Binary("-", Const.splat(0.0, x.lanes), x))))


def _bound(bound: Bound) -> str:
    e = c_affine(bound.expr)
    sides = ([f"{e} >= {bound.lo}"] if bound.lo is not None else []) + (
        [f"{e} < {bound.hi}"] if bound.hi is not None else []
    )
    return " && ".join(sides)
