"""Loop pass `vectorize`: SIMD in the target's vector widths over output channels (the paper's principle 4), or over
output pixels where the layer was lowered for that (see the vectorize-pixels pass).

Marks, in each kernel, the innermost parallel loop that every store walks contiguously (a loop
whose border checks depend on it is first split into its border iterations, left scalar, and the
interior, where the checks hold and are dropped), then materialises it: a loop over vector blocks
whose expressions have N lanes, plus a scalar tail when the extent is not a multiple of N. With
several widths, widest first (avx512: 16/8/4), the extent is split greedily: blocks of the widest
width that fits, the remainder in the next narrower width, and so on; only what is left after the
narrowest is scalar (12 channels at 16/8/4: one 8-lane and one 4-lane block). Loads that do not
depend on the loop become broadcasts. A call (exp, ...) becomes a vector call: backends without a
vector version call the function per lane.

The int8 kernels are vectorised the same way on targets with integer vectors (Target.integer_vectors):
int32 accumulators over output channels, an invariant integer operand (the input value) broadcast
whole, requantised per vector; where the target has integer dot products, the reduction over input
channels first becomes dot products of 2 or 4 channels (dot_product.py), and with Target.tap_dots a
depthwise's interior columns (split from the borders, dot_taps.py) dot products of 2 or 4 taps whose
activations are vectors, each lane its own channel's. Integer Winograd (Target.int16_dots) stores its
transformed inputs as int16 vectors and runs its GEMMs in dots of int16 pairs. QuantizeLinear runs as its
float quotient requantised per vector, DequantizeLinear as its float product; an int8 MaxPool takes
int32 maxima and QLinearGlobalAveragePool int32 sums over channels; the lookups (256-entry tables)
stay scalar gathers; QLinearAdd, on targets with FMA, in vector fused
multiply-adds as onnxruntime computes it. ConvInteger and MatMulInteger run as QLinearConv and
QLinearDense do, their int32 sums stored as they are or dequantised in float32 vectors
(dequantized_vectors.py). A kernel in the fixed-point form stays scalar."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir.analysis import is_accumulator, vector_instructions
from ..ir.applicability import FUSED_OPS, fused_ops_vectorise, integer_kernel_vectorises
from ..ir.dtypes import buffer_dtypes, is_integer_kernel
from ..ir.kinds import BufferRole, DType, LoopKind
from ..ir.loops import (
    Affine,
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
    Kernel,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Requantize,
    RequantizeFixed,
    Select,
    Stmt,
    Store,
    expr_dots,
    map_body,
    map_stmt_exprs,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from ..ir.target import Target
from ..lowering.winograd_integer import WINOGRAD_OP
from .dequantized_vectors import DEQUANTIZING_OPS, dequantized_vectors
from .dot_product import dot_products, multiply_accumulate
from .dot_taps import split_tap_borders
from .substitute import interior, iterations, substitute_body


def vectorize(program: Program, target: Target) -> Program:
    """SIMD in the target's vector widths (widest first); a target without vectors changes nothing."""
    widths = target.vector_widths
    if not widths:
        return program
    if list(widths) != sorted(set(widths), reverse=True):
        raise ValueError(f"vector widths {widths} are not strictly decreasing")
    integer = {k.name for k in program.kernels if is_integer_kernel(k, program)}
    vectorizable_integer = {k.name for k in program.kernels if k.name in integer and _integer_vectorizable(k, target)}
    program = dot_products(split_tap_borders(program, vectorizable_integer, target), vectorizable_integer, target)
    kernels = []
    for kernel in program.kernels:
        if kernel.name in integer and kernel.name not in vectorizable_integer:
            kernels.append(kernel)
            continue
        if kernel.op == "Band" and kernel.name in integer:
            floats = {b.name for b in program.buffers if b.dtype == DType.FLOAT32}
            scratch = {b.name for b in program.role(BufferRole.INTERNAL) if b.dtype in (DType.INT16, DType.INT32)}
            int16 = scratch if target.int16_dots else set()
            body = _mark_band_stages(kernel.body, widths, floats, int16, fused_ops_vectorise(target))
        else:
            body = mark_vector_loop(kernel.body, widths)
        overlaps = any(
            isinstance(s, Loop) and s.kind == LoopKind.VECTORIZED and _overlapped_tail_pays(s, widths)
            for s in walk_stmts(body)
        )
        body = map_body(body, lambda s: materialize(s, widths))
        if kernel.op in DEQUANTIZING_OPS:
            body = dequantized_vectors(body, buffer_dtypes(program))
        if kernel.name in integer and not target.fma:
            body = map_body(body, lambda s: map_stmt_exprs(s, _sum_of_fma_by_one))
        kernels.append(replace(kernel, body=body, overlapping_stores=kernel.overlapping_stores or overlaps))
    return replace(program, kernels=tuple(kernels))


