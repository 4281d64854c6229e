"""The hardware facts passes and printers may use: one `Target` per backend, handed to passes by the
pass manager. The pipeline text records choices (which layer is vectorised, blocked, unrolled), never
these facts, so a pipeline cannot disagree with the target it runs for."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Target:
    """What one backend's code runs on.

    vector_widths: the SIMD widths (float lanes) it prints, widest first; () for scalar C.
    registers: vector registers (float registers for scalar C) register blocking may fill.
    fma: a multiply feeding an add can be one fused multiply-add (one rounding).
    l1_bytes, l2_bytes: the data caches of one core the cache-block pass sizes weight panels for, the
    smallest of the CPUs the backend serves (0: no data cache, as on a Cortex-M; nothing is blocked).
    integer_vectors: its widths also hold int32 lanes with a 32-bit multiply, widening 8-bit loads and
    narrowing 8-bit stores, so the vectorize pass vectorises the int8 kernels too.
    memory_operands: an arithmetic instruction may read one operand straight from memory (x86), so a
    fused multiply-add needs no register for the weight vector it reads.
    broadcast_operands: that memory operand may also be one float broadcast to every lane (AVX-512's
    {1to16}), so a multiply-add by a broadcast input needs no register for the input either.
    dot_uint8, dot_int8: the input channels one integer dot product (loops.Dot) multiplies per lane,
    for uint8 and for int8 activations: 2 (pmaddwd on int16 pairs), 4 (vpdpbusd on u8 x s8 quads);
    0: none, the int8 kernels multiply channel by channel.
    dot_uint8_int16: the input channels (4) of a uint8 dot product that sums its pairs of products in
    int16 with saturation (pmaddubsw, then pmaddwd by ones); the dot product pass takes it instead of
    dot_uint8 only for a layer whose weights it proves keep every pair sum within int16, 0: none.
    tap_dots: the dot products also take a depthwise convolution's taps, each lane its own channel's
    activations (loops.Dot with vector x; passes/dot_taps.py).
    dot2_int16_weights: the K = 2 dot products read their weights as int16 pairs packed at generation
    time (ssse3: without SSE4.1's pmovsxbw, widening int8 weights per use took three instructions
    per pmaddwd; the weights take twice the bytes).
    dot2_quad_loads: a K = 2 dot's adjacent 8-bit activations are widened from a 4-byte load whose
    other pair the next dot takes (ssse3, without vpbroadcastd: one load and unpack serve two pairs),
    so register-block unrolls those reductions by 2 (passes/register_block.py, unroll_pair_reductions).
    dot_int8_activations: the K = 4 dot multiplies int8 activations (AArch64 sdot: s8 x s8 quads), so
    uint8 activations and zero points the lowering did not fold are offset into int8 and the constant
    difference is added back per output channel (passes/dot_product.py).
    dot_uint8_activations: the K = 4 dot multiplies uint8 activations (x86's vpdpbusd: u8 x s8 quads),
    so int8 activations and zero points the lowering did not fold are offset into uint8 (x + 128, the
    byte x ^ 0x80) and the constant difference is added back per output channel, as for
    dot_int8_activations (TFLite's int8 models take the quads instead of K = 2 pairs).
    centred_weight_dots: its K = 2 dot products also take int16 weights (pmaddwd), the int8 or uint8
    weights minus their zero points that the lowering keeps where those are not all 0 (or are uint8).
    int16_dots: its integer widths also store int16 lanes and take K = 2 dot products of int16
    activations and int16 weights (pmaddwd on both as they are): integer Winograd's nests
    (lowering/winograd_integer.py) vectorise, its GEMMs in those dots.
    fma_in_double: without FMA, its vectors still compute a fused multiply-add of float32 values
    (loops.Fma) with one rounding, in double as the scalar C does (ssse3), so QLinearAdd's vector form
    matches its scalar one."""

    name: str
    vector_widths: tuple[int, ...] = ()
    registers: int = 16
    fma: bool = False
    l1_bytes: int = 0
    l2_bytes: int = 0
    integer_vectors: bool = False
    memory_operands: bool = False
    broadcast_operands: bool = False
    dot_uint8: int = 0
    dot_int8: int = 0
    dot_uint8_int16: int = 0
    tap_dots: bool = False
    dot2_int16_weights: bool = False
    centred_weight_dots: bool = False
    dot2_quad_loads: bool = False
    dot_int8_activations: bool = False
    dot_uint8_activations: bool = False
    fma_in_double: bool = False
    int16_dots: bool = False

    @property
    def lanes(self) -> int:
        """The widest vector: 1 for scalar C."""
        return self.vector_widths[0] if self.vector_widths else 1

    @property
    def widths_text(self) -> str:
        """The widths as pipeline parameters spell them: `16/8/4`, `1` for none."""
        return "/".join(map(str, self.vector_widths)) or "1"
