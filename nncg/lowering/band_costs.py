"""What the band planner (band_plan.py) charges a layer, per target: the time of a Conv run whole or
in bands, in multiply-accumulates of a whole direct Conv (the unit).

Run whole, a Conv keeps what the graph passes chose for it: Winograd does 2.25x fewer multiplies, but
its transforms and scratch traffic take back part of that, more so the wider the vectors; cache
blocking and pixel vectors gain less. In a group of bands, a Conv runs as a direct,
channels-last nest over the band's rows (stream.py), or as Winograd over its tiles (charged
`winograd` x `banded`), which costs more than the same nest over the
whole layer (the row loop cut into bands, line-buffer indices, shorter loops for register blocking
and unrolling); a layer alone in bands has no line buffers, its nest is the whole layer's. On top,
each band runs every layer's nest once (`per_band`) and shifts the line buffers (`shift`, per 4 bytes).

The x86 figures are rounded from the memory suite's side-by-side runs of robot, pedestrian, resnet8,
ball and mobilenet_v1_025 (speed, balanced, min; and speed against speed without Winograd) on a
machine other jobs loaded, where two builds of the same C differed by up to 40 %: they order plans,
they do not predict microseconds. On avx2 a dense 3x3 Conv loses more in bands than a depthwise or
1x1 one (robot, resnet8 at min: 1.3-1.6x per MAC; ball 1.1x; mobilenet none): `banded` is in
between. ansi-c (scalar: Winograd's saving nearer its 2.25x) and neon (the 4-lane figures) are not
measured.

An int8 Conv in bands runs in the target's int8 dot products as it does whole (vectorize.py takes a band
kernel's convolution nests): two int8 3x3 Convs (dense, strided) in one group took 1.00-1.04x the
instructions of the same Convs whole on ssse3 and 1.05-1.07x on avx2, line buffers and per-band loops
included (callgrind Ir, `python3 -m benchmarks.int8_band_costs`; scalar in bands before: 4.7-4.8x on
ssse3, 11x on avx2); a depthwise pair 1.07x on ssse3, 1.12-1.15x on avx2 (its border columns in vectors over
channels too; scalar before: 1.17x, 1.26-1.29x). `integer_banded` prices that with a margin.

An int8 3x3 Conv as integer Winograd (lowering/winograd_integer.py) took 0.53-0.66x the instructions
of the direct one run whole on resnet8's layers of 16 to 64 input channels (0.63-0.66x ssse3,
0.53-0.58x avx2; callgrind Ir, `python3 -m benchmarks.int8_winograd`): `integer_winograd`, charged
times `kept_banded` when kept in bands (0: `integer_banded`). Scalar C: 2.6x fewer instructions.
The avx2 figures are fitted to resnet8 int8's plans (callgrind Ir of one inference against speed's,
clang -O2, integer Winograd in 1-tile chunks: winograd.WHOLE_CHUNKS): its input..stage2_add in bands of 2
rows with Winograd kept 1.22x, the same with stage2_b_conv direct 1.41x, all direct 1.90x, where
(integer_banded, integer_winograd, kept_banded) = (1.1, 0.55, -) had estimated 1.07x, 1.21x, 1.49x;
(1.2, 0.4, 1.4) estimates 1.22x, 1.44x, 1.88x and keeps ball int8's direct bands (two int8 3x3 Convs:
1.05-1.07x above). On ssse3 (gcc) the 4-lane figures estimate the plan with stage2_b_conv direct at
1.17x, and it took 1.17x.
With M in bands one block of 8 output channels (winograd.BAND_CHUNKS: 512 B a tile) and U laid out block by
block (winograd.blocked_filters), balanced keeps Winograd on both avx2 and ssse3 at 25,088 B (2.02x less than
speed's 50,688). On avx2 (clang -O2, one inference, cachegrind with a 32 KB I1 and D1) it takes 1.28x speed's
Ir (the same plan with all channels in M: 1.21x, at 26,624 B; stage1's 16-channel layers in two blocks
broadcast V once per block) and has fewer D1 read misses than speed (64k against 67k; 71k with all channels
in M, 81k with blocks over U unblocked). Its band kernel's QLinearAdds were then scalar (double arithmetic,
every channel unrolled: 132 KB of code, 27k I1 misses against speed's 3.3k, Ir 1.28x); vectorised as run whole
(vectorize.py) the kernel is 61.5 KB, 3.9k I1 misses, Ir 1.08x. The avx2 int8 figures are re-fitted to TIME
then: interleaved A/B on a loaded machine (`benchmark_variants`, 31 batches, the plans forced), resnet8's
input..stage2_add in bands of 2 rows with Winograd kept took 1.06x speed's latency, with stage2_b_conv direct
1.17x, all direct 1.41x; (integer_banded, integer_winograd, kept_banded) = (1.2, 0.55, 1.05) estimate 1.07x,
1.25x, 1.60x (VECTOR8's integer_winograd, the int8_winograd figure above; integer_banded kept at 1.2, as ball
int8's plan with its QuantizeLinear in 2-row bands, which 1.05 chose, took 1.21x speed against 1.02x for the
1-row bands 1.2 keeps). pedestrian int8's balanced then keeps Winograd in both groups on avx2 too (5,248 B
instead of 8,576: 0.76x speed's latency against 0.92x, same A/B).

A QuantizeLinear in bands (the model input's, into a channels-last line buffer) costs what it costs whole,
1 per element: it quantises each row in vectors into a planar scratch row, then interleaves that into the line
buffer byte by byte (lowering/quantized.py). On mobilenet_v1_025 int8 (96x96x3 input), balanced's plan with the
QuantizeLinear in its group took 1.007x speed's instructions on ssse3 (gcc -O2; clang: 1.019x) and 1.015x on
avx2 (clang), fewer than the same plan with the QuantizeLinear run whole (1.010x, 1.027x, 1.027x; callgrind Ir,
`python3 -m benchmarks.int8_band_costs --quantize [--cc clang]`); quantised element by element at a stride of C
before: 1.14x, 1.08x, 1.09x, and latency 1.43x (ssse3) / 2.07x (avx2).

Work the vectorize pass leaves in scalar C costs the target's lanes a MAC and element (not measured), whole and
in bands alike, by one rule (band_plan.StepCosts, asking ir/applicability.py what the pass asks). A requantised
add (QLinearAdd) stays scalar where fused_ops_vectorise says so, run whole or as a band kernel's stage (its
convolutions still vectorised): every vector target vectorises them today and scalar C has 1 lane, so no plan
changed; band adds left scalar while whole ones vectorised is what had made resnet8's avx2 band kernel 132 KB
(above). Under requantize=fixed an int8 kernel that requantises in the fixed-point form (a QLinearConv,
QLinearDense or QLinearGlobalAveragePool run whole, or a band kernel with one among its stages) stays scalar as
a whole: no backend has that form in vectors (integer_kernel_vectorises). It is priced at scalar C's int8
figures, every MAC and element at the lanes. Only fixed-point plans change: mobilenet_v1_025 int8 balanced on
ssse3, avx2 and avx512 takes 22,912 B instead of 27,648 (resnet8 and dscnn keep theirs)."""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class BandCosts:
    """Time per MAC relative to a whole direct Conv: `winograd` and `blocked` a whole Conv the graph
    passes made Winograd or cache-blocked (or pixel-vectorised), `banded` a Conv in a group of bands;
    `per_band` MAC-equivalents per layer and band run, `shift` per 4 bytes a line buffer shifts."""

    winograd: float
    blocked: float
    banded: float
    per_band: float
    shift: float
    integer_banded: float  # an int8 Conv in a group of bands against run whole, both in the target's dots
    integer_winograd: float  # an int8 Conv run whole as integer Winograd against direct (in bands: direct)
    kept_banded: float = 0.0  # an integer Winograd Conv kept in bands against run whole (0: integer_banded)


SCALAR = BandCosts(
    winograd=0.45, blocked=0.9, banded=1.0, per_band=64.0, shift=1.0, integer_banded=1.0, integer_winograd=0.4
)
VECTOR4 = BandCosts(
    winograd=0.5, blocked=0.85, banded=1.05, per_band=128.0, shift=0.5, integer_banded=1.1, integer_winograd=0.65
)
VECTOR8 = BandCosts(
    winograd=0.6, blocked=0.85, banded=1.2, per_band=128.0, shift=0.25, integer_banded=1.1, integer_winograd=0.55
)
AVX2 = replace(VECTOR8, integer_banded=1.2, kept_banded=1.05)  # int8: resnet8 by time (docstring)
COSTS = {
    "ansi-c": SCALAR,
    "ssse3": VECTOR4,
    "neon": VECTOR4,
    "neon-dotprod": VECTOR4,  # its float kernels are neon's
    "avx2": AVX2,
    "avx512": VECTOR8,
    "avx512vnni": VECTOR8,  # its float kernels are avx512's
}


def band_costs(target: str | None) -> BandCosts:
    """The figures of `target` (a backend's name); None or an unknown name: the 4-lane figures."""
    return COSTS.get(target or "", VECTOR4)