# the multiply-accumulate kernels, QuantizeLinear (float division, then requantised as they are), the
# int32 sums of QLinearGlobalAveragePool, the int32 maxima of an int8 MaxPool, and DequantizeLinear
# (one float32 product of the int32 difference), QLinearAveragePool's float32 sums (_unfused_sum): the
# same arithmetic in every lane as in scalar C; of an int8 band kernel (lowering/stream.py), the
# convolutions' and QuantizeLinear's nests (_mark_band_stages)
INTEGER_OPS = (
    "QLinearConv",
    "QLinearDense",
    *DEQUANTIZING_OPS,
    "QuantizeLinear",
    "QLinearGlobalAveragePool",
    "MaxPool",
    "DequantizeLinear",
    "QLinearAveragePool",
    "Band",
)


def _integer_vectorizable(kernel: Kernel, target: Target) -> bool:
    """One of INTEGER_OPS, a QLinearAdd on a target with a fused multiply-add, or an integer Winograd
    (int16 scratch) on one with Target.int16_dots, where integer_kernel_vectorises: integer vectors and
    no fixed-point requantisation in the kernel."""
    fixed = any(
        isinstance(e, RequantizeFixed) for s in walk_stmts(kernel.body) for t in stmt_exprs(s) for e in walk_exprs(t)
    )
    ops = INTEGER_OPS + (FUSED_OPS if fused_ops_vectorise(target) else ())
    ops += (WINOGRAD_OP,) if target.int16_dots else ()
    return integer_kernel_vectorises(target, fixed) and kernel.op in ops


# ---------------------------------------------------------------------------- choice


def mark_vector_loop(body: tuple[Stmt, ...], widths: int | tuple[int, ...]) -> tuple[Stmt, ...]:
    """Marks the innermost eligible loop on each path (loops already marked are kept) with the
    widest width that fits its extent."""
    widths = (widths,) if isinstance(widths, int) else widths

    def mark(stmt: Stmt) -> Stmt | tuple[Stmt, ...]:
        if not isinstance(stmt, Loop) or stmt.kind != LoopKind.SERIAL:
            return stmt
        if any(isinstance(s, Loop) and s.kind == LoopKind.VECTORIZED for s in walk_stmts(stmt.body)):
            return stmt
        if vectorizable(stmt, widths[-1]):
            return _marked(stmt, widths)
        first, last = interior(stmt)
        if last - first < widths[-1] or not vectorizable(stmt, widths[-1], borders=True):
            return stmt
        inner = iterations(stmt, first, last, prune=True)[0]
        return (*iterations(stmt, 0, first), _marked(inner, widths), *iterations(stmt, last, stmt.extent))

    return map_body(body, mark)


def _marked(loop: Loop, widths: tuple[int, ...]) -> Loop:
    return replace(loop, kind=LoopKind.VECTORIZED, lanes=next(w for w in widths if w <= loop.extent))


