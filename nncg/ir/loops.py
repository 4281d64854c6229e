"""Loop-nest IR: what the graph lowers to, what loop passes rewrite and what backends print.

A Program is a list of Kernels (one per layer) over flat buffers, float32 unless a buffer says
another DType (the int8 path, see nncg/ir/dtypes.py for how expressions are typed). Indices are
affine in the integer loop variables, so unrolling is substitution and vectorisation is a stride
check. Every expression has a lane count: a vector operation is the same node with lanes > 1.
All nodes are frozen dataclasses, so two IRs compare structurally with ==.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Union

import numpy as np

from .arrays import same_arrays
from .kinds import BinaryOp, BufferRole, Comparison, DType, Layout, LoopKind, MathFunction, coerce

# ---------------------------------------------------------------------------- integer indices


@dataclass(frozen=True)
class Affine:
    """sum(coeff * var) + const over loop variables; terms are sorted and have no zero coefficient."""

    terms: tuple[tuple[str, int], ...] = ()
    const: int = 0

    @staticmethod
    def of(value: Affine | str | int) -> Affine:
        if isinstance(value, Affine):
            return value
        if isinstance(value, str):
            return Affine(((value, 1),))
        return Affine((), int(value))

    @staticmethod
    def _make(coeffs: dict[str, int], const: int) -> Affine:
        return Affine(tuple(sorted((v, c) for v, c in coeffs.items() if c)), const)

    def __add__(self, other: Affine | str | int) -> Affine:
        other = Affine.of(other)
        coeffs = dict(self.terms)
        for var, c in other.terms:
            coeffs[var] = coeffs.get(var, 0) + c
        return Affine._make(coeffs, self.const + other.const)

    __radd__ = __add__

    def __sub__(self, other: Affine | str | int) -> Affine:
        return self + Affine.of(other) * -1

    def __mul__(self, k: int) -> Affine:
        return Affine._make({v: c * k for v, c in self.terms}, self.const * k)

    __rmul__ = __mul__

    def coeff(self, var: str) -> int:
        return dict(self.terms).get(var, 0)

    @property
    def vars(self) -> tuple[str, ...]:
        return tuple(v for v, _ in self.terms)

    @property
    def is_const(self) -> bool:
        return not self.terms

    def substitute(self, env: dict[str, Affine | int]) -> Affine:
        out = Affine((), self.const)
        for var, c in self.terms:
            out = out + (Affine.of(env[var]) * c if var in env else Affine(((var, c),)))
        return out

    def bounds(self, extents: dict[str, int]) -> tuple[int, int]:
        """Smallest and largest value over loop vars ranging in [0, extent)."""
        lo = hi = self.const
        for var, c in self.terms:
            span = c * (extents[var] - 1)
            lo, hi = lo + min(0, span), hi + max(0, span)
        return lo, hi

    def __str__(self) -> str:
        parts = [var if c == 1 else f"{c}*{var}" for var, c in self.terms]
        if self.const or not parts:
            parts.append(str(self.const))
        return " + ".join(parts).replace("+ -", "- ")


# ---------------------------------------------------------------------------- expressions


@dataclass(frozen=True)
class Const:
    """A literal; one value per lane (a splat repeats it). Integer types hold Python ints."""

    values: tuple[float, ...]
    dtype: DType = DType.FLOAT32

    def __post_init__(self) -> None:
        coerce(self, dtype=DType)

    @staticmethod
    def splat(value: float, lanes: int = 1) -> Const:
        return Const((float(np.float32(value)),) * lanes)

    @staticmethod
    def integer(value: int, dtype: DType = DType.INT32) -> Const:
        return Const((int(value),), dtype)

    @property
    def lanes(self) -> int:
        return len(self.values)

    @property
    def is_splat(self) -> bool:
        return all(v == self.values[0] for v in self.values) and len({np.signbit(v) for v in self.values}) == 1


@dataclass(frozen=True)
class Load:
    """buffer[index .. index + lanes - 1]."""

    buffer: str
    index: Affine
    lanes: int = 1


@dataclass(frozen=True)
class Lookup:
    """table[index]: one element of a constant table at a computed int32 index (in its range)."""

    table: str
    index: Expr
    lanes: int = 1


@dataclass(frozen=True)
class LocalRef:
    name: str
    lanes: int = 1


@dataclass(frozen=True)
class Broadcast:
    value: Expr
    lanes: int


@dataclass(frozen=True)
class Binary:
    op: BinaryOp
    a: Expr
    b: Expr

    def __post_init__(self) -> None:
        coerce(self, op=BinaryOp)

    @property
    def lanes(self) -> int:
        return max(self.a.lanes, self.b.lanes)


@dataclass(frozen=True)
class Select:
    """The paper's conditional move: (lhs cmp rhs) ? then : otherwise, per lane."""

    cmp: Comparison
    lhs: Expr
    rhs: Expr
    then: Expr
    otherwise: Expr

    def __post_init__(self) -> None:
        coerce(self, cmp=Comparison)

    @property
    def lanes(self) -> int:
        return max(e.lanes for e in (self.lhs, self.rhs, self.then, self.otherwise))


