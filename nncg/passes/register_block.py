"""Loop pass `register-block{layers=NAME:PxC;...}`: register blocking by unroll-and-jam, sized to the
target's vector registers.

A layer that accumulates (a Let whose body loops over a reduction, as Conv, Gemm and pooling do)
adds into one register per output: every add waits for the previous one. This pass jams several
iterations of the parallel loops around the accumulator into one, so P output pixels x C output
channels (vectors, after vectorize) accumulate in P*C independent registers: the adds overlap, each
input value is loaded (broadcast) once for C channels and each weight once for P pixels.

The *channel loops* are parallel loops that hold accumulators directly and whose iterations store
side by side (the output-channel vector loop and its tail); the *pixel loop* is the innermost
parallel loop around them that encloses all of a layer's accumulators (for a layer of one channel
vector, the column loop). A block of more pixels than a row holds takes whole rows: it is 2-D
(rows x columns), each weight vector serving the pixels of several rows. Border checks
that depend on a jammed loop would differ between the jammed iterations, so that loop is first
split into its border iterations (kept as they were) and the interior, where the checks always hold
and are dropped. Choice and mechanism are apart: `choose_blocks` is the cost model, `layers`
overrides it per layer (what `--tune` measured), `jam_loop` does the rewriting."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import takewhile

from ..ir.analysis import holds_accumulators, is_accumulator
from ..ir.dtypes import is_integer_kernel
from ..ir.kinds import BufferRole, DType, Layout
from ..ir.loops import (
    Affine,
    Assign,
    Binary,
    Cast,
    Const,
    Expr,
    If,
    Kernel,
    Let,
    Load,
    Loop,
    Program,
    Stmt,
    Store,
    body_dots,
    stmt_exprs,
    walk_exprs,
    walk_stmts,
)
from ..ir.rename import rename_variables
from ..ir.target import Target
from .per_layer import check_layer_names, parse_layer_map
from .substitute import interior, iterations, prune_bounds, substitute_body

PIXEL_BLOCKS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24)  # pixels per block --tune times
# The cost model: channel vectors jammed per pixel at most, and registers left besides accumulators
# (the broadcast input, a product, weights the compiler keeps).
MAX_CHANNEL_BLOCK = 5
RESERVED = 6
# Pixels per block at most where a fused multiply-add reads a vector of inputs per channel (depthwise) and
# a pixel holds MAX_CHANNEL_BLOCK - 1 channel vectors: avx512's register fit, 6x4, measured 1.2x-1.9x
# slower than 3x4 on single 3x3 depthwise layers shaped like mobilenet_v2's (96-192 channels, stride 1
# and 2; a 5x5 one of 240 channels: no difference, nor with fewer channel vectors).
VECTOR_INPUT_PIXELS = 3
# Pixels per block at most of a fused int8 layer of one channel vector: avx512vnni's register fit, 15
# (15 accumulators, 15 broadcasts), measured 1.8x slower than 12 (8, 10 and 16 within 15 % of 12) on
# resnet8's 32x32x16 layers.
ONE_VECTOR_INT8_PIXELS = 12
# Pixels per block of a float layer of one channel vector where the multiply-add broadcasts its input
# from memory (avx512). Whole models, these layers (stems, 1x1 Convs to one vector) at 6 pixels
# against 24 (idle, interleaved, gcc 12): mlperf_vww_mobilenet 1.028x faster, keras_mobilenet_nhwc_96
# 1.032x, mobilenet_v2_96 1.029x, mobilenet_v1_025 1.032x. VWW's 3x3 stride-2 stem alone: 10.5 us at
# 6, 9.8 at 24, but 16.1 at 8 and 21.2 at 12 (gcc keeps a tap loop there).
ONE_VECTOR_FLOAT_PIXELS = 6
# Channel vectors of the one-pixel block of an SSE int8 kernel of pmaddwd pairs (pair_dot_block).
PAIR_DOT_CHANNELS = 10


def parse_block(text: str) -> tuple[int, int]:
    """`4x2` -> (4, 2): pixels x channel vectors."""
    pixels, x, channels = text.partition("x")
    if not x or not pixels.isdigit() or not channels.isdigit() or int(pixels) < 1 or int(channels) < 1:
        raise ValueError("a block is PIXELSxCHANNELS, both at least 1")
    return int(pixels), int(channels)


def format_block(block: tuple[int, int]) -> str:
    return f"{block[0]}x{block[1]}"


def parse_layers(text: str) -> dict[str, tuple[int, int]]:
    """`conv1:4x2;conv2:3x3` -> {"conv1": (4, 2), "conv2": (3, 3)}."""
    return parse_layer_map(text, parse_block, "conv1:4x2")


def register_block(program: Program, target: Target, layers: dict[str, tuple[int, int]] | None = None) -> Program:
    layers = layers or {}
    check_layer_names(program, layers, "register-block")
    blocks = chosen_blocks(program, target, layers)
    kernels = tuple(
        replace(k, body=_block_kernel(k, blocks[k.name], k.name not in layers, program, target))
        if k.name in blocks
        else k
        for k in program.kernels
    )
    if target.dot2_quad_loads:
        kernels = tuple(replace(k, body=unroll_pair_reductions(k.body)) for k in kernels)
    return replace(program, kernels=kernels)


def _block_kernel(
    kernel: Kernel, block: tuple[int, int], own: bool, program: Program, target: Target
) -> tuple[Stmt, ...]:
    """A kernel's body blocked by `block`; a band kernel runs several layers' nests, each of which the
    cost model sizes for itself (unless `layers` chose the kernel's block: `own` is False)."""
    if kernel.op != "Band" or not own:
        return block_body(kernel.body, *block)
    planar = planar_tensors(program)

    def per_nest(pixel: Loop) -> tuple[int, int]:
        pixels, channels = pair_dot_block(kernel, program, target, nest_facts(kernel, pixel, program, target))
        return (1 if reads_across_planes((pixel,), planar) else pixels), channels

    return block_body(kernel.body, *block, per_nest)


def chosen_blocks(
    program: Program, target: Target, layers: dict[str, tuple[int, int]] | None = None
) -> dict[str, tuple[int, int]]:
    """Layer -> (pixels, channel vectors) the pass blocks it by: `layers`' choice, else the cost model's
    (one pixel where the layer reads across planes). Also what --report shows."""
    layers = layers or {}
    blocks = {}
    for kernel in program.kernels:
        # an int8 kernel is blocked once vectorised (int32 vector accumulators), a scalar one is not
        scalar_integer = is_integer_kernel(kernel, program) and not any(
            e.lanes > 1 for s in walk_stmts(kernel.body) for top in stmt_exprs(s) for e in walk_exprs(top)
        )
        facts = None if scalar_integer else kernel_facts(kernel, program, target)
        if facts is None:
            continue
        pixels, channels = layers.get(kernel.name) or pair_dot_block(kernel, program, target, facts)
        if kernel.name not in layers and facts.fused and channels == 1:
            pixels = one_vector_pixels(kernel, program, target, facts.shape[0], pixels, facts.vector_inputs)
        if kernel.name not in layers and reads_across_planes(kernel.body, planar_tensors(program)):
            pixels = 1
        blocks[kernel.name] = (pixels, channels)
    return blocks


def pair_dot_block(kernel: Kernel, program: Program, target: Target, facts: NestFacts) -> tuple[int, int]:
    """The cost model's block, but one pixel of up to PAIR_DOT_CHANNELS channel vectors for an int8 kernel
    whose products are all pmaddwd pairs of shared activations on SSE (Target.dot2_quad_loads). Each
    pmaddwd reads its weights from memory and overwrites a copy of its broadcast activations (two-operand
    instructions), so pixels in a block share nothing a register would keep and only add live
    activations and accumulators: the 2x4 blocks spilled accumulators and copied them across the loop's
    back edge. Ten accumulators, two activation pairs, a product and a zero still fit 16 registers.
    Callgrind Ir, gcc -O3 (-fno-inline per layer): dscnn's pointwise layers 288,420 -> 270,913,
    mobilenet_v1_025's 6x6x128 ones 311,633 -> 302,065, resnet8's Winograd GEMM layers 989,034 ->
    863,142; whole models 1,855,035 -> 1,798,843, 5,221,588 -> 5,023,829, 5,597,341 -> 5,308,906 (8
    channel vectors: 1,814,977, 5,109,474, 5,314,333; 12: 1,804,387, 4,973,178, 5,330,078). A dense
    layer's "pixels" are its output vectors: the autoencoder's took 311,703 Ir as one, 285,099 as 10."""
    pair_dots = target.dot2_quad_loads and is_integer_kernel(kernel, program) and _pair_dots_only(kernel)
    if not pair_dots or facts.shape[1] == 1:  # one vector a pixel (a dense layer's): its pixels are channels
        return facts.choose()
    return 1, min(facts.shape[1], PAIR_DOT_CHANNELS)


def _pair_dots_only(kernel: Kernel) -> bool:
    """Whether the kernel's products are all dots of 2 adjacent activations summed in one loop under
    their accumulators: a reduction over input channels only, as a 1x1 convolution's, a dense layer's or
    integer Winograd's GEMMs have (not a first layer's taps, whose pairs are packed from
    zero-point-shifted values, nor a KxK convolution, whose pixels share border checks and loops over
    taps: resnet8's stride-2 3x3 one 760,461 -> 981,401 Ir as one pixel)."""
    dots = body_dots(kernel.body)
    if not dots or not all(len(d.x) == 2 and _adjacent_loads(d.x) for d in dots):
        return False
    depths = [_serial_depth(s.body) for s in walk_stmts(kernel.body) if isinstance(s, Let)]
    return max(depths, default=0) == 1


def _serial_depth(body: tuple[Stmt, ...], depth: int = 0) -> int:
    """The most serial loops around a statement of `body`."""
    deepest = depth
    for stmt in body:
        if isinstance(stmt, Loop | Let | If):
            inner = depth + (isinstance(stmt, Loop) and not stmt.parallel)
            deepest = max(deepest, _serial_depth(stmt.body, inner))
    return deepest


def _adjacent_loads(xs: tuple[Expr, ...]) -> bool:
    """Activations of adjacent elements from the first on, a missing last channel read as 0."""
    first = xs[0].value if isinstance(xs[0], Cast) else None
    return isinstance(first, Load) and all(
        x in (Cast(DType.INT32, Load(first.buffer, first.index + j)), Const.integer(0)) for j, x in enumerate(xs)
    )


def one_vector_pixels(kernel: Kernel, program: Program, target: Target, extent: int, pixels: int, vector_inputs: bool):
    """The pixels of a fused layer of one channel vector: at most ONE_VECTOR_INT8_PIXELS (int8),
    ONE_VECTOR_FLOAT_PIXELS (float, its broadcast inputs read by the multiply-adds)."""
    if is_integer_kernel(kernel, program):
        return min(pixels, ONE_VECTOR_INT8_PIXELS)
    if target.broadcast_operands and not vector_inputs:
        return min(extent, ONE_VECTOR_FLOAT_PIXELS)
    return pixels


# ---------------------------------------------------------------------------- structure


def pixel_loop_of(stmt: Stmt) -> Loop | None:
    """The innermost parallel loop at or below stmt that encloses every accumulator under stmt and
    is not a channel loop (unless there is nothing outside the channel loop to block)."""
    if not isinstance(stmt, Loop) or not stmt.parallel or not holds_accumulators(stmt):
        return None
    inner = [s for s in stmt.body if isinstance(s, Loop) and holds_accumulators(s)]
    if len(inner) == 1 and not is_channel_loop(stmt):
        deeper = pixel_loop_of(inner[0])
        if deeper is not None and not is_channel_loop(deeper):
            return deeper
    return stmt


def row_loop_of(body: tuple[Stmt, ...], pixel: Loop) -> Loop | None:
    """The parallel loop in body directly around the pixel loop (its rows), if its iterations may run
    jammed and the pixel loop is all it blocks; else None."""
    for loop in walk_stmts(body):
        if isinstance(loop, Loop) and any(s is pixel for s in loop.body):
            inner = [s for s in loop.body if isinstance(s, Loop) and holds_accumulators(s)]
            fits = loop.parallel and inner == [pixel] and not is_channel_loop(loop) and jammable(loop)
            return loop if fits else None
    return None


def row_extent(body: tuple[Stmt, ...], pixel: Loop | None) -> int:
    """Rows a block of the pixel loop in body may span: its row loop's extent, else 1."""
    rows = None if pixel is None else row_loop_of(body, pixel)
    return 1 if rows is None else rows.extent


def is_channel_loop(loop: Loop) -> bool:
    """A loop over output-channel blocks: it holds accumulators directly and its iterations store
    side by side (the vector loop strides by its lanes, the scalar tail by 1); not the column loop of
    a layer of one channel vector, which also stores side by side (one_vector_columns)."""
    stores = [s for s in walk_stmts(loop.body) if isinstance(s, Store)]
    accumulators = [s for s in loop.body if is_accumulator(s)]
    if not accumulators or one_vector_columns(loop, accumulators):
        return False
    return all(s.index.coeff(loop.var) == s.value.lanes for s in stores)


def one_vector_columns(loop: Loop, accumulators: list[Let]) -> bool:
    """Whether the loop's accumulators start from a load that stays put (one vector's bias): it runs
    over pixels, blocked as such (resnet8's 32x32x16 layers on avx512vnni 1.8x faster than jamming 4
    columns)."""
    return any(isinstance(s.init, Load) and loop.var not in s.init.index.vars for s in accumulators)


def first_pixel_loop(body: tuple[Stmt, ...]) -> Loop | None:
    """The pixel loop of the first blockable nest, or None."""
    for stmt in body:
        pixel = pixel_loop_of(stmt) if isinstance(stmt, Loop) else None
        if pixel is not None and jammable(pixel):
            return pixel
        if isinstance(stmt, Loop | Let | If):
            inner = first_pixel_loop(stmt.body)
            if inner is not None:
                return inner
    return None


def block_shape(body: tuple[Stmt, ...]) -> tuple[int, int] | None:
    """(pixel loop extent, accumulators per pixel) of the first blockable nest, or None (also when
    its pixels hold their accumulators only in inner loops, as split border columns do)."""
    pixel = first_pixel_loop(body)
    vectors = 0 if pixel is None else sum(_vectors(s) for s in pixel.body)
    return (pixel.extent, vectors) if vectors else None


def _vectors(stmt: Stmt) -> int:
    """Accumulators (channel vectors) one pixel's statement holds: a channel loop holds one per iteration."""
    if is_accumulator(stmt):
        return 1
    if isinstance(stmt, Loop) and is_channel_loop(stmt):
        return stmt.extent
    return 0


def jammable(loop: Loop) -> bool:
    """Iterations that may run interleaved: parallel, a buffer they write read only at the element each
    iteration writes (a partial sum read back), and locals assigned only where declared (so each
    jammed copy gets its own)."""
    if not loop.parallel:
        return False
    written: dict[str, list[Store]] = {}
    for stmt in walk_stmts(loop.body):
        if isinstance(stmt, Store):
            written.setdefault(stmt.buffer, []).append(stmt)
    inner: dict[str, int] = {}  # the loops inside, each var at its largest extent (siblings may share one)
    for s in walk_stmts(loop.body):
        if isinstance(s, Loop):
            inner[s.var] = max(s.extent, inner.get(s.var, 0))
    own = {
        buffer: {s.index for s in stores}
        for buffer, stores in written.items()
        if len({s.index for s in stores}) == 1 or _disjoint_per_iteration(stores, loop.var, inner)
    }
    declared = {s.name for s in walk_stmts(loop.body) if isinstance(s, Let)}
    for stmt in walk_stmts(loop.body):
        if isinstance(stmt, Assign) and stmt.name not in declared:
            return False
        for top in stmt_exprs(stmt):
            for e in walk_exprs(top):
                if isinstance(e, Load) and e.buffer in written and not _reads_own_element(e, own, loop.var):
                    return False
    return True


def _reads_own_element(load: Load, own: dict, var: str) -> bool:
    """The load reads an element of its buffer this iteration stores (a different one per iteration)."""
    return load.index in own.get(load.buffer, ()) and load.index.coeff(var) != 0


def _disjoint_per_iteration(stores: list[Store], var: str, inner: dict[str, int]) -> bool:
    """Each iteration of `var` stores elements no other iteration stores: all the stores step by the
    same stride in var, their elements within an iteration (over the `inner` loops, the vector's lanes)
    span less than it, and the rest of their indices (outer loops) is the same. So a layer whose
    channel vectors and tail store side by side (40 = 16 + 16 + 8 channels) reads its partial sums back
    jammed, as one of a single store does."""
    step = stores[0].index.coeff(var)
    outer = {tuple(t for t in s.index.terms if t[0] != var and t[0] not in inner) for s in stores}
    if step <= 0 or len(outer) != 1 or any(s.index.coeff(var) != step for s in stores):
        return False
    spans = [_within_iteration(s, var, inner) for s in stores]
    return max(hi for _, hi in spans) - min(lo for lo, _ in spans) < step


def _within_iteration(store: Store, var: str, inner: dict[str, int]) -> tuple[int, int]:
    """The first and last element (offsets from the iteration's start) the store writes in one iteration."""
    offset = Affine(tuple(t for t in store.index.terms if t[0] in inner), store.index.const)
    lo, hi = offset.bounds(inner)
    return lo, hi + max(1, store.value.lanes) - 1


# ---------------------------------------------------------------------------- cost model


def tuning_candidates(program: Program, target: Target) -> dict[str, tuple[tuple[int, int], ...]]:
    """For --tune: each blockable layer's block shapes worth timing."""
    out = {}
    for kernel in program.kernels:
        facts = kernel_facts(kernel, program, target)
        if facts is not None:
            out[kernel.name] = tuple(facts.candidates())
    return out


@dataclass(frozen=True)
class NestFacts:
    """What the cost model sizes a nest's block from, read off its kernel for the target (nest_facts),
    so that blocking, --report and --tune ask it the same question."""

    shape: tuple[int, int]  # (pixel loop extent, channel vectors per pixel)
    registers: int
    fused: bool  # fused_kernel
    vector_inputs: bool  # multiplies_vector_inputs
    rows: int  # row_extent

    def choose(self) -> tuple[int, int]:
        return choose_blocks(self.shape, self.registers, self.fused, self.vector_inputs, self.rows)

    def candidates(self) -> list[tuple[int, int]]:
        return block_candidates(self.shape, self.registers, self.fused, self.vector_inputs, self.rows)


def nest_facts(kernel: Kernel, pixel: Loop, program: Program, target: Target) -> NestFacts:
    """The facts of the nest around `pixel` in `kernel`."""
    return NestFacts(
        (pixel.extent, sum(_vectors(s) for s in pixel.body)),
        min(target.registers, FLIPPED_REGISTERS) if flipped_activations(kernel, target) else target.registers,
        fused_kernel(kernel, program, target),
        multiplies_vector_inputs(pixel, constant_buffers(program)),
        row_extent(kernel.body, pixel),
    )


def kernel_facts(kernel: Kernel, program: Program, target: Target) -> NestFacts | None:
    """The facts of the kernel's first blockable nest (block_shape's), None when it has none."""
    pixel = first_pixel_loop(kernel.body)
    facts = None if pixel is None else nest_facts(kernel, pixel, program, target)
    return facts if facts is not None and facts.shape[1] else None


def blockable(program: Program) -> dict[str, tuple[int, int]]:
    """Layer -> (pixel extent, channel vectors) of every kernel the pass would block."""
    shapes = {k.name: block_shape(k.body) for k in program.kernels}
    return {name: shape for name, shape in shapes.items() if shape is not None}


def block_candidates(
    shape: tuple[int, int], registers: int, fused: bool = False, vector_inputs: bool = False, rows: int = 1
) -> list[tuple[int, int]]:
    """Block shapes worth timing: the cost model's first, then pixel counts up to a register file
    of accumulators, with all channel vectors of a pixel (or 2, 3, 4 of them when there are many)."""
    extent, vectors = shape
    first = choose_blocks(shape, registers, fused, vector_inputs, rows)
    channel_options = [vectors] if vectors <= 5 else [2, 3, 4]
    out = [first]
    for channels in channel_options:
        for pixels in PIXEL_BLOCKS:
            if pixels <= extent and pixels * channels <= registers - 2 and (pixels, channels) not in out:
                out.append((pixels, channels))
    return out


def fma_from_memory(target: Target) -> bool:
    """Whether a float multiply-add on `target` is one instruction reading its weight vector from memory."""
    return target.fma and target.memory_operands


# The registers a block of dots with flipped activations is sized for: gcc 12 hoists every pixel's
# xor-ed broadcast ahead of the dots, and past about 20 live vectors it copies and spills accumulators
# every reduction step (mlperf_kws_dscnn int8, avx512vnni, 1x1 64 -> 64 on 25x5: 5x4 blocks 78-92 us
# for the model, 4x4 48, 3x4 33, 5x2 28; clang 14 was fine with 5x4).
FLIPPED_REGISTERS = 20


def fused_kernel(kernel: Kernel, program: Program, target: Target) -> bool:
    """fma_from_memory for a float kernel, and for an int8 kernel whose products are all dots of 4
    shared activations (vpdpbusd: acc + dot is one instruction reading its weights from memory); other
    int8 kernels multiply and add in two instructions."""
    if not fma_from_memory(target):
        return False
    if not is_integer_kernel(kernel, program):
        return True
    dots = body_dots(kernel.body)
    return bool(dots) and all(len(d.x) == 4 and all(x.lanes == 1 for x in d.x) for d in dots)


def flipped_activations(kernel: Kernel, target: Target) -> bool:
    """Whether the kernel's dots read int8 activations as uint8 x + 128 (Target.dot_uint8_activations)."""
    flipped = Const.integer(-128)
    dots = body_dots(kernel.body)
    return target.dot_uint8_activations and any(isinstance(x, Binary) and x.b == flipped for d in dots for x in d.x)


def choose_blocks(
    shape: tuple[int, int], registers: int, fused: bool = False, vector_inputs: bool = False, rows: int = 1
) -> tuple[int, int]:
    """Pixels x channel vectors. All of a pixel's channel vectors when they are few (each saves a
    broadcast per tap), else MAX_CHANNEL_BLOCK; then as many pixels as keep the accumulators to
    `registers - RESERVED` (measured on SSE: more spills, fewer leave the adds waiting). Where a
    multiply-add reads its weight from memory (`fused`: x86 FMA) no product or weight registers are
    needed, but the C compiler loads every pixel's broadcast input before the multiply-adds: a pixel
    takes its accumulators and a broadcast, and one weight vector is left (avx2: 3x4 instead of 2x4,
    squeezenet1_1 and regnet_x_400mf 1.07x-1.13x faster; 6x2, 12 accumulators and 6 broadcasts,
    spilled three accumulators every reduction step). Where each channel vector multiplies its own
    input vector (`vector_inputs`, a depthwise Conv) nothing is shared across a pixel's channels and
    the compiler loads those inputs ahead as it does broadcasts: fused, with 4 channel vectors, at most
    VECTOR_INPUT_PIXELS pixels (what avx2's 16 registers give anyway; avx512's 32 would give 6).
    Where the pixel loop is shorter than the registers allow and sits in a loop of `rows`, the block
    takes whole rows, as many as fit: each weight vector then serves the pixels of several rows
    (resnet18's layer4, 3x3 pixels, avx512: 6x4, two rows, 1.07x faster than 3x4; 9x3 spills)."""
    extent, vectors = shape
    channels = channel_block(vectors)
    fit = (registers - 1) // (channels + 1) if fused else (registers - RESERVED) // channels
    if fused and vector_inputs and channels == MAX_CHANNEL_BLOCK - 1:
        fit = min(fit, VECTOR_INPUT_PIXELS)
    pixels = max(1, min(extent, fit))
    if pixels == extent and rows > 1 and fit >= 2 * extent:
        pixels = extent * min(rows, fit // extent)
    return pixels, channels


def channel_block(vectors: int) -> int:
    """The channel vectors a block jams of a pixel's `vectors` (choose_blocks; cache-block's panels)."""
    return vectors if vectors <= MAX_CHANNEL_BLOCK else MAX_CHANNEL_BLOCK - 1


def constant_buffers(program: Program) -> set[str]:
    return {b.name for b in program.buffers if b.role == BufferRole.CONSTANT}


def multiplies_vector_inputs(pixel: Loop | None, constants: set[str]) -> bool:
    """Whether an accumulator under the pixel loop adds products of a vector of weights and a vector
    of activations (a depthwise Conv: one input per channel, not one broadcast for all of them)."""
    if pixel is None:
        return False
    for stmt in walk_stmts(pixel.body):
        if not is_accumulator(stmt):
            continue
        loads = {
            e.buffer in constants
            for update in walk_stmts(stmt.body)
            if isinstance(update, Assign) and update.name == stmt.name
            for e in walk_exprs(update.value)
            if isinstance(e, Load) and e.lanes > 1
        }
        if loads == {True, False}:
            return True
    return False


def planar_tensors(program: Program) -> dict[str, int]:
    """The activation buffers stored row-major with channels before the pixels (NCHW), with the size
    of one channel's plane: the graph's inputs and outputs, and what a layer vectorised over pixels
    writes (the layout the lowering recorded, typed, on each buffer)."""
    return {
        b.name: math.prod(b.shape[2:])
        for b in program.buffers
        if b.role != BufferRole.CONSTANT and b.layout == Layout.ROW_MAJOR and len(b.shape) >= 3
    }


def reads_across_planes(body: tuple[Stmt, ...], planar: dict[str, int]) -> bool:
    """Whether a channel loop of the first blockable nest reads a planar tensor channel by channel
    (a channels-last consumer of a planar tensor, element by element). Jamming its pixels as well
    measured slower (robot pool1 after a pixel-vectorised conv1, avx512: 6x4 5.9 us, 2x4 5.9, 1x4
    2.3), so such a layer jams channels only."""
    pixel = first_pixel_loop(body)
    if pixel is None:
        return False
    return any(_reads_planes(s, planar) for s in walk_stmts(pixel.body) if isinstance(s, Loop) and is_channel_loop(s))


def _reads_planes(loop: Loop, planar: dict[str, int]) -> bool:
    """A load from a planar tensor that moves a whole plane per iteration of the channel loop."""
    if loop.extent < 2:
        return False
    for stmt in walk_stmts(loop.body):
        for top in stmt_exprs(stmt):
            for e in walk_exprs(top):
                if isinstance(e, Load) and e.buffer in planar and abs(e.index.coeff(loop.var)) >= planar[e.buffer] > 1:
                    return True
    return False


# ---------------------------------------------------------------------------- mechanism


def block_body(body: tuple[Stmt, ...], pixels: int, channels: int, per_nest=None) -> tuple[Stmt, ...]:
    """Every blockable nest blocked by pixels x channels, or by what `per_nest(pixel loop)` says."""
    out: list[Stmt] = []
    for stmt in body:
        pixel = pixel_loop_of(stmt) if isinstance(stmt, Loop) else None
        if pixel is not None and jammable(pixel):
            block = per_nest(pixel) if per_nest else (pixels, channels)
            out.extend(_block_nest(stmt, pixel, *block))
        elif isinstance(stmt, Loop | Let | If):
            out.append(replace(stmt, body=block_body(stmt.body, pixels, channels, per_nest)))
        else:
            out.append(stmt)
    return tuple(out)


def _block_nest(stmt: Loop, pixel: Loop, pixels: int, channels: int) -> tuple[Stmt, ...]:
    """The nest `stmt` with its pixel loop blocked; a block of whole rows (`pixels` at least twice the
    pixel loop's extent) jams the pixel loop entirely and its row loop by `pixels // extent`."""
    rows = row_loop_of((stmt,), pixel) if pixels >= 2 * pixel.extent else None
    if rows is None:
        return _replace_loop(stmt, pixel, _block_pixel_loop(pixel, pixels, channels))
    columns = _block_pixel_loop(pixel, pixel.extent, channels)
    row = replace(rows, body=tuple(s for child in rows.body for s in _replace_loop(child, pixel, columns)))
    return _replace_loop(stmt, rows, jam_loop(row, pixels // pixel.extent))


def unroll_pair_reductions(body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    """Reduction loops of K = 2 dots of shared activations unrolled by 2 (Target.dot2_quad_loads): the
    two pairs of a 4-byte activation load then sit in one body, where the printer widens both from one
    load, and the accumulators cross the loop's back edge half as often (GCC copies them there). ssse3
    int8, loaded, interleaved: dscnn 1.11x-1.21x, mobilenet_v1_025 1.03x-1.11x, autoencoder 1.25x
    faster; more accumulators instead (1x12, 2x6 blocks: fewer instructions) spilled and ran slower."""
    out: list[Stmt] = []
    for stmt in body:
        if isinstance(stmt, Loop) and _reduces_pairs(stmt):
            out.extend(_unrolled_by_2(stmt))
        elif isinstance(stmt, Loop | Let | If):
            out.append(replace(stmt, body=unroll_pair_reductions(stmt.body)))
        else:
            out.append(stmt)
    return tuple(out)


def _reduces_pairs(loop: Loop) -> bool:
    """A serial loop of at least 2 iterations whose body only accumulates dots of 2 shared activations."""
    if loop.parallel or loop.extent < 2 or not all(isinstance(s, Assign) for s in loop.body):
        return False
    dots = body_dots(loop.body)  # its Assigns' values
    return bool(dots) and all(len(d.x) == 2 and all(x.lanes == 1 for x in d.x) for d in dots)


def _unrolled_by_2(loop: Loop) -> tuple[Stmt, ...]:
    """The loop with iterations 2 i and 2 i + 1 in one body, an odd last iteration after it."""
    var, pairs = loop.var, loop.extent // 2
    at = Affine.of(var) * 2 if pairs > 1 else Affine.of(0)
    body = tuple(s for j in range(2) for s in substitute_body(loop.body, {var: at + j}))
    paired = (replace(loop, extent=pairs, body=body),) if pairs > 1 else body
    return paired + iterations(loop, 2 * pairs, loop.extent)


def _replace_loop(stmt: Stmt, target: Loop, new: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    if stmt is target:
        return new
    if isinstance(stmt, Loop | Let | If):
        body = tuple(s for child in stmt.body for s in _replace_loop(child, target, new))
        return (replace(stmt, body=body),)
    return (stmt,)


def _block_pixel_loop(loop: Loop, pixels: int, channels: int) -> tuple[Stmt, ...]:
    body: list[Stmt] = []
    for stmt in loop.body:
        if isinstance(stmt, Loop) and is_channel_loop(stmt) and jammable(stmt):
            body.extend(jam_loop(stmt, channels))
        else:
            body.append(stmt)
    return jam_loop(replace(loop, body=fuse_siblings(tuple(body), channels)), pixels)


def fuse_siblings(body: tuple[Stmt, ...], limit: int) -> tuple[Stmt, ...]:
    """Consecutive accumulators of one pixel (an 8-lane and a 4-lane block of 12 channels, a jammed
    block and a leftover vector) share their reduction loops, up to `limit` accumulators together."""
    out: list[Stmt] = []
    run: list[Stmt] = []
    for stmt in (*body, None):
        if stmt is not None and is_accumulator(stmt) and len(_let_chain(stmt)[0]) + _count(run) <= limit:
            run.append(stmt)
            continue
        out.extend(_fused_run(run))
        run = [stmt] if stmt is not None and is_accumulator(stmt) else []
        if stmt is not None and not is_accumulator(stmt):
            out.append(stmt)
    return tuple(out)


def _count(run: list[Stmt]) -> int:
    return sum(len(_let_chain(s)[0]) for s in run)


def _let_chain(stmt: Let) -> tuple[list[Let], tuple[Stmt, ...]]:
    """The Lets of a chain (a Let whose body is just the next Let) and the innermost body."""
    lets = [stmt]
    while len(lets[-1].body) == 1 and isinstance(lets[-1].body[0], Let):
        lets.append(lets[-1].body[0])
    return lets, lets[-1].body


def _fused_run(run: list[Stmt]) -> tuple[Stmt, ...]:
    if len(run) < 2:
        return tuple(run)
    chains = [_let_chain(_suffixed_locals((s,), f"_s{i}")[0]) for i, s in enumerate(run)]
    inners = [inner for _, inner in chains]
    body = fuse(inners) or merge(inners)
    if body is None:
        return tuple(run)
    for let in reversed([let for lets, _ in chains for let in lets]):
        body = (replace(let, body=body),)
    return body


def merge(bodies: list[tuple[Stmt, ...]]) -> tuple[Stmt, ...] | None:
    """Sibling accumulators' bodies of different sizes in one (a jammed block of 2 channel vectors and
    a half-width tail vector: 40 channels on avx512), so each broadcast input serves all of them: each
    body is loops and border checks, then stores; the loops and checks, of the same shape in every body,
    are shared with their bodies merged, and the statements follow one body's after the other's. None
    when the bodies are not of that form."""
    heads = [tuple(takewhile(lambda s: isinstance(s, Loop | If), b)) for b in bodies]
    tails = [b[len(h) :] for b, h in zip(bodies, heads)]
    if len({len(h) for h in heads}) != 1 or not all(isinstance(s, Store | Assign) for t in tails for s in t):
        return None
    out: list[Stmt] = []
    for stmts in zip(*heads):
        head = replace(stmts[0], body=())
        body = merge([s.body for s in stmts]) if all(replace(s, body=()) == head for s in stmts) else None
        if body is None:
            return None
        out.append(replace(stmts[0], body=body))
    return (*out, *(s for t in tails for s in t))


def jam_loop(loop: Loop, factor: int) -> tuple[Stmt, ...]:
    """The loop with `factor` consecutive interior iterations jammed into one: border iterations,
    then the jammed blocks (what is left over in one smaller block), then the far border."""
    first, last = interior(loop)
    factor = min(factor, last - first)
    if factor <= 1:
        return (loop,)
    jammed = _jammed_range(loop, first, last, factor)
    if jammed is None:
        return (loop,)
    return iterations(loop, 0, first) + jammed + iterations(loop, last, loop.extent)


def _jammed_range(loop: Loop, start: int, stop: int, factor: int) -> tuple[Stmt, ...] | None:
    """Iterations [start, stop), whose border checks all hold, `factor` at a time in one body."""
    var, blocks = loop.var, (stop - start) // factor
    extents = {var: blocks} if blocks > 1 else {}
    copies = []
    for j in range(factor):
        at = Affine.of(var) * factor + (start + j) if blocks > 1 else Affine.of(start + j)
        copy = prune_bounds(substitute_body(loop.body, {var: at}), extents)
        copies.append(_suffixed_locals(copy, f"_{j}"))
    fused = fuse(copies)
    if fused is None:
        return None
    out = (replace(loop, extent=blocks, body=fused),) if blocks > 1 else fused
    done = start + blocks * factor
    rest = _jammed_range(loop, done, stop, stop - done) if stop - done > 1 else None
    return out + (rest if rest is not None else iterations(loop, done, stop, prune=True))


def _suffixed_locals(body: tuple[Stmt, ...], suffix: str) -> tuple[Stmt, ...]:
    names = {s.name: s.name + suffix for s in walk_stmts(body) if isinstance(s, Let)}
    return rename_variables(body, names) if names else body


def fuse(copies: list[tuple[Stmt, ...]]) -> tuple[Stmt, ...] | None:
    """One body doing the work of all copies, interleaved statement by statement: loops and border
    checks of the same shape are shared, locals declared around the shared body. None when the
    copies differ in shape (then they cannot be jammed)."""
    first = copies[0]
    if any(len(c) != len(first) for c in copies):
        return None
    out: list[Stmt] = []
    for stmts in zip(*copies):
        head = stmts[0]
        if isinstance(head, Loop | If):
            same = all(type(s) is type(head) and replace(s, body=()) == replace(head, body=()) for s in stmts)
            body = fuse([s.body for s in stmts]) if same else None
            if body is None:
                return None
            out.append(replace(head, body=body))
        elif isinstance(head, Let):
            if not all(isinstance(s, Let) for s in stmts):
                return None
            body = fuse([s.body for s in stmts])
            if body is None:
                return None
            for let in reversed(stmts):
                body = (replace(let, body=body),)
            out.extend(body)
        elif all(isinstance(s, Store | Assign) for s in stmts):
            out.extend(stmts)
        else:
            return None
    return tuple(out)