def vectorizable(loop: Loop, lanes: int, borders: bool = False) -> bool:
    """Parallel, at least one full vector of `lanes`, stores contiguous along the loop, loads
    contiguous or invariant, no branch or outer local that depends on the loop. With `borders`,
    border checks that depend on the loop are allowed (the caller splits off their iterations)."""
    if not loop.parallel or loop.extent < lanes:
        return False
    var = loop.var
    declared = {s.name for s in walk_stmts(loop.body) if isinstance(s, Let)}
    stores = 0
    for stmt in walk_stmts(loop.body):
        if isinstance(stmt, Store):
            stores += 1
            if stmt.index.coeff(var) != 1:
                return False
        if isinstance(stmt, Assign) and stmt.name not in declared:
            return False
        if isinstance(stmt, If) and not borders and any(b.expr.coeff(var) for b in stmt.bounds):
            return False
        for expr in stmt_exprs(stmt):
            dots = expr_dots(expr)
            if any(not _dot_vectorizable(d, var) for d in dots):
                return False
            weights = {d.w for d in dots}
            for e in walk_exprs(expr):
                if isinstance(e, Load) and e not in weights and e.index.coeff(var) not in (0, 1):
                    return False
    return stores > 0


def _dot_vectorizable(dot: Dot, var: str) -> bool:
    """The lanes of a dot product run along `var`: its weights are packed K per lane, its
    activations do not depend on var (shared by all lanes) or all walk it contiguously (each lane
    its own channel's taps)."""
    steps = {e.index.coeff(var) for x in dot.x for e in walk_exprs(x) if isinstance(e, Load)}
    return steps in ({0}, {1}, set()) and dot.w.index.coeff(var) == len(dot.x)


def _mark_band_stages(
    body: tuple[Stmt, ...], widths: tuple[int, ...], floats: set[str], scratch: set[str], fused: bool
) -> tuple[Stmt, ...]:
    """An int8 band kernel's body with its convolutions' and QuantizeLinear's nests marked: through the
    band's serial loops (over bands, nested runs, a run's rows) and border checks, each layer's nest (a
    parallel loop) is marked where it multiply-accumulates, quantises floats (`floats`: the float
    buffers) or is an integer Winograd transform (it stores or loads `scratch`: V's int16 and M's int32
    buffers, on a target with Target.int16_dots) or, with `fused` (FUSED_OPS vectorise), is a QLinearAdd
    (_adds), as run whole; the other layers (table lookups,
    pooling, the line buffers' shifts and the interleaving of a quantised row: 8-bit loads and stores
    the integer vectors do not widen) stay scalar."""
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, If) or (isinstance(stmt, Loop) and not stmt.parallel):
            stmt = replace(stmt, body=_mark_band_stages(stmt.body, widths, floats, scratch, fused))
        elif (
            any(_multiply_accumulates(s) for s in walk_stmts((stmt,)))
            or _quantizes(stmt, floats)
            or _uses(stmt, scratch)
            or (fused and _adds(stmt))
        ):
            out += mark_vector_loop((stmt,), widths)
            continue
        out.append(stmt)
    return tuple(out)


def _uses(stmt: Stmt, buffers: set[str]) -> bool:
    """Whether the nest stores into or loads from one of `buffers`."""
    stores = {s.buffer for s in walk_stmts((stmt,)) if isinstance(s, Store)}
    loads = {e.buffer for s in walk_stmts((stmt,)) for t in stmt_exprs(s) for e in walk_exprs(t) if isinstance(e, Load)}
    return bool((stores | loads) & buffers)


def _quantizes(stmt: Stmt, floats: set[str]) -> bool:
    """A nest whose stores are all requantised values of float loads: QuantizeLinear's (lowering/quantized.py)."""
    stores = [s for s in walk_stmts((stmt,)) if isinstance(s, Store)]
    loads = [e for s in stores for e in walk_exprs(s.value) if isinstance(e, Load)]
    return bool(loads) and all(isinstance(s.value, Requantize) for s in stores) and {e.buffer for e in loads} <= floats


