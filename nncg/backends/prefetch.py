"""Backend: software prefetch of weights that stream from beyond L1.

A layer whose constant weights exceed the target's L1 (the cache-blocked convolutions and matrix
products) reads them once per panel, in one contiguous stream, from L2, L3 or memory; between two
reads of a stream it does little work (a 1x1 conv on 3x3 pixels: 9 FMAs per weight vector), so the
hardware prefetcher falls behind. Each reduction loop that reads such a stream by vectors therefore
prefetches, one line per cache line it reads, the data PREFETCH_BYTES ahead of its loads (mobilenet_v2
at 96x96 on avx512, 1x1 convs on 3x3 pixels: 20-27 % less time per layer, loaded). In a model those
weights come from memory, where 2 KiB ahead was too close: its 320->1280 and 960->320 1x1 convs on 3x3
pixels alone, weights evicted from the caches before each call, 115 -> 90 and 70 -> 58 us at 8 KiB ahead
(16 KiB: 5 % slower from L3; avx512, loaded). A loop whose multiply-adds each read a weight vector of
their own (a GEMV: a classifier at batch 1) is not prefetched: the hardware prefetcher follows its
streams, and the prefetches only cost issue slots (1280x1000 Gemm, avx512, loaded: 54 -> 49 us from
L3, 189 -> 174 us from memory, as fast as a plain vector sum over its weights). The address is clamped
to the buffer's last element where the lookahead could pass its end, so no pointer leaves its array.

x86 prefetches into L2 (T1), not L1 (T0): a prefetch into L1 holds one of L1's few miss buffers until
its line arrives from memory, and those bound how many lines are in flight; L2 tracks more, and the
hardware moves the lines on into L1 as the loads near them. Whole models, weights from memory (64 MB
read between inferences, one weights copy, interleaved; Zen 4, gcc -O3), T1 / T0 time: avx512
resnet18_96 0.95, regnet_x_400mf_96 0.93, squeezenet1_1_96 0.96, efficientnet_b0_96 0.96,
mobilenet_v2_96 0.99; avx2 resnet18_96 0.90, regnet 0.94, mobilenet_v2 0.96; ssse3 0.97-1.01 (its
slower arithmetic hides the memory); with the weights in L3, 0.99-1.015 everywhere."""

from __future__ import annotations

from ..ir.kinds import BufferRole, DType
from ..ir.loops import Affine, Assign, Load, Loop, Program, walk_exprs
from .c_text import c_affine

PREFETCH_BYTES = 8192
LINE_BYTES = 64
FLOAT_BYTES = 4


def streamed_constants(program: Program, l1_bytes: int) -> dict[str, int]:
    """The constant float buffers larger than L1, name -> elements."""
    return {
        b.name: b.size
        for b in program.buffers
        if b.role == BufferRole.CONSTANT and b.dtype == DType.FLOAT32 and b.size * FLOAT_BYTES > l1_bytes
    }


def prefetch_addresses(loop: Loop, streamed: dict[str, int], extents: dict[str, int]) -> list[tuple[str, str]]:
    """(buffer, C index) of each line to prefetch at the top of `loop`'s body: the vector loads of
    streamed buffers in its own statements whose address moves with it, PREFETCH_BYTES ahead, one per
    cache line; none where no weight vector serves more than one update (a GEMV). `extents`: the loop
    variables in scope (this loop's included), to bound the index."""
    if loop.parallel:
        return []
    ahead = PREFETCH_BYTES // FLOAT_BYTES
    line = LINE_BYTES // FLOAT_BYTES
    lines: dict[tuple, tuple[str, str]] = {}
    loads: set[Load] = set()
    updates = 0
    for stmt in loop.body:
        if not isinstance(stmt, Assign):
            continue
        streaming = [e for e in walk_exprs(stmt.value) if _streamed_load(e, loop.var, streamed, extents)]
        updates += bool(streaming)
        for e in streaming:
            loads.add(e)
            index = e.index + ahead
            key = (e.buffer, index.terms, index.const // line)
            lines.setdefault(key, (e.buffer, _clamped(index, streamed[e.buffer] - 1, extents)))
    return list(lines.values()) if updates > len(loads) else []


def _streamed_load(e, var: str, streamed: dict[str, int], extents: dict[str, int]) -> bool:
    """A vector load of a streamed buffer that moves with the loop `var`, indexed by loops in scope."""
    if not (isinstance(e, Load) and e.lanes > 1 and e.buffer in streamed and e.index.coeff(var)):
        return False
    return all(v in extents for v in e.index.vars)


def _clamped(index: Affine, last: int, extents: dict[str, int]) -> str:
    text = c_affine(index)
    if index.bounds(extents)[1] <= last:
        return text
    return f"{text} < {last} ? {text} : {last}"
