"""Part of the loop pass `vectorize`: the int8 kernels' reduction over input channels as dot products
of K channels (loops.Dot) on targets that have them (Target.dot_uint8, dot_int8: K = 2, pmaddwd on
int16 pairs; K = 4, vpdpbusd on u8 x s8 quads), and K = Target.dot_uint8_int16 (pmaddubsw quads) for
uint8 activations where the layer's weights are proven never to saturate the int16 pair sums (and, with
Target.int16_dots, K = 2 of int16 activations and int16 weights: integer Winograd's GEMMs; with
Target.centred_weight_dots, K = 2 of 8-bit activations and the int16 weights minus their zero points
that ConvInteger, MatMulInteger and QLinear ops with weight zero points or uint8 weights have); layers
that fail the proof keep pmaddwd pairs (splitting their weights in two halves that pass, two pmaddubsw
per quad, measured no faster than the pairs with twice the weight bytes: benchmarks/int8_dot_forms.py).

    for ci < C: acc += int32(x[.. ci ..]) * int32(w[lead + Cs * ci + co])   (x minus its zero point, or not)
becomes
    for cp < C / K: acc += dot(x[.. K cp ..], ..., x[.. K cp + K - 1 ..]; wK[lead' + K Cs cp + K co : K])
and, when K does not divide C, one more dot of the last channels, the missing ones read as 0.

On targets with Target.tap_dots the same rewrite takes the taps of a convolution of one input channel
per group (the loop over kernel columns): a first layer's (one input channel, the taps' activations
shared by all lanes) and a depthwise's (x depends on the channel too: the dots' activations are then
vectors, each lane its own channel's K taps). passes/dot_taps.py splits off the border columns first,
each its own code: there the taps outside the image are read as 0 (x - zero point is 0 on the padding,
so the products are the loop's) and the groups of K taps all outside are left out.

The weights [lead..., C, Cs] are repacked at generation time as wK [lead..., C / K (rounded up), Cs, K]
(the missing channels' weights 0; pairs as int16 where Target.dot2_int16_weights): the K weights of
one output channel side by side, the output channels one after another, exactly the order one vector
instruction reads them. Exact: the products
and sums are those of the loop, in int32.

Where the dot takes int8 activations only (Target.dot_int8_activations: AArch64 sdot), an activation
x - zero_point is read as x - offset, offset 128 for uint8 (x ^ 0x80 as a byte) and 0 for int8, and
acc += (offset - zero_point) * sum_ci w[lead..., ci, co] follows the dots: a constant array [lead...,
Cs] of generation time, exact in int32, added where the dots run (inside the border checks). Where it
takes uint8 activations only (Target.dot_uint8_activations: vpdpbusd), signed ones are read the other way
round, offset -128 for int8 (x + 128, the byte x ^ 0x80) and 0 for uint8 minus a zero point: TFLite's
int8 models get the quads of nncg.quantize's uint8 ones. A depthwise's per-lane taps and the border
columns' taps keep their activations and the pairs (the correction would count the taps outside)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..ir.kinds import DType
from ..ir.loops import (
    Affine,
    Assign,
    Binary,
    Buffer,
    Cast,
    Const,
    Dot,
    Expr,
    If,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Stmt,
    read_buffer,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from ..ir.target import Target

INT32 = DType.INT32


def dot_products(program: Program, kernels: set[str], target: Target) -> Program:
    """The reductions of the named kernels as dot products where the target has them."""
    packer = _Packer(program)
    out = []
    for kernel in program.kernels:
        if kernel.name in kernels:
            kernel = replace(kernel, body=packer.body(kernel.body, {}, target))
        out.append(kernel)
    read = {read_buffer(e) for k in out for s in walk_stmts(k.body) for t in stmt_exprs(s) for e in walk_exprs(t)}
    unread = {name for name in packer.replaced if name not in read}
    buffers = tuple(b for b in program.buffers if b.name not in unread) + tuple(packer.added)
    constants = {n: a for n, a in program.constants.items() if n not in unread} | packer.arrays
    return replace(program, kernels=tuple(out), buffers=buffers, constants=constants)


class _Packer:
    """Rewrites reduction loops, packing each weight array once per K."""

    def __init__(self, program: Program):
        self.program = program
        self.buffers = {b.name: b for b in program.buffers}
        self.names = set(self.buffers)
        self.packed: dict[tuple[str, int], str] = {}  # (weights, K) -> packed weights
        self.corrections: dict[tuple[str, int], str] = {}  # (weights, offset difference) -> offset_correction
        self.added: list[Buffer] = []
        self.arrays: dict[str, np.ndarray] = {}
        self.replaced: set[str] = set()

    def body(self, body: tuple[Stmt, ...], extents: dict[str, int], target: Target) -> tuple[Stmt, ...]:
        out: list[Stmt] = []
        for stmt in body:
            if isinstance(stmt, Loop):
                rewritten = self.reduction(stmt, extents, target)
                if rewritten is not None:
                    out += rewritten
                    continue
                stmt = replace(stmt, body=self.body(stmt.body, extents | {stmt.var: stmt.extent}, target))
            elif isinstance(stmt, Let | If):
                stmt = replace(stmt, body=self.body(stmt.body, extents, target))
            out.append(stmt)
        return tuple(out)

    def reduction(self, loop: Loop, extents: dict[str, int], target: Target) -> tuple[Stmt, ...] | None:
        """The loop as dot products, or None when it is not `acc += int32(x) * int32(w)` over all the
        input channels of a constant int8 weight array."""
        inside = None  # the taps inside the image of a border column (passes/dot_taps.py), None: all
        if target.tap_dots and multiply_accumulate(loop) is None:
            loop, inside = _guarded_taps(loop)
        match = multiply_accumulate(loop)
        if match is None:
            return None
        acc, x, zero_point, w = match
        wbuf, xbuf = self.buffers.get(w.buffer), self.buffers.get(x.buffer)
        if wbuf is None or xbuf is None or w.buffer not in self.program.constants:
            return None
        # x - x_zero_point (a zero point the lowering did not fold) is signed whatever x's type
        signed = xbuf.dtype == DType.INT8 or zero_point
        # a depthwise's per-lane taps and a border column's taps keep the activations as they are
        per_lane = _per_lane(x, w, loop.var)
        eight_bit = xbuf.dtype in (DType.INT8, DType.UINT8)
        as_uint8 = bool(signed and target.dot_uint8_activations and inside is None and not per_lane and eight_bit)
        if signed and not as_uint8:
            k = target.dot_int8
        else:
            k = target.dot_uint8 if xbuf.dtype == DType.UINT8 or as_uint8 else 0
        array = self.program.constants[w.buffer]
        array = _squeezed(array) if target.tap_dots else array
        # int16 pairs: integer Winograd's GEMMs (int16 activations), or 8-bit activations times the
        # weights minus their zero points (int16, in [-255, 255]: the lowering's where those are not 0)
        int16 = xbuf.dtype == DType.INT16 and not zero_point and target.int16_dots
        centred = xbuf.dtype != DType.INT16 and array.dtype == np.int16 and target.centred_weight_dots and bool(k)
        wide_weights = centred or (int16 and array.dtype == np.int16)
        k = 2 if wide_weights else k
        if (
            not k
            or array.dtype != (np.int16 if wide_weights else np.int8)
            or array.ndim < 2
            or array.shape[-2] != loop.extent
        ):
            return None
        if (
            not (signed or wide_weights)
            and xbuf.dtype == DType.UINT8
            and target.dot_uint8_int16
            and pair_sums_fit_int16(array)
        ):
            k = target.dot_uint8_int16
        split = _split_index(w.index, loop.var, array.shape, extents)
        # a depthwise's per-lane taps take int8 weights only (the int16 templates share x in every lane)
        if split is None or (per_lane and (not target.tap_dots or centred)):
            return None
        lead, co = split
        c, cs = array.shape[-2:]
        index = lead * (-(-c // k) * k * cs) + co * k + Affine.of(loop.var) * (k * cs)
        wide = wide_weights or (k == 2 and target.dot2_int16_weights)
        packed = self.packed_buffer(w.buffer, array, k, np.int16 if wide else np.int8)
        channels, groups = loop.extent, loop.extent // k
        offset = zero_point
        if target.dot_int8_activations and k == 4:
            offset = 128 * (xbuf.dtype == DType.UINT8)
        elif as_uint8 and k == 4:
            offset = -128 * (xbuf.dtype == DType.INT8)
        if inside is not None and offset != zero_point:
            return None  # the offset's correction sums every tap's weights, the outside ones too

        def dot(group: Affine, count: int, taps: range | frozenset = range(channels)) -> Stmt:
            """acc += the dot of channels K group .. K group + count - 1 (the rest, and those not in
            `taps` where the group is a constant, read as 0)."""
            xs = tuple(
                _at_channel(x, offset, loop.var, group * k + j)
                if j < count and (not group.is_const or group.const * k + j in taps)
                else Const.integer(0)
                for j in range(k)
            )
            weights = Load(packed, index.substitute({loop.var: group}), k)
            return Assign(acc, Binary("+", LocalRef(acc), Dot(xs, weights)))

        if inside is not None:  # a border column: the groups holding a tap inside, the others skipped
            touched = sorted({tap // k for tap in inside})
            return (Loop(loop.var, 1, tuple(dot(Affine.of(g), min(k, channels - g * k), inside) for g in touched)),)
        # the groups stay a loop even of one iteration: register-block finds accumulators by their loops
        stmts: list[Stmt] = [Loop(loop.var, groups, (dot(Affine.of(loop.var), k),))] if groups else []
        if channels % k:
            stmts.append(dot(Affine.of(groups), channels % k))
        stmts = stmts if groups else [Loop(loop.var, 1, tuple(stmts))]
        if offset != zero_point:
            correction = self.offset_correction(w.buffer, array, offset - zero_point)
            stmts.append(Assign(acc, Binary("+", LocalRef(acc), Load(correction, lead * cs + co))))
        return tuple(stmts)

    def offset_correction(self, name: str, array: np.ndarray, difference: int) -> str:
        """difference * the sum over input channels of the weights `name` (`array`, [lead..., C, Cs]),
        as int32 [lead..., Cs]: what reading the activations `difference` too low takes from the dots."""
        if (name, difference) in self.corrections:
            return self.corrections[(name, difference)]
        sums = (array.astype(np.int64).sum(axis=-2) * difference).astype(np.int32)
        new = _fresh(f"{name}_offset", self.names)
        self.names.add(new)
        base = self.buffers[name]
        self.added.append(replace(base, name=new, size=sums.size, shape=sums.shape, offset=None, dtype=INT32))
        self.arrays[new] = sums
        self.corrections[(name, difference)] = new
        return new

    def packed_buffer(self, name: str, array: np.ndarray, k: int, dtype: type[np.integer]) -> str:
        """The weights of `name` (`array`) as [lead..., C / K, Cs, K] of `dtype` (int8, or int16 where
        Target.dot2_int16_weights), once per (array, K)."""
        if (name, k) in self.packed:
            return self.packed[(name, k)]
        *lead, c, cs = array.shape
        groups = -(-c // k)
        padded = np.zeros((*lead, groups * k, cs), dtype)
        padded[..., :c, :] = array
        packed = np.ascontiguousarray(np.moveaxis(padded.reshape(*lead, groups, k, cs), -2, -1))
        new = _fresh(f"{name}_dot{k}", self.names)
        self.names.add(new)
        base = self.buffers[name]
        wide = DType.INT16 if dtype == np.int16 else base.dtype
        self.added.append(replace(base, name=new, size=packed.size, shape=packed.shape, offset=None, dtype=wide))
        self.arrays[new] = packed
        self.packed[(name, k)] = new
        self.replaced.add(name)
        return new


def pair_sums_fit_int16(weights: np.ndarray) -> bool:
    """Whether no sum of two products of uint8 activations (0..255) and the int8 weights of input
    channels 2i and 2i + 1 ([lead..., C, Cs], the missing last channel 0) can leave int16, so that
    pmaddubsw never saturates: per pair 255 * (sum of its positive weights) <= 32767 and
    255 * (sum of its negative weights) >= -32768."""
    *lead, c, cs = weights.shape
    pairs = np.zeros((*lead, c + c % 2, cs), np.int32)
    pairs[..., :c, :] = weights
    pairs = pairs.reshape(*lead, -1, 2, cs)
    highest = 255 * np.maximum(pairs, 0).sum(axis=-2)
    lowest = 255 * np.minimum(pairs, 0).sum(axis=-2)
    return bool(highest.max(initial=0) <= np.iinfo(np.int16).max and lowest.min(initial=0) >= np.iinfo(np.int16).min)


def _squeezed(array: np.ndarray) -> np.ndarray:
    """A convolution's weights [k..., C, Cs] without C when it is 1 (a depthwise's [kh, kw, 1, Cs],
    or a first layer's of one input channel): the reduction over kernel columns then reads the
    second-last axis, as dots of K taps."""
    return array.reshape(array.shape[:-2] + array.shape[-1:]) if array.ndim > 2 and array.shape[-2] == 1 else array


def multiply_accumulate(loop: Loop) -> tuple[str, Load, int, Load] | None:
    """(acc, x load, x zero point, w load) of a loop whose one statement is acc += (int32(x) - zero
    point) * int32(w), the zero point 0 where there is no subtraction."""
    if len(loop.body) != 1 or not isinstance(loop.body[0], Assign):
        return None
    stmt = loop.body[0]
    value = stmt.value
    if not (isinstance(value, Binary) and value.op == "+" and value.a == LocalRef(stmt.name)):
        return None
    product = value.b
    if not (isinstance(product, Binary) and product.op == "*"):
        return None
    x, zero_point = product.a, 0
    if isinstance(x, Binary) and x.op == "-" and isinstance(x.b, Const) and x.b.dtype == INT32:
        x, zero_point = x.a, int(x.b.values[0])
    loads = [_widened_load(e) for e in (x, product.b)]
    if None in loads or not all(loop.var in load.index.vars for load in loads):
        return None
    return stmt.name, loads[0], zero_point, loads[1]


def _guarded_taps(loop: Loop) -> tuple[Loop, frozenset[int] | None]:
    """A border column's `for kw: if (check on kw alone) acc += ...` as the loop without the check and
    the taps kw for which it holds; the loop as it is, and None, for any other loop (or no tap inside)."""
    guard = loop.body[0] if len(loop.body) == 1 else None
    if not isinstance(guard, If) or any(set(b.expr.vars) - {loop.var} for b in guard.bounds):
        return loop, None
    inside = frozenset(
        tap
        for tap in range(loop.extent)
        if all(replace(b, expr=b.expr.substitute({loop.var: Affine.of(tap)})).holds() for b in guard.bounds)
    )
    return (replace(loop, body=guard.body), inside) if inside else (loop, None)


def _widened_load(e: Expr) -> Load | None:
    """The 8-bit load of int32(load)."""
    scalar = isinstance(e, Cast) and e.dtype == INT32 and isinstance(e.value, Load) and e.value.lanes == 1
    return e.value if scalar else None


def _split_index(
    index: Affine, var: str, shape: tuple[int, ...], extents: dict[str, int]
) -> tuple[Affine, Affine] | None:
    """w's index [lead..., C, Cs] at channel `var` 0 as (lead, co): lead counts [C, Cs] blocks, co
    the output channel in [0, Cs); None when it is not lead * C * Cs + Cs * var + co."""
    c, cs = shape[-2], shape[-1]
    block = c * cs
    if index.coeff(var) != cs:
        return None
    lead_terms, co_terms = {}, {}
    for name, coeff in index.terms:
        if name == var:
            continue
        if coeff % block == 0:
            lead_terms[name] = coeff // block
        else:
            co_terms[name] = coeff
    lead_const, co_const = divmod(index.const, block)
    co = Affine._make(co_terms, co_const)
    if any(name not in extents for name in co.vars):
        return None
    low, high = co.bounds(extents)
    if low < 0 or high >= cs:
        return None
    return Affine._make(lead_terms, lead_const), co


def _per_lane(x: Load, w: Load, var: str) -> bool:
    """Whether x walks the output channels as w does (a depthwise convolution's taps: each lane its
    own activations) rather than being shared by all of them (a grouped convolution's x depends on
    the group, but not on the output channel within it, along which the lanes run)."""
    return any(name != var and coeff == 1 and x.index.coeff(name) == 1 for name, coeff in w.index.terms)


def _at_channel(x: Load, zero_point: int, var: str, channel: Affine) -> Expr:
    value = Cast(INT32, replace(x, index=x.index.substitute({var: channel})))
    return Binary("-", value, Const.integer(zero_point)) if zero_point else value


def _fresh(name: str, taken: set[str]) -> str:
    candidate, n = name, 1
    while candidate in taken:
        candidate, n = f"{name}_{n}", n + 1
    return candidate