def _adds(stmt: Stmt) -> bool:
    """A nest whose stores are all requantised fused multiply-adds: QLinearAdd's (lowering/quantized_add.py)."""
    stores = [s for s in walk_stmts((stmt,)) if isinstance(s, Store)]
    fused = (any(_fused_multiply_add(e) for e in walk_exprs(s.value)) for s in stores)
    return bool(stores) and all(isinstance(s.value, Requantize) for s in stores) and all(fused)


def _multiply_accumulates(stmt: Stmt) -> bool:
    """acc += dot(...) (dot_product.py), or a loop of acc += int32(x) * int32(w), that one statement
    under a border check too (a depthwise's border columns, split from its dot products by dot_taps.py:
    vectors over channels there as in the layer run whole)."""
    if isinstance(stmt, Loop):
        guarded = len(stmt.body) == 1 and isinstance(stmt.body[0], If)
        body = stmt.body[0].body if guarded else stmt.body
        return multiply_accumulate(replace(stmt, body=body)) is not None
    return isinstance(stmt, Assign) and bool(expr_dots(stmt.value))


# ---------------------------------------------------------------------------- mechanism


def materialize(stmt: Stmt, widths: tuple[int, ...] = ()) -> Stmt | tuple[Stmt, ...]:
    """A marked loop as blocks of its width, then of each narrower width of `widths` that fits the
    rest, then a scalar tail; or, where that pays, blocks of its width and one more ending at the
    last iteration."""
    if not isinstance(stmt, Loop) or stmt.kind != LoopKind.VECTORIZED:
        return stmt
    var, start = stmt.var, 0
    out: list[Stmt] = []
    overlap = _overlapped_tail_pays(stmt, widths)
    for lanes in (stmt.lanes,) if overlap else (stmt.lanes, *(w for w in widths if w < stmt.lanes)):
        blocks = (stmt.extent - start) // lanes
        if not blocks:
            continue
        # Which loads become vector loads is decided on the original indices, before var is scaled.
        vector = _vector_body(stmt.body, var, lanes, set())
        if blocks == 1:
            out += substitute_body(vector, {var: Affine.of(start)})
        else:
            index = Affine.of(var) * lanes + start
            out.append(Loop(var, blocks, substitute_body(vector, {var: index}), parallel=True, lanes=lanes))
        start += blocks * lanes
    if overlap:
        return (*out, *substitute_body(vector, {var: Affine.of(stmt.extent - stmt.lanes)}))
    tail = stmt.extent - start
    if tail == 1:
        out += substitute_body(stmt.body, {var: Affine.of(start)})
    elif tail:
        out.append(Loop(var, tail, substitute_body(stmt.body, {var: Affine.of(start) + var}), parallel=True))
    return tuple(out)


def _overlapped_tail_pays(loop: Loop, widths: tuple[int, ...]) -> bool:
    """Whether the iterations after the last full vector are better done as one more full vector
    ending at the last iteration, overlapping the one before: when they would otherwise take more
    than one instruction (narrower blocks, scalars) and redoing an iteration changes nothing (no
    buffer the loop stores to is read in it). The kernel is then marked as storing some elements twice
    (plan-memory keeps it out of place). Only for reductions (convolutions, pooling): an elementwise
    kernel keeps its scalar tail, which costs little there and lets it compute in place."""
    rest = loop.extent % loop.lanes
    if not rest or loop.extent < loop.lanes:
        return False
    if not any(is_accumulator(s) for s in loop.body):
        return False
    if vector_instructions(rest, tuple(w for w in widths if w < loop.lanes)) <= 1:
        return False
    stored = {s.buffer for s in walk_stmts(loop.body) if isinstance(s, Store)}
    loaded = {
        e.buffer
        for st in walk_stmts(loop.body)
        for top in stmt_exprs(st)
        for e in walk_exprs(top)
        if isinstance(e, Load)
    }
    return not stored & loaded


