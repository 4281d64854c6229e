"""Backend: the x86 intrinsics' spelling of one vector width (`_mm`, `_mm256`, `_mm512` prefixes),
the table the ssse3, avx2 and avx512 targets fill theirs from."""

from __future__ import annotations

from .vector_width import VectorWidth

ARITH = {"+": "add", "-": "sub", "*": "mul", "/": "div", "max": "max", "min": "min"}
COMPARE = {">": "cmpgt", ">=": "cmpge", "<": "cmplt", "<=": "cmple"}
PREDICATES = {">": "_CMP_GT_OQ", ">=": "_CMP_GE_OQ", "<": "_CMP_LT_OQ", "<=": "_CMP_LE_OQ"}
# Data caches per core every x86 target may meet: 32 KiB L1d (48 KiB from Ice Lake on) and 256 KiB
# L2 (Skylake client; 512 KiB Zen 2, 1 MiB Skylake-SP): the cache-block pass sizes for the smallest.
X86_L1 = 32 * 1024
X86_L2 = 256 * 1024
# SSE's prefetch into L2, which all x86 targets print (prefetch.py says where and why L2).
X86_PREFETCH = "_mm_prefetch((const char *){address}, _MM_HINT_T1);"


def x86_width(prefix: str, vector_type: str, select: str, fma: bool) -> VectorWidth:
    """One width: `prefix` of its intrinsics (`_mm256_add_ps`), its type (`__m256`), how it selects
    ("bitwise": and/andnot/or on a comparison, SSE; "blendv": blendv_ps, AVX; "mask": a __mmask,
    AVX-512) and whether it has fmadd_ps. Its math helpers are nncg_exp_ps, nncg256_exp_ps, ...;
    their integer operations (vector_math.py) are SSE2's, AVX2's and AVX-512F's epi32 intrinsics."""
    p = prefix
    ops = {
        "load": f"{p}_loadu_ps({{address}})",
        "store": f"{p}_storeu_ps({{address}}, {{value}})",
        "splat": f"{p}_set1_ps({{value}})",
        "vector": f"{p}_setr_ps({{values}})",
        **{op: f"{p}_{name}_ps({{a}}, {{b}})" for op, name in ARITH.items()},
        **{cmp: _select(p, select, cmp) for cmp in COMPARE},
        "math": f"nncg{p.removeprefix('_mm')}_{{fn}}_ps",
        "sqrt": f"{p}_sqrt_ps({{a}})",
    }
    if fma:
        ops["fma"] = f"{p}_fmadd_ps({{a}}, {{b}}, {{c}})"
    si = f"si{vector_type.removeprefix('__m')}"  # si128, si256, si512
    bits = {
        "type": f"{vector_type}i",
        "splat": f"{p}_set1_epi32({{value}})",
        "from_float": f"{p}_castps_{si}({{a}})",
        "to_float": f"{p}_cast{si}_ps({{a}})",
        "convert": f"{p}_cvtepi32_ps({{a}})",
        "+": f"{p}_add_epi32({{a}}, {{b}})",
        "-": f"{p}_sub_epi32({{a}}, {{b}})",
        "&": f"{p}_and_{si}({{a}}, {{b}})",
        "|": f"{p}_or_{si}({{a}}, {{b}})",
        "<<": f"{p}_slli_epi32({{a}}, {{n}})",
        ">>": f"{p}_srai_epi32({{a}}, {{n}})",
    }
    return VectorWidth(vector_type, ops, bits=bits)


def _select(p: str, style: str, cmp: str) -> str:
    if style == "mask":
        return f"{p}_mask_blend_ps({p}_cmp_ps_mask({{lhs}}, {{rhs}}, {PREDICATES[cmp]}), {{otherwise}}, {{then}})"
    if style == "blendv":
        return f"{p}_blendv_ps({{otherwise}}, {{then}}, {p}_cmp_ps({{lhs}}, {{rhs}}, {PREDICATES[cmp]}))"
    # no blend: (mask & then) | (~mask & otherwise)
    mask = f"{p}_{COMPARE[cmp]}_ps({{lhs}}, {{rhs}})"
    return f"{p}_or_ps({p}_and_ps({mask}, {{then}}), {p}_andnot_ps({mask}, {{otherwise}}))"
