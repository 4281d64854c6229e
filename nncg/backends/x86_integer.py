"""Backend: the int8 kernels' int32 vectors on x86 (SSE4.1, AVX2, AVX-512F intrinsics, which every
avx2 and avx512 target CPU has): widening byte loads (pmovzxbd/pmovsxbd), 32-bit multiply (pmulld),
or, on ssse3 (no SSE4.1), byte unpacks and pmaddwd (below); dot products of 2 input channels as
pmaddwd on int16 pairs (exact: no two int16 products of an 8-bit activation and an int8 weight sum
beyond int32), of 4 as AVX-512 VNNI's vpdpbusd on u8 x s8 quads (no saturation: the non-saturating
form) or as pmaddubsw quads where the weights are proven not to saturate (x86_quads.py); and
requantisation as onnxruntime's MLAS does it per vector: clamp in float, cvtps2dq (round half to even
in the default rounding mode), add the zero point, pack to bytes (the lanes are in range, so the
saturating packs change nothing)."""

from __future__ import annotations

from .x86_quads import SSE2_QUAD, maddubs_dot4

# lanes -> (prefix, vector type, the load of `lanes` bytes as a __m128i, int32 load/store suffix)
SHAPES = {
    4: ("_mm", "__m128i", "_mm_loadu_si32((const void *)({address}))", "si128"),
    8: ("_mm256", "__m256i", "_mm_loadl_epi64((const __m128i *)({address}))", "si256"),
    16: ("_mm512", "__m512i", "_mm_loadu_si128((const __m128i *)({address}))", "si512"),
}


# lanes -> the load of `lanes` int16 values
INT16_LOADS = {
    4: "_mm_loadl_epi64((const __m128i *)({address}))",
    8: "_mm_loadu_si128((const __m128i *)({address}))",
    16: "_mm256_loadu_si256((const __m256i *)({address}))",
}
# lanes -> the int16 pairs of `lanes` output channels' packed weights, sign-extended from int8 (SSE4.1, AVX2, AVX-512BW)
PAIRS = {
    4: "_mm_cvtepi8_epi16(_mm_loadl_epi64((const __m128i *)({address})))",
    8: "_mm256_cvtepi8_epi16(_mm_loadu_si128((const __m128i *)({address})))",
    16: "_mm512_cvtepi8_epi16(_mm256_loadu_si256((const __m256i *)({address})))",
}


def halves(template: str, weights: int, per_lane: bool = False) -> str:
    """A 16-lane dot from the 8-lane `template` for AVX-512F, which has no 512-bit pmaddwd or pmaddubsw
    (AVX-512BW): each 256-bit half of {xs} times its half of the packed weights, `weights` elements further
    on. Activations shared by all lanes are the same in both halves; `per_lane` ones (a depthwise's
    taps) take the upper half extracted."""
    upper = "_mm512_extracti64x4_epi64({xs}, 1)" if per_lane else "_mm512_castsi512_si256({xs})"
    low = template.format(xs="_mm512_castsi512_si256({xs})", address="{address}")
    high = template.format(xs=upper, address=f"({{address}}) + {weights}")
    return f"_mm512_inserti64x4(_mm512_castsi256_si512({low}), {high}, 1)"