def _vector_body(body: tuple[Stmt, ...], var: str, lanes: int, vector_locals: set[str]) -> tuple[Stmt, ...]:
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Store):
            out.append(Store(stmt.buffer, stmt.index, _vector(stmt.value, var, lanes, vector_locals)))
        elif isinstance(stmt, Let):
            inner = vector_locals | {stmt.name}
            init = _vector(stmt.init, var, lanes, vector_locals)
            out.append(Let(stmt.name, init, _vector_body(stmt.body, var, lanes, inner)))
        elif isinstance(stmt, Assign):
            out.append(Assign(stmt.name, _vector(stmt.value, var, lanes, vector_locals)))
        else:
            out.append(replace(stmt, body=_vector_body(stmt.body, var, lanes, vector_locals)))
    return tuple(out)


def _vector(e: Expr, var: str, lanes: int, vector_locals: set[str]) -> Expr:
    """The lanes-wide version of e; operands that do not vary along the loop are broadcast."""
    if isinstance(e, Load):
        return Load(e.buffer, e.index, lanes) if e.index.coeff(var) else Broadcast(e, lanes)
    if isinstance(e, Const):
        return Const(e.values * lanes, e.dtype) if e.dtype.is_integer else Const.splat(e.values[0], lanes)
    if isinstance(e, Dot):
        per_lane = any(isinstance(n, Load) and n.index.coeff(var) for x in e.x for n in walk_exprs(x))
        xs = tuple(_vector(x, var, lanes, vector_locals) for x in e.x) if per_lane else e.x
        return Dot(xs, Load(e.w.buffer, e.w.index, lanes * len(e.x)))
    fused = _fused_multiply_add(e) or _product_then_sum(e) or _unfused_sum(e)
    if fused is not None:
        return _vector(fused, var, lanes, vector_locals)
    if isinstance(e, Fma):
        return Fma(*(_vector(x, var, lanes, vector_locals) for x in (e.a, e.b, e.c)))
    if isinstance(e, Cast | Binary) and _invariant_integer(e, var, vector_locals):
        return Broadcast(e, lanes)  # x - x_zero_point: one broadcast, not a vector subtraction
    if isinstance(e, Cast | Requantize):
        return replace(e, value=_vector(e.value, var, lanes, vector_locals))
    if isinstance(e, LocalRef):
        return LocalRef(e.name, lanes) if e.name in vector_locals else Broadcast(e, lanes)
    if isinstance(e, Binary):
        return Binary(e.op, _vector(e.a, var, lanes, vector_locals), _vector(e.b, var, lanes, vector_locals))
    if isinstance(e, Select):
        parts = (_vector(x, var, lanes, vector_locals) for x in (e.lhs, e.rhs, e.then, e.otherwise))
        return Select(e.cmp, *parts)
    if isinstance(e, Call):
        return Call(e.fn, _vector(e.arg, var, lanes, vector_locals))
    raise TypeError(f"cannot vectorize {e!r}")


def _fused_multiply_add(e: Expr) -> Fma | None:
    """float32(double(x) * r + double(c)), the scalar spelling of a fused multiply-add of an integer x
    (lowering/quantized_add.py), as the Fma a vector computes it in one rounding; None for anything else."""
    if not (isinstance(e, Cast) and e.dtype == DType.FLOAT32 and isinstance(e.value, Binary) and e.value.op == "+"):
        return None
    product, addend = e.value.a, e.value.b
    if not (isinstance(product, Binary) and product.op == "*" and isinstance(product.b, Const)):
        return None
    x, ratio = product.a, product.b
    integer = isinstance(x, Cast) and isinstance(x.value, Cast) and x.value.dtype.is_integer
    if not (integer and x.dtype == DType.FLOAT64 and isinstance(addend, Cast) and addend.dtype == DType.FLOAT64):
        return None
    if ratio.dtype != DType.FLOAT64 or float(np.float32(ratio.values[0])) != ratio.values[0]:
        return None
    return Fma(Cast(DType.FLOAT32, x.value), Const.splat(ratio.values[0]), addend.value)


