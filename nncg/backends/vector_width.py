"""Backend: the table a SIMD target fills for each vector width it prints — its C type and a C
template per operation of the loop-nest IR. The SIMD printer (simd.py) prints only from these."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from ..ir.loops import BINARY_OPS, COMPARISONS

# The operations a width's templates spell, with the fields each template is formatted with.
OPERATIONS = {
    "load": ("address",),  # address: `&x[i + 4]`, or a row of the constant table
    "store": ("address", "value"),
    "splat": ("value",),  # a constant splat, or a broadcast scalar
    **{op: ("a", "b") for op in BINARY_OPS},
    **{cmp: ("lhs", "rhs", "then", "otherwise") for cmp in COMPARISONS},  # (lhs cmp rhs) ? then : otherwise
    "math": ("fn",),  # the NAME of the helper computing the math function fn of each lane: NAME(x)
    # Optional:
    "sqrt": ("a",),  # the correctly rounded square root of each lane; required with `bits`
    "fma": ("a", "b", "c"),  # a * b + c in the ISA's instruction (one rounding; ARMv7 NEON: vmla); required with FMA
    "fma_exact": ("a", "b", "c"),  # a * b + c, one rounding, emulated where the ISA has no FMA (Target.fma_in_double)
    "vector": ("values",),  # a constant vector lane by lane; without it constants are table rows
    "table": (),  # the name of the static table of constant vectors (when there is no `vector`)
}
OPTIONAL = ("sqrt", "fma", "fma_exact", "vector", "table")

# The integer and bit operations on vectors of int32 lanes the vector math functions are written in
# (vector_math.py), with `sqrt`. A width without them computes a math function with math.h, lane by lane.
BIT_OPERATIONS = {
    "type": (),  # the C type of a vector of int32 lanes (`__m256i`, `int32x4_t`)
    "splat": ("value",),  # an int32 constant in every lane
    "from_float": ("a",),  # the bits of a float vector, unchanged
    "to_float": ("a",),  # the float vector of these bits
    "convert": ("a",),  # the float value of each int32 lane
    **{op: ("a", "b") for op in ("+", "-", "&", "|")},
    **{op: ("a", "n") for op in ("<<", ">>")},  # shift by the constant n; >> is arithmetic
}

# The operations of the int8 kernels on vectors of int32 lanes (the vectorize pass makes them where
# Target.integer_vectors says the width has them).
INTEGER_OPERATIONS = {
    "type": (),  # the C type of a vector of int32 lanes
    "load": ("address",),  # int32 lanes
    "widen_uint8": ("address",),  # one uint8 per lane, widened to int32
    "widen_int8": ("address",),
    "splat": ("value",),
    "vector": ("values",),  # a constant vector lane by lane
    **{op: ("a", "b") for op in ("+", "-", "*", "max")},
    "convert": ("a",),  # the float value of each lane
    "requantize": ("value", "low", "high", "zero_point"),  # float lanes clamped, rounded half to even, + zp
    "store_uint8": ("address", "value"),  # int32 lanes already in the type's range, stored as bytes
    "store_int8": ("address", "value"),
}
# optional: the dot products of loops.Dot (without them a width computes each lane in scalar C)
INTEGER_DOTS = {
    "dot2": ("xs", "address"),  # pmaddwd: xs two int16 in each lane, address 2 int8 weights per lane
    "dot4": ("xs", "address"),  # pmaddubsw + pmaddwd by ones: xs four uint8 in each lane, address 4 int8 per lane
    "dot2_add": ("acc", "xs", "address"),  # acc + dot2 (NEON's vmlal_s16)
    "dot4_add": ("acc", "xs", "address"),  # acc + vpdpbusd: xs four uint8 in each lane, address 4 int8 per lane
    # dot2, dot4 of per-lane activations (a depthwise's taps) where they differ from the shared ones'
    # (avx512's halves: the upper half extracted)
    "dot2_lanes": ("xs", "address"),
    "dot4_lanes": ("xs", "address"),
    # (sdot, Target.dot_int8_activations: four int8)
    # xs from 2 (4) adjacent 8-bit activations in memory, in every lane; else from a scalar int (splat)
    "pair_uint8": ("address",),
    "pair_int8": ("address",),
    "quad_uint8": ("address",),
    "quad_int8_as_uint8": ("address",),  # 4 adjacent int8 as uint8 x + 128 (Target.dot_uint8_activations)
    # the pair at address + 2 half (half 0 or 0x55) of 4 adjacent uint8 at address, a multiple of 4
    "pair_uint8_of_quad": ("address", "half"),
    # a depthwise's per-lane taps packed into the lanes (simd_integer._lane_activations): two taps'
    # 8-bit vectors at addresses a and b interleaved into int16 pairs, else widened, shifted and or-ed
    "pair_lanes_uint8": ("a", "b"),
    "pair_lanes_int8": ("a", "b"),
    "shift_left": ("a", "bits"),
    "or": ("a", "b"),
    "and": ("a", "b"),
    # Target.int16_dots (integer Winograd): pmaddwd of int16 pairs read as they are, 2 adjacent int16
    # activations in every lane, int32 lanes in int16 range stored as int16
    "dot2_int16": ("xs", "address"),
    "pair_int16": ("address",),
    "store_int16": ("address", "value"),
    "store_int32": ("address", "value"),
    # int16 weights (a weight zero point subtracted) widened to int32 where no dot product takes them
    "widen_int16": ("address",),
}


@dataclass(frozen=True)
class VectorWidth:
    """How a target spells one vector width.

    type: the C vector type (`__m256`, `float32x4_t`).
    ops: operation -> C template (see OPERATIONS), e.g. `_mm256_add_ps({a}, {b})`.
    helpers: operation -> the lines defining what its template calls beyond the ISA's intrinsics
    (NEON's division on ARMv7), printed once before the kernels when the program uses it.
    bits: operation -> C template of BIT_OPERATIONS (all or none).
    ints: operation -> C template of INTEGER_OPERATIONS (all or none), with `int_helpers`: stored
    dtype -> the lines defining the narrowing store, printed once for a program that stores that
    dtype from vectors of this width, and `requantize`, `widen_<dtype>`, `vector` -> the lines
    defining what that template calls, printed once for a program that uses it (simd_integer.py)."""

    type: str
    ops: Mapping[str, str]
    helpers: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    bits: Mapping[str, str] = field(default_factory=dict)
    ints: Mapping[str, str] = field(default_factory=dict)
    int_helpers: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def spell(self, op: str, **fields: str) -> str:
        return self.ops[op].format(**fields)

    def problems(self, fma: bool) -> list[str]:
        """What this table lacks or has too much of, for a target with (or without) FMA."""
        required = [op for op in OPERATIONS if op not in OPTIONAL] + (["fma"] if fma else [])
        required += [] if "vector" in self.ops else ["table"]
        required += ["sqrt"] if self.bits else []
        missing = [op for op in required if op not in self.ops]
        unknown = [op for op in (*self.ops, *self.helpers) if op not in OPERATIONS]
        if self.bits:
            missing += [f"bits {op}" for op in BIT_OPERATIONS if op not in self.bits]
            unknown += [f"bits {op}" for op in self.bits if op not in BIT_OPERATIONS]
        if self.ints:
            missing += [f"ints {op}" for op in INTEGER_OPERATIONS if op not in self.ints]
            unknown += [f"ints {op}" for op in self.ints if op not in {**INTEGER_OPERATIONS, **INTEGER_DOTS}]
        return [f"no template for {op}" for op in missing] + [f"unknown operation {op}" for op in unknown]