def x86_dots(lanes: int, bw: bool = False, vnni: bool = False, maddubs: bool = False) -> dict[str, str]:
    """The dot-product templates of one x86 width: `dot2` (pmaddwd; 16 lanes in halves without
    AVX-512BW, and `dot2_lanes` for per-lane activations), with `vnni` (AVX-512 VNNI, and VL below 16
    lanes) `dot4_add` (vpdpbusd) and `quad_int8_as_uint8`, with `maddubs` `dot4` (pmaddubsw quads,
    x86_quads.py; halves too), the
    activations of adjacent channels broadcast straight from memory (vpbroadcastd), and the shifts and
    masks that pack a depthwise's per-lane taps."""
    p, _, _, si = SHAPES[lanes]
    bytes_at = "_mm_loadu_si{bits}((const void *)({{address}}))"
    in_halves = lanes == 16 and not bw
    int16_pairs = f"{p}_loadu_{si}((const void *)({{address}}))"
    dots = {
        "dot2": halves(x86_dots(8)["dot2"], 16) if in_halves else f"{p}_madd_epi16({{xs}}, {PAIRS[lanes]})",
        # weights already int16 pairs (integer Winograd's U', or ssse3's packed int8 weights)
        "dot2_int16": halves(x86_dots(8)["dot2_int16"], 16) if in_halves else f"{p}_madd_epi16({{xs}}, {int16_pairs})",
        "pair_int16": f"{p}_broadcastd_epi32({bytes_at.format(bits=32)})",  # 2 adjacent int16 activations
        "pair_uint8": f"{p}_broadcastd_epi32(_mm_cvtepu8_epi16({bytes_at.format(bits=16)}))",
        "pair_int8": f"{p}_broadcastd_epi32(_mm_cvtepi8_epi16({bytes_at.format(bits=16)}))",
        "quad_uint8": f"{p}_broadcastd_epi32({bytes_at.format(bits=32)})",
        # a depthwise's taps, each lane its own (passes/dot_taps.py), packed into the lanes by shifts
        "shift_left": f"{p}_slli_epi32({{a}}, {{bits}})",
        "or": f"{p}_or_{si}({{a}}, {{b}})",
        "and": f"{p}_and_{si}({{a}}, {{b}})",
    }
    if in_halves:  # a depthwise's taps, each lane its own (Dot with vector x)
        dots["dot2_lanes"] = halves(x86_dots(8)["dot2"], 16, per_lane=True)
    if maddubs:
        dots["dot4"] = halves(maddubs_dot4(8), 32) if in_halves else maddubs_dot4(lanes)
    if maddubs and in_halves:
        dots["dot4_lanes"] = halves(maddubs_dot4(8), 32, per_lane=True)
    if vnni:
        dots["dot4_add"] = f"{p}_dpbusd_epi32({{acc}}, {{xs}}, {p}_loadu_{si}((const void *)({{address}})))"
        # 4 adjacent int8 activations as uint8 x + 128: each byte's sign bit flipped (-2139062144: 0x80808080)
        dots["quad_int8_as_uint8"] = f"{p}_xor_{si}({dots['quad_uint8']}, {p}_set1_epi32(-2139062144))"
    return dots


def x86_integer(lanes: int, bw: bool = False, vnni: bool = False, maddubs: bool = False) -> dict:
    """VectorWidth fields `ints` and `int_helpers` of one x86 width (with AVX-512BW, VNNI, pmaddubsw: dots)."""
    p, vt, bytes_load, si = SHAPES[lanes]
    name = f"nncg{p.removeprefix('_mm')}_store"
    ints = {
        "type": vt,
        "load": f"{p}_loadu_{si}((const void *)({{address}}))",
        "widen_uint8": f"{p}_cvtepu8_epi32({bytes_load})",
        "widen_int8": f"{p}_cvtepi8_epi32({bytes_load})",
        "widen_int16": f"{p}_cvtepi16_epi32({INT16_LOADS[lanes]})",
        "splat": f"{p}_set1_epi32({{value}})",
        "vector": f"{p}_setr_epi32({{values}})",
        "+": f"{p}_add_epi32({{a}}, {{b}})",
        "-": f"{p}_sub_epi32({{a}}, {{b}})",
        "*": f"{p}_mullo_epi32({{a}}, {{b}})",
        "max": f"{p}_max_epi32({{a}}, {{b}})",
        "convert": f"{p}_cvtepi32_ps({{a}})",
        "requantize": f"{p}_add_epi32({p}_cvtps_epi32({p}_min_ps({p}_max_ps({{value}}, {p}_set1_ps({{low}})), "
        f"{p}_set1_ps({{high}}))), {p}_set1_epi32({{zero_point}}))",
        "store_uint8": f"{name}_uint8({{address}}, {{value}})",
        "store_int8": f"{name}_int8({{address}}, {{value}})",
        "store_int16": f"{name}_int16({{address}}, {{value}})",
        "store_int32": f"{p}_storeu_{si}((void *)({{address}}), {{value}})",
        **x86_dots(lanes, bw, vnni, maddubs),
    }
    return {"ints": ints, "int_helpers": _stores(lanes, name, vt)}