def _product_then_sum(e: Expr) -> Fma | None:
    """float32(double(float32(double(x) * r)) + c), QLinearMul's scalar spelling of two float32
    operations on an integer x of at most 24 bits (lowering/quantized_mul.py), as a vector product and
    Fma(product, 1, c): the sum rounded once, as scalar C rounds it; a vector multiply feeding a vector
    add the C compiler would contract into one rounding (GCC does, -ffp-contract=fast), an Fma by 1 it
    does not. None for anything else."""
    if not (isinstance(e, Cast) and e.dtype == DType.FLOAT32 and isinstance(e.value, Binary) and e.value.op == "+"):
        return None
    rounded, addend = e.value.a, e.value.b
    if not (isinstance(rounded, Cast) and rounded.dtype == DType.FLOAT64 and _float32_constant(addend)):
        return None
    inner = rounded.value
    if not (isinstance(inner, Cast) and inner.dtype == DType.FLOAT32 and isinstance(inner.value, Binary)):
        return None
    product = _float32_product(inner.value)
    return None if product is None else Fma(product, Const.splat(1.0), Const.splat(addend.values[0]))


def _unfused_sum(e: Expr) -> Fma | None:
    """acc + float32(double(x) * r) of an integer x and a float32 r (QLinearAveragePool's sum of its
    dequantised taps, lowering/quantized.py; the double product is exact) as Fma(x * r, 1, acc): two
    roundings, as onnxruntime and scalar C compute it, where a vector multiply feeding a vector add
    would be contracted into one."""
    if not (isinstance(e, Binary) and e.op == "+" and isinstance(e.a, LocalRef) and isinstance(e.b, Cast)):
        return None
    rounded = e.b
    if rounded.dtype != DType.FLOAT32 or not isinstance(rounded.value, Binary):
        return None
    product = _float32_product(rounded.value)
    return None if product is None else Fma(product, Const.splat(1.0), e.a)


def _float32_product(e: Binary) -> Binary | None:
    """double(x) * r of an integer x (at most 24 bits) and a float32 constant r, exact in double, as
    the float32 product a vector computes: the same value once rounded to float32; None otherwise."""
    x, ratio = e.a, e.b
    integer = (
        isinstance(x, Cast)
        and x.dtype == DType.FLOAT64
        and any(isinstance(n, Cast) and n.dtype.is_integer for n in walk_exprs(x.value))
    )
    if e.op != "*" or not integer or not _float32_constant(ratio):
        return None
    return Binary("*", Cast(DType.FLOAT32, x.value), Const.splat(ratio.values[0]))


def _sum_of_fma_by_one(e: Expr) -> Expr:
    """Fma(a, 1, c) as a + c (one rounding either way) where no compiler can fuse a's product into it
    (a target without FMA): ssse3 adds, not computes in double (Target.fma_in_double)."""
    if isinstance(e, Fma) and isinstance(e.b, Const) and set(e.b.values) == {1.0}:
        return Binary("+", e.a, e.c)
    return e


def _float32_constant(e: Expr) -> bool:
    """A double constant that is a float32 value."""
    return isinstance(e, Const) and e.dtype == DType.FLOAT64 and float(np.float32(e.values[0])) == e.values[0]


def _invariant_integer(e: Expr, var: str, vector_locals: set[str]) -> bool:
    """An integer expression (it holds a Cast: float kernels reach here without one) that does not
    depend on the vectorised loop."""
    nodes = list(walk_exprs(e))
    return any(isinstance(n, Cast) for n in nodes) and not any(
        (isinstance(n, Load) and n.index.coeff(var)) or (isinstance(n, LocalRef) and n.name in vector_locals)
        for n in nodes
    )