@dataclass(frozen=True)
class Call:
    """fn(arg) per lane, in float: how each target computes it, see MathFunction."""

    fn: MathFunction
    arg: Expr

    def __post_init__(self) -> None:
        coerce(self, fn=MathFunction)

    @property
    def lanes(self) -> int:
        return self.arg.lanes


@dataclass(frozen=True)
class Fma:
    """a * b + c per lane, fused (one rounding): formed by a backend for targets that have it."""

    a: Expr
    b: Expr
    c: Expr

    @property
    def lanes(self) -> int:
        return max(self.a.lanes, self.b.lanes, self.c.lanes)


class _Converting:
    """A node that converts its `value` to its `dtype`: it has value's lanes."""

    def __post_init__(self) -> None:
        coerce(self, dtype=DType)

    @property
    def lanes(self) -> int:
        return self.value.lanes


@dataclass(frozen=True)
class Cast(_Converting):
    """value converted to `dtype`: integer widening or narrowing to a type that holds the value,
    integer to float (rounded to nearest), float32 to float64 (exact) and back (rounded). Float to
    integer is never a Cast: Requantize rounds and saturates."""

    dtype: DType
    value: Expr


@dataclass(frozen=True)
class Requantize(_Converting):
    """The float form of requantisation (MLAS's, onnxruntime's CPU kernels): a float32 `value`
    already multiplied by its scale, clamped to [low - zero_point, high - zero_point] (NaN to the
    low end), rounded half to even, plus `zero_point`; an integer of `dtype` in [low, high]."""

    value: Expr
    zero_point: int
    low: int
    high: int
    dtype: DType


@dataclass(frozen=True)
class RequantizeFixed(_Converting):
    """The fixed-point form (the int32 multiplier and shift of gemmlowp, TFLite and CMSIS-NN): an
    int32 `value` times the int32 `multiplier` (in [2^30, 2^31)), divided by 2^(31 + `shift`)
    rounding half away from zero (one rounding, CMSIS-NN's single-rounding mode), plus
    `zero_point`, saturated to [low, high]: the scale is multiplier * 2^-(31 + shift), with no float
    arithmetic."""

    value: Expr
    multiplier: Expr
    shift: Expr
    zero_point: int
    low: int
    high: int
    dtype: DType


@dataclass(frozen=True)
class Dot:
    """The widening multiply-accumulate of K = len(x) input channels: lane l is the int32
    sum_j x[j] * w[l * K + j], x the K int32 scalars every lane shares (activations), `w` the K *
    lanes weights (int8) packed at generation time in exactly that order. Targets print it as one
    pmaddwd (K = 2) or vpdpbusd (K = 4) per vector, scalar C as K products. A depthwise
    convolution's taps (passes/dot_taps.py): x the K int32 vectors of the lanes' own activations,
    lane l summing x[j][l] * w[l * K + j]."""

    x: tuple[Expr, ...]
    w: Load

    @property
    def lanes(self) -> int:
        return self.w.lanes // len(self.x)


Expr = Union[
    Const, Load, Lookup, LocalRef, Broadcast, Binary, Select, Call, Fma, Cast, Requantize, RequantizeFixed, Dot
]

BINARY_OPS = tuple(BinaryOp)
COMPARISONS = tuple(Comparison)
FUNCTIONS = tuple(MathFunction)

# ---------------------------------------------------------------------------- statements

LOOP_KINDS = tuple(LoopKind)


@dataclass(frozen=True)
class Loop:
    """for var in [0, extent). `parallel`: iterations are independent (a spatial, not a reduction,
    axis), set by the lowering. `kind` is a pass's mark that the same pass materialises (only serial
    loops leave a pipeline). `lanes`: the vector width of one iteration, i.e. how many elements along
    the loop's axis each iteration covers — set when vectorize marks the loop and kept on the loop
    over vector blocks it becomes; 1 for every scalar loop."""

    var: str
    extent: int
    body: tuple[Stmt, ...]
    kind: LoopKind = LoopKind.SERIAL
    parallel: bool = False
    lanes: int = 1

    def __post_init__(self) -> None:
        coerce(self, kind=LoopKind)