# SSSE3 has neither pmovzxbd nor pmulld. The bytes are unpacked with zeros (a signed byte lands in
# the top byte of its lane, then shifts down arithmetically), and the product is pmaddwd of the lanes'
# low halves, the second operand's high halves cleared: exact because the int8 kernels multiply
# (x - x_zero_point) in [-255, 255] by a weight in [-128, 127], both int16 values.
ZERO = "_mm_setzero_si128()"
SSE2_BYTES = "_mm_loadu_si32((const void *)({address}))"
SSE2_PAIR = "_mm_loadu_si16((const void *)({address}))"
# the bytes of 4 channels' taps a and b interleaved: a0 b0 a1 b1 ...
SSE2_TAPS = f"_mm_unpacklo_epi8({SSE2_BYTES.format(address='{a}')}, {SSE2_BYTES.format(address='{b}')})"
SSE2 = {
    "widen_uint8": f"_mm_unpacklo_epi16(_mm_unpacklo_epi8({SSE2_BYTES}, {ZERO}), {ZERO})",
    "widen_int8": f"_mm_srai_epi32(_mm_unpacklo_epi16({ZERO}, _mm_unpacklo_epi8({ZERO}, {SSE2_BYTES})), 24)",
    "widen_int16": f"_mm_srai_epi32(_mm_unpacklo_epi16({ZERO}, {INT16_LOADS[4]}), 16)",
    "*": "_mm_madd_epi16({a}, _mm_and_si128({b}, _mm_set1_epi32(0xFFFF)))",
    # no pmaxsd: the int8 kernels take maxima of 8-bit values, which pmaxsw takes in the low int16
    # halves (the high halves, their sign extensions, follow the same lane)
    "max": "_mm_max_epi16({a}, {b})",
    # 2 adjacent 8-bit activations widened to int16 in every int32 lane (no pmovzxbw, no vpbroadcastd)
    "pair_uint8": f"_mm_shuffle_epi32(_mm_unpacklo_epi8({SSE2_PAIR}, {ZERO}), 0)",
    "pair_int8": f"_mm_shuffle_epi32(_mm_srai_epi16(_mm_unpacklo_epi8({SSE2_PAIR}, {SSE2_PAIR}), 8), 0)",
    # the low (half 0) or high (0x55) pair of 4 uint8 at address: both pairs share one load and unpack
    "pair_int16": f"_mm_shuffle_epi32({SSE2_BYTES}, 0)",
    "pair_uint8_of_quad": f"_mm_shuffle_epi32(_mm_unpacklo_epi8({SSE2_BYTES}, {ZERO}), {{half}})",
    # a depthwise's two taps (4 channels each) interleaved into int16 pairs: tap a low, tap b high
    "pair_lanes_uint8": f"_mm_unpacklo_epi8({SSE2_TAPS}, {ZERO})",
    "pair_lanes_int8": f"_mm_srai_epi16(_mm_unpacklo_epi8({ZERO}, {SSE2_TAPS}), 8)",
    # the weights packed as int16 pairs at generation time (Target.dot2_int16_weights): no pmovsxbw
    "dot2_int16": "_mm_madd_epi16({xs}, _mm_loadu_si128((const __m128i *)({address})))",
}


def sse2_integer() -> dict:
    """x86_integer(4) in SSE2 intrinsics and SSSE3's pmaddubsw, for the ssse3 target."""
    fields = x86_integer(4, maddubs=True)
    return {**fields, "ints": {**fields["ints"], **SSE2, "dot2": SSE2["dot2_int16"], "quad_uint8": SSE2_QUAD}}


def _stores(lanes: int, name: str, vt: str) -> dict[str, tuple[str, ...]]:
    """The narrowing stores, by the stored type: the lanes are already in the type's range."""
    stores: dict[str, tuple[str, ...]] = {}
    stores["int16"] = _int16_store(lanes, name, vt)
    for dtype, pack in (("uint8", "_mm_packus_epi16"), ("int8", "_mm_packs_epi16")):
        head = [f"static NNCG_INLINE void {name}_{dtype}(nncg_{dtype} *p, {vt} v)", "{"]
        if lanes == 4:
            body = [f"    _mm_storeu_si32((void *)p, {pack}(_mm_packs_epi32(v, v), v));"]
        elif lanes == 8:
            body = [
                "    __m128i h = _mm_packs_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));",
                f"    _mm_storel_epi64((__m128i *)p, {pack}(h, h));",
            ]
        else:  # vpmovdb truncates, exact for lanes in range
            body = ["    _mm_storeu_si128((__m128i *)p, _mm512_cvtepi32_epi8(v));"]
        stores[dtype] = (*head, *body, "}")
    return stores


def _int16_store(lanes: int, name: str, vt: str) -> tuple[str, ...]:
    """The narrowing store to int16 (integer Winograd's V): the lanes are already in range."""
    if lanes == 4:
        body = "    _mm_storel_epi64((__m128i *)p, _mm_packs_epi32(v, v));"
    elif lanes == 8:
        halves_packed = "_mm_packs_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1))"
        body = f"    _mm_storeu_si128((__m128i *)p, {halves_packed});"
    else:  # vpmovdw truncates, exact for lanes in range
        body = "    _mm256_storeu_si256((__m256i *)p, _mm512_cvtepi32_epi16(v));"
    return (f"static NNCG_INLINE void {name}_int16(nncg_int16 *p, {vt} v)", "{", body, "}")
