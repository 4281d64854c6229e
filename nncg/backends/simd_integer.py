"""Backend: the SIMD printer's int8 part — int32 vectors of the vectorised int8 convolutions and
matrix products, printed from each width's `ints` table (vector_width.INTEGER_OPERATIONS): int32
loads and arithmetic, 8-bit loads widened to int32, dot products (`dot2`: int16 pairs; accumulated,
`dot2_add`: NEON's vmlal_s16, `dot4_add`: vpdpbusd's u8 x s8 or sdot's s8 x s8 quads; a width
without its template computes each lane in scalar C), the conversion to float, the float form of
requantisation and the narrowing 8-bit stores."""

from __future__ import annotations

from collections.abc import Iterator

from ..ir.dtypes import expr_dtype
from ..ir.kinds import DType
from ..ir.loops import (
    Binary,
    Broadcast,
    Cast,
    Const,
    Dot,
    Expr,
    Load,
    LocalRef,
    Program,
    Requantize,
    Stmt,
    Store,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from .c_text import c_affine, c_float, c_int
from .scalar import scalar_dot
from .vector_width import VectorWidth


class IntegerVectors:
    """Mixed into SimdPrinter, which has `dtypes`, `expr` and `width`."""

    integer_helpers_used: frozenset[tuple[int, str]] = frozenset()  # (lanes, key of the width's int_helpers)
    buffer_sizes: dict[str, int] = {}  # elements of each buffer, for reads of a whole quad (_quad_half)

    def with_integer_helpers(self, program: Program, buffer_dtypes: dict[str, DType]):
        self.buffer_sizes = {b.name: b.size for b in program.buffers}
        self.integer_helpers_used = frozenset(
            (lanes, key)
            for k in program.kernels
            for s in walk_stmts(k.body)
            for lanes, key in _helper_keys(s, buffer_dtypes)
            if lanes in self.widths and key in self.widths[lanes].int_helpers
        )
        return self

    def integer_helpers(self) -> list[str]:
        blocks = [self.widths[lanes].int_helpers[key] for lanes, key in sorted(self.integer_helpers_used, reverse=True)]
        return [line for block in blocks for line in ("", *block)]

    def is_integer_vector(self, e: Expr) -> bool:
        return isinstance(e, Cast | Requantize) or expr_dtype(e, self.dtypes, self.dtypes).is_integer

    def integer_store(self, store: Store, width: VectorWidth) -> str:
        dtype = self.dtypes[store.buffer]
        value = store.value
        if isinstance(value, Cast) and value.dtype == dtype:  # int32 lanes already in range (a MaxPool's maxima)
            value = value.value
        return width.ints[f"store_{dtype.value}"].format(
            address=f"&{store.buffer}[{c_affine(store.index)}]", value=self.expr(value)
        )

    def integer_vector(self, e: Expr, width: VectorWidth) -> str:
        ints = width.ints
        if isinstance(e, Load):
            return self._int32_load(e, ints)
        if isinstance(e, LocalRef):
            return e.name
        if isinstance(e, Const):
            return _integer_const(e.values, ints)
        if isinstance(e, Broadcast):
            return ints["splat"].format(value=self.expr(e.value))
        if isinstance(e, Binary) and e.op == "+" and isinstance(e.b, Dot) and f"dot{len(e.b.x)}_add" in ints:
            # vpdpbusd accumulates: acc + dot is one instruction
            return self._dot(e.b, width, accumulator=self.expr(e.a))
        if isinstance(e, Binary):
            return ints[e.op].format(a=self.expr(e.a), b=self.expr(e.b))
        if isinstance(e, Dot):
            return self._dot(e, width)
        if isinstance(e, Requantize):
            low, high = (c_float(float(v - e.zero_point)) for v in (e.low, e.high))
            return ints["requantize"].format(value=self.expr(e.value), low=low, high=high, zero_point=e.zero_point)
        return self._integer_cast(e, width)

    def _int32_load(self, e: Load, ints: dict[str, str]) -> str:
        """A vector of int32 lanes from an int32 buffer. An 8-bit buffer's elements are no int32 lanes:
        loaded unwidened (a copy of bytes, e.g. a line buffer's shift), they would be read 4 to a lane
        and stored as int32 values, so that is refused rather than printed wrong."""
        dtype = self.dtypes[e.buffer]
        if dtype != DType.INT32:
            raise TypeError(f"{e.lanes}-lane load of {dtype} {e.buffer} not widened to int32: no byte-copy vectors")
        return ints["load"].format(address=f"&{e.buffer}[{c_affine(e.index)}]")

    def _dot(self, e: Dot, width: VectorWidth, accumulator: str | None = None) -> str:
        """A dot product from the width's template (with the accumulator: `dot4_add`; per-lane
        activations: `dot<K>_lanes` where the width has it), its activations in every lane (2 int16 or
        4 bytes, the lowest channel lowest); lane by lane without one."""
        k, ints = len(e.x), width.ints
        address = f"&{e.w.buffer}[{c_affine(e.w.index)}]"
        if f"dot{k}_add" in ints:
            acc = accumulator or ints["splat"].format(value="0")
            return ints[f"dot{k}_add"].format(acc=acc, xs=self._activations(e, ints), address=address)
        per_lane = any(x.lanes > 1 for x in e.x)
        template = f"dot{k}_lanes" if per_lane and f"dot{k}_lanes" in ints else f"dot{k}"
        if self.dtypes[e.w.buffer] == DType.INT16:  # int16 pairs as they are (Target.int16_dots, dot2_int16_weights)
            template = "dot2_int16"
        if template in ints:
            return ints[template].format(xs=self._activations(e, ints), address=address)
        if per_lane:  # Target.tap_dots promises the templates
            raise TypeError(f"no dot{k} template for a depthwise's per-lane taps")
        return ints["vector"].format(values=", ".join(scalar_dot(self, e, lane) for lane in range(e.lanes)))

    def _activations(self, e: Dot, ints: dict[str, str]) -> str:
        """The K activations of a dot in every int32 lane: one broadcast from memory where they are
        adjacent bytes, else packed in a scalar int and splat."""
        k = len(e.x)
        if any(x.lanes > 1 for x in e.x):
            return self._lane_activations(e, ints)
        flipped = _flipped(e.x)  # int8 read as uint8 x + 128 (Target.dot_uint8_activations)
        xs = tuple(x.a for x in e.x) if flipped else e.x
        first = xs[0].value if isinstance(xs[0], Cast) and isinstance(xs[0].value, Load) else None
        adjacent = first is not None and all(
            x == Cast(DType.INT32, Load(first.buffer, first.index + j)) for j, x in enumerate(xs)
        )
        template = f"{'pair' if k == 2 else 'quad'}_{self.dtypes[first.buffer].value}" if first else ""
        template += "_as_uint8" if flipped else ""
        half = self._quad_half(first) if adjacent and k == 2 and f"{template}_of_quad" in ints else None
        if half is not None:
            address = f"&{first.buffer}[{c_affine(first.index - 2 * half)}]"
            return ints[f"{template}_of_quad"].format(address=address, half=half * 0x55)
        if adjacent and template in ints:
            return ints[template].format(address=f"&{first.buffer}[{c_affine(first.index)}]")
        bits, mask = 32 // k, "0xFFFFu" if k == 2 else "0xFFu"
        parts = [
            f"(((unsigned){self.expr(x)} & {mask}) << {bits * j})" for j, x in enumerate(e.x) if x != Const.integer(0)
        ]
        return ints["splat"].format(value=f"(int)({' | '.join(parts) or '0u'})")

    def _quad_half(self, first: Load) -> int | None:
        """0 or 1 where the pair at `first` is the low or the high half of 4 bytes at an index that is a
        multiple of 4 inside the buffer (every index the loop variables give: their coefficients and
        the buffer's size multiples of 4), else None. Both pairs of a quad then read the same 4 bytes,
        which the C compiler loads and unpacks once."""
        index = first.index
        if self.buffer_sizes.get(first.buffer, 1) % 4 or any(c % 4 for _, c in index.terms) or index.const % 2:
            return None
        return index.const % 4 // 2

    def _lane_activations(self, e: Dot, ints: dict[str, str]) -> str:
        """The K activation vectors of a depthwise's taps packed into each lane, tap j in bits
        [32 j / K, 32 (j + 1) / K): widened to int32, the lower ones masked to their field unless
        they are uint8 (a signed or zero-point-shifted value would spill its sign bits)."""
        k = len(e.x)
        pair = _byte_pair(e, self.dtypes)
        if pair is not None and f"pair_lanes_{pair[0]}" in ints:
            dtype, a, b = pair
            return ints[f"pair_lanes_{dtype}"].format(a=a, b=b)
        bits = 32 // k
        parts = []
        for j, x in enumerate(e.x):
            if isinstance(x, Const) and not any(x.values):
                continue
            value = self.expr(x)
            unsigned = isinstance(x, Cast) and isinstance(x.value, Load) and self.dtypes[x.value.buffer] == DType.UINT8
            if j < k - 1 and not unsigned:
                value = ints["and"].format(a=value, b=ints["splat"].format(value=(1 << bits) - 1))
            parts.append(ints["shift_left"].format(a=value, bits=bits * j) if j else value)
        packed = parts[0] if parts else ints["splat"].format(value="0")
        for part in parts[1:]:
            packed = ints["or"].format(a=packed, b=part)
        return packed

    def _integer_cast(self, e: Cast, width: VectorWidth) -> str:
        if e.dtype == DType.FLOAT32:
            return width.ints["convert"].format(a=self.expr(e.value))
        if isinstance(e.value, Const):  # weights the unroll pass inlined
            return _integer_const(e.value.values, width.ints)
        if isinstance(e.value, Load):  # an 8-bit load widened to int32
            source = self.dtypes[e.value.buffer].value
            return width.ints[f"widen_{source}"].format(address=f"&{e.value.buffer}[{c_affine(e.value.index)}]")
        raise TypeError(f"cannot print {e!r} on vectors")


def _flipped(xs: tuple[Expr, ...]) -> bool:
    """Whether every activation of a dot is read as x - (-128): int8 as uint8 (passes/dot_product.py)."""
    return all(isinstance(x, Binary) and x.op == "-" and x.b == Const.integer(-128) for x in xs)


def _byte_pair(e: Dot, dtypes: dict[str, DType]) -> tuple[str, str, str] | None:
    """(dtype, address, address) of a dot of two taps that are plain 8-bit vector loads of one type."""
    loads = [x.value for x in e.x if isinstance(x, Cast) and isinstance(x.value, Load)]
    if len(e.x) != 2 or len(loads) != 2 or dtypes[loads[0].buffer] != dtypes[loads[1].buffer]:
        return None
    a, b = (f"&{load.buffer}[{c_affine(load.index)}]" for load in loads)
    return dtypes[loads[0].buffer].value, a, b


def _helper_keys(stmt: Stmt, buffer_dtypes: dict[str, DType]) -> Iterator[tuple[int, str]]:
    """(lanes, key) of the int_helpers a statement's integer vectors may call: the stored dtype of an
    8-bit vector store, and the operations `requantize`, `widen_<dtype>`, `vector` and `dot<K>`."""
    if isinstance(stmt, Store) and stmt.value.lanes > 1 and buffer_dtypes[stmt.buffer].is_integer:
        yield stmt.value.lanes, buffer_dtypes[stmt.buffer].value
    for e in (e for top in stmt_exprs(stmt) for e in walk_exprs(top) if e.lanes > 1):
        if isinstance(e, Requantize):
            yield e.lanes, "requantize"
        elif isinstance(e, Cast) and e.dtype.is_integer and isinstance(e.value, Load):
            yield e.lanes, f"widen_{buffer_dtypes[e.value.buffer].value}"
        elif isinstance(e, Const) and e.dtype.is_integer and not e.is_splat:
            yield e.lanes, "vector"
        elif isinstance(e, Dot):
            yield e.lanes, f"dot{len(e.x)}"


def _integer_const(values: tuple[int, ...], ints: dict[str, str]) -> str:
    if all(v == values[0] for v in values):
        return ints["splat"].format(value=c_int(values[0]))
    return ints["vector"].format(values=", ".join(c_int(v) for v in values))