@dataclass(frozen=True)
class Store:
    buffer: str
    index: Affine
    value: Expr


@dataclass(frozen=True)
class Let:
    """Declares a mutable local (scalar or vector) initialised to `init`, visible in `body`."""

    name: str
    init: Expr
    body: tuple[Stmt, ...]


@dataclass(frozen=True)
class Assign:
    name: str
    value: Expr


@dataclass(frozen=True)
class Bound:
    """lo <= expr < hi; a side that is None needs no check."""

    expr: Affine
    lo: int | None
    hi: int | None

    def holds(self) -> bool | None:
        """True or False when expr is constant, else None."""
        if not self.expr.is_const:
            return None
        v = self.expr.const
        return (self.lo is None or self.lo <= v) and (self.hi is None or v < self.hi)


@dataclass(frozen=True)
class If:
    """Runs body when every bound holds: the border checks of padded windows."""

    bounds: tuple[Bound, ...]
    body: tuple[Stmt, ...]


Stmt = Union[Loop, Store, Let, Assign, If]

# ---------------------------------------------------------------------------- program

BUFFER_ROLES = tuple(BufferRole)


@dataclass(frozen=True)
class Buffer:
    """A flat array of `dtype`. `shape` and `layout` are documentation for the reader of the C."""

    name: str
    size: int
    role: BufferRole
    shape: tuple[int, ...] = ()
    layout: Layout = Layout.UNSPECIFIED
    onnx_name: str = ""
    offset: int | None = None  # floats into the arena (internal) or the weights blob (constant), by plan-memory
    dtype: DType = DType.FLOAT32

    def __post_init__(self) -> None:
        coerce(self, role=BufferRole, layout=Layout, dtype=DType)

    @property
    def floats(self) -> int:
        """The float32 slots the buffer takes in the arena or the weights blob (rounded up)."""
        return -(-self.size * self.dtype.bytes // 4)


@dataclass(frozen=True)
class Kernel:
    """One layer: the unit that unroll levels count loops in. `overlapping_stores`: some elements are
    stored more than once (a vector tail that overlaps the vector before it), so the kernel must not
    compute in place (plan-memory reads it instead of assuming every element is written once)."""

    name: str
    op: str
    body: tuple[Stmt, ...]
    overlapping_stores: bool = False


@dataclass(frozen=True)
class ArenaPlan:
    """One block of memory holds every internal buffer, each at its Buffer.offset.

    `floats` is the arena size; `activation_floats` the sum of the activation buffers the plan
    started from (the memory they would take without reuse); offsets are multiples of `align_floats`.
    When `weights_floats` > 0 the constant buffers live in a weights blob of that size (offsets in
    Buffer.offset too) that the caller passes, instead of in the C file."""

    floats: int
    activation_floats: int
    align_floats: int
    weights_floats: int = 0


@dataclass(frozen=True)
class StoredValue:
    """Where the lowering stored a graph value and when it is complete, for the debug build that reads
    every layer's output back (verify --per-layer): the buffer, the logical shape, the physical
    order of its dims (outermost first), its halo ((before, after) per dim; () for none) and the
    kernel after which the buffer holds the value."""

    value: str
    buffer: str
    shape: tuple[int, ...]
    order: tuple[int, ...]
    halo: tuple[tuple[int, int], ...]
    layer: str


@dataclass(frozen=True)
class Program:
    """Buffers (inputs and outputs in ONNX graph order) and kernels run in order.
    `constants` holds the data of the constant buffers, keyed by buffer name; `values` where each
    node output of the graph lives (not part of the code: equality ignores it)."""

    name: str
    buffers: tuple[Buffer, ...]
    kernels: tuple[Kernel, ...]
    constants: dict[str, np.ndarray] = field(default_factory=dict)
    arena: ArenaPlan | None = None  # set by the plan-memory pass
    values: tuple[StoredValue, ...] = ()

    def __eq__(self, other: object) -> bool:
        """Structural equality, constants included (same names, dtypes, shapes and values)."""
        if not isinstance(other, Program):
            return NotImplemented
        same = (self.name, self.buffers, self.kernels, self.arena)
        return same == (other.name, other.buffers, other.kernels, other.arena) and same_arrays(
            self.constants, other.constants
        )

    def buffer(self, name: str) -> Buffer:
        for buf in self.buffers:
            if buf.name == name:
                return buf
        raise KeyError(name)

    def role(self, role: str) -> tuple[Buffer, ...]:
        return tuple(b for b in self.buffers if b.role == role)


# ---------------------------------------------------------------------------- generic traversal


def children(expr: Expr) -> tuple[Expr, ...]:
    if isinstance(expr, Broadcast):
        return (expr.value,)
    if isinstance(expr, Binary):
        return (expr.a, expr.b)
    if isinstance(expr, Select):
        return (expr.lhs, expr.rhs, expr.then, expr.otherwise)
    if isinstance(expr, Call):
        return (expr.arg,)
    if isinstance(expr, Lookup):
        return (expr.index,)
    if isinstance(expr, Fma):
        return (expr.a, expr.b, expr.c)
    if isinstance(expr, Cast | Requantize):
        return (expr.value,)
    if isinstance(expr, RequantizeFixed):
        return (expr.value, expr.multiplier, expr.shift)
    if isinstance(expr, Dot):
        return (*expr.x, expr.w)
    return ()


def with_children(expr: Expr, new: tuple[Expr, ...]) -> Expr:
    """expr with its children (in the order `children` gives them) replaced."""
    if isinstance(expr, Broadcast):
        return Broadcast(new[0], expr.lanes)
    if isinstance(expr, Binary):
        return Binary(expr.op, *new)
    if isinstance(expr, Select):
        return Select(expr.cmp, *new)
    if isinstance(expr, Call):
        return Call(expr.fn, new[0])
    if isinstance(expr, Lookup):
        return replace(expr, index=new[0])
    if isinstance(expr, Fma):
        return Fma(*new)
    if isinstance(expr, Cast | Requantize):
        return replace(expr, value=new[0])
    if isinstance(expr, RequantizeFixed):
        return replace(expr, value=new[0], multiplier=new[1], shift=new[2])
    if isinstance(expr, Dot):
        return Dot(tuple(new[:-1]), new[-1])
    return expr


def map_expr(expr: Expr, fn) -> Expr:
    """Rebuilds expr bottom-up, applying fn to every node after its children."""
    kids = children(expr)
    if kids:
        expr = with_children(expr, tuple(map_expr(k, fn) for k in kids))
    return fn(expr)


def read_buffer(expr: Expr) -> str | None:
    """The buffer a Load or a Lookup reads (None for every other node)."""
    if isinstance(expr, Load):
        return expr.buffer
    return expr.table if isinstance(expr, Lookup) else None


def walk_exprs(expr: Expr):
    """Yields expr and all its sub-expressions."""
    yield expr
    for child in children(expr):
        yield from walk_exprs(child)


def stmt_exprs(stmt: Stmt) -> tuple[Expr, ...]:
    """The expressions a statement evaluates itself (not those of nested statements)."""
    if isinstance(stmt, Store | Assign):
        return (stmt.value,)
    if isinstance(stmt, Let):
        return (stmt.init,)
    return ()


def walk_stmts(body: tuple[Stmt, ...]):
    """Yields every statement, depth first, nested ones included."""
    for stmt in body:
        yield stmt
        if isinstance(stmt, Loop | Let | If):
            yield from walk_stmts(stmt.body)


def walk_bodies(body: tuple[Stmt, ...]):
    """Yields body and the body of every statement in it, nested ones included."""
    yield body
    for stmt in body:
        if isinstance(stmt, Loop | Let | If):
            yield from walk_bodies(stmt.body)


def expr_dots(expr: Expr) -> list[Dot]:
    """The dot products in expr, itself included."""
    return [e for e in walk_exprs(expr) if isinstance(e, Dot)]


def body_dots(body: tuple[Stmt, ...]) -> list[Dot]:
    """The dot products the statements of body evaluate, nested statements included."""
    return [dot for stmt in walk_stmts(body) for expr in stmt_exprs(stmt) for dot in expr_dots(expr)]


def map_body(body: tuple[Stmt, ...], fn) -> tuple[Stmt, ...]:
    """Rebuilds statements bottom-up; fn(stmt) returns a replacement statement or a tuple of them."""
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop | Let | If):
            stmt = _with_body(stmt, map_body(stmt.body, fn))
        result = fn(stmt)
        out.extend(result if isinstance(result, tuple) else (result,))
    return tuple(out)


def _with_body(stmt: Loop | Let | If, body: tuple[Stmt, ...]) -> Stmt:
    return replace(stmt, body=body)


def map_stmt_exprs(stmt: Stmt, fn) -> Stmt:
    """Applies map_expr(., fn) to the expressions a statement evaluates itself."""
    if isinstance(stmt, Store | Assign):
        return replace(stmt, value=map_expr(stmt.value, fn))
    if isinstance(stmt, Let):
        return replace(stmt, init=map_expr(stmt.init, fn))
    return stmt
