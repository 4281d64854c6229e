"""ConvTranspose lowering as a gather: each output sums the taps that reach it, so every output is
written once, by one store, and the output-channel loop vectorises as in Conv.

Output o receives input i through tap k when o = i*stride + k*dilation - pad_begin, that is when
i = (o + pad_begin - k*dilation) / stride is integral and inside the input. Integrality is decided
at compile time by splitting each output dim by stride phase, o = stride*q + phase: for a fixed
phase the taps that reach it are k = first + step*j (step = stride / gcd(stride, dilation)) and
tap j reads input q + offset - shift*j, affine in q and j. A kernel is one loop nest per
combination of phases (prod(strides) nests, one for stride 1), each a windowed accumulation with
the usual border checks. Phases no tap reaches store the bias.

Weights [C_in, C_out/group, k...] are read as [k...][c_in/group][group][c_out/group], packed in
that order when constant, so c_out is contiguous (and the group for a depthwise layer)."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from ..ir.graph import ConvTransposeAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Loop, Stmt, Store
from .context import LoweringContext, TensorRef, channels_last, nest
from .weights import permuted, split, weight_operand
from .window import guarded_taps, spatial_names


@dataclass(frozen=True)
class PhaseTaps:
    """The taps of one spatial dim reaching outputs stride*q + phase: tap j (j < count) is kernel
    index first + step*j and reads input q + offset - shift*j."""

    first: int
    step: int
    count: int
    offset: int
    shift: int


def phase_taps(phase: int, kernel: int, stride: int, dilation: int, pad_begin: int) -> PhaseTaps:
    # k*dilation = phase + pad_begin (mod stride) has solutions spaced `step` apart.
    step = stride // math.gcd(stride, dilation)
    solutions = [k for k in range(min(step, kernel)) if (phase + pad_begin - k * dilation) % stride == 0]
    if not solutions:
        return PhaseTaps(0, step, 0, 0, 0)
    first = solutions[0]
    offset = (phase + pad_begin - first * dilation) // stride  # exact: the numerator is a multiple
    return PhaseTaps(first, step, len(range(first, kernel, step)), offset, step * dilation // stride)


@dataclass(frozen=True)
class Operands:
    """Where the layer reads and writes, shared by its phase nests."""

    x: TensorRef
    w: TensorRef  # [k..., c_in/group, group, c_out/group]
    bias: TensorRef | None
    out: TensorRef


def lower_conv_transpose(ctx: LoweringContext, node: Node) -> None:
    attrs: ConvTransposeAttrs = node.attrs
    rank = len(attrs.kernel)
    # [C_in, C_out_g, k...] -> [G, C_in_g, C_out_g, k...] -> [k..., C_in_g, G, C_out_g]
    perm = (*range(3, rank + 3), 1, 0, 2)
    w = weight_operand(ctx, node.inputs[1], f"w_{node.name}", lambda r: permuted(split(r, 0, attrs.group), perm))
    bias = weight_operand(ctx, node.inputs[2], f"b_{node.name}") if len(node.inputs) > 2 else None
    refs = Operands(ctx.ref(node.inputs[0]), w, bias, ctx.output(node.outputs[0], channels_last(rank + 2)))
    body: list[Stmt] = []
    for phases in itertools.product(*(range(s) for s in attrs.strides)):
        body += _phase_nest(attrs, refs, phases)
    ctx.emit(node.name, "ConvTranspose", tuple(body))


def _phase_nest(attrs: ConvTransposeAttrs, refs: Operands, phases: tuple[int, ...]) -> tuple[Stmt, ...]:
    """The loop nest writing the outputs o = stride*q + phase (per dim), or () if there are none."""
    x, w, bias, out = refs.x, refs.w, refs.bias, refs.out
    names = spatial_names(len(phases))
    phase_ranges = zip(phases, out.shape[2:], attrs.strides)  # o = phase, phase + stride, ... < size
    q_loops = [("o" + s, len(range(*r))) for s, r in zip(names, phase_ranges)]
    if any(extent == 0 for _, extent in q_loops):
        return ()
    taps = [phase_taps(*d) for d in zip(phases, attrs.kernel, attrs.strides, attrs.dilations, attrs.pads_begin)]
    c_in_g, groups, c_out_g = w.shape[-3:]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, g, co = env["n"], env["g"], env["co"]
        q = [env[var] for var, _ in q_loops]
        tap_loops = [("k" + s, t.count) for s, t in zip(names, taps)]
        j = [Affine.of(var) if extent > 1 else Affine() for var, extent in tap_loops]
        positions = [qi + t.offset - ji * t.shift for qi, ji, t in zip(q, j, taps)]
        k_index = [ji * t.step + t.first for ji, t in zip(j, taps)]
        ci = Affine.of("ci") if c_in_g > 1 else Affine()

        def tap() -> tuple[Stmt, ...]:
            x_load = Load(x.buffer, x.at([n, g * c_in_g + ci, *positions]))
            product = Binary("*", x_load, Load(w.buffer, w.at([*k_index, ci, g, co])))
            update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
            return (Loop("ci", c_in_g, update),) if c_in_g > 1 else update

        reached = all(t.count for t in taps)
        window = guarded_taps(tap_loops, positions, x.spatial_ranges, dict(q_loops), tap) if reached else ()
        c = g * c_out_g + co
        init = Load(bias.buffer, bias.at([c])) if bias else Const.splat(0.0)
        o = [qi * stride + p for qi, stride, p in zip(q, attrs.strides, phases)]
        return (Let("acc", init, (*window, Store(out.buffer, out.at([n, c, *o]), LocalRef("acc")))),)

    loops = [("n", out.shape[0]), *q_loops, ("g", groups), ("co", c_out_g)]
    return nest(loops, body, parallel=True)
