"""Cache-blocked direct convolution (the cache-block pass chose it; see nncg/passes/cache_block.py).

The output channels are split into panels of `attrs.panel` (the last one may be narrower), the
input channels into blocks of `attrs.ci_block`. For each panel, one nest over the output pixels per
reduction block, the panel's channels innermost (they vectorise and register-block as in conv.py):

    for panel:
        first block:         acc = bias;      acc += x * w over its input channels; out = acc
        middle blocks (kb):  acc = out;       ...;                                   out = acc
        last block:          acc = out;       ...;                                   out = act(acc + residual)

A single block is first and last at once. Weights are packed in the order the nests read them:
[panel][block][k_1..k_d][input channel in block][channel in panel], so each block of pixels streams
one contiguous slice of them, small enough to stay in L1 across the pixel blocks. A grouped Conv's
panel is one group: panel g reads the input channels of group g."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from ..ir.graph import ConvAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Const, Expr, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, channels_last, nest
from .conv import conv_extras
from .weights import by_panels, weight_operand
from .window import around_row_taps, spatial_names, window_nest


class _Operands(NamedTuple):
    x: TensorRef
    out: TensorRef
    bias: TensorRef | None
    residual: TensorRef | None


def lower_blocked_conv(ctx: LoweringContext, node: Node) -> None:
    attrs: ConvAttrs = node.attrs
    weights = ctx.graph.constants[node.inputs[1]]  # [c_out, c_in / group, k_1..k_d]
    c_out, c_in_group = weights.shape[:2]
    bias_name, residual_name = conv_extras(node)
    operands = _Operands(
        ctx.ref(node.inputs[0]),
        ctx.output(node.outputs[0], channels_last(len(attrs.kernel) + 2)),
        weight_operand(ctx, bias_name, f"b_{node.name}") if bias_name else None,
        ctx.ref(residual_name) if residual_name else None,
    )
    if _pointwise(attrs):
        attrs, operands = _flattened(attrs, operands)
        weights = weights.reshape(*weights.shape[:2], *attrs.kernel)

    def pack(start: int, stop: int, panels: int) -> np.ndarray:
        return _packed(weights[start:stop], panels, attrs.ci_block)

    def nests(w: TensorRef, panel: Affine, first_channel: Affine, width: int) -> tuple[Stmt, ...]:
        first_input = panel * c_in_group if attrs.group > 1 else Affine()  # a group per panel
        return _stages(attrs, operands, w, panel, (first_channel, first_input), width)

    body = by_panels(ctx, f"w_{node.name}", c_out, attrs.panel, pack, nests)
    ctx.emit(node.name, "Conv", body)


def _pointwise(attrs: ConvAttrs) -> bool:
    return all(k == 1 for k in attrs.kernel) and all(s == 1 for s in attrs.strides) and not any(attrs.pads_begin)


def _flattened(attrs: ConvAttrs, ops: _Operands) -> tuple[ConvAttrs, _Operands]:
    """A 1x1, stride-1 conv over the output pixels as one dim where every tensor it touches stores
    them so (no halo, spatial dims adjacent and in order): the register block then spans rows (a
    3x3 image is 9 pixels to block, not 3 rows of 3)."""
    refs = [ops.x, ops.out, *(r for r in (ops.residual,) if r)]
    flat = [_flat_spatial(r) for r in refs]
    if any(f is None for f in flat):
        return attrs, ops
    one = (1,)
    attrs = replace(attrs, kernel=one, strides=one, dilations=one, pads_begin=(0,), pads_end=(0,))
    residual = flat[2] if ops.residual else None
    return attrs, _Operands(flat[0], flat[1], ops.bias, residual)


def _flat_spatial(ref: TensorRef) -> TensorRef | None:
    """ref [N, C, S_1..S_d] viewed as [N, C, S_1*...*S_d], or None when the spatial dims are not one
    contiguous run of memory."""
    spatial = list(range(2, len(ref.shape)))
    where = [ref.order.index(d) for d in spatial]
    if ref.halo or where != list(range(where[0], where[0] + len(spatial))):
        return None
    order = [0 if d == 0 else 1 if d == 1 else 2 for d in ref.order if d < 2 or d == 2]
    return TensorRef(ref.buffer, (*ref.shape[:2], math.prod(ref.shape[2:])), tuple(order))


def _packed(weights: np.ndarray, panels: int, block: int) -> np.ndarray:
    """[c_out, c_in, k...] -> [panel][block][k...][input channel][panel channel]."""
    c_out, c_in, *kernel = weights.shape
    rank = len(kernel)
    split = weights.reshape(panels, c_out // panels, c_in // block, block, *kernel)
    return split.transpose(0, 2, *range(4, 4 + rank), 3, 1)


def _stages(
    attrs: ConvAttrs, ops: _Operands, w: TensorRef, panel: Affine, firsts: tuple[Affine, Affine], width: int
) -> tuple[Stmt, ...]:
    """One panel's nests: the first reduction block, the middle ones in a loop, the last. `firsts`:
    the panel's first output channel and first input channel."""
    blocks = w.shape[1]

    def stage(block: Affine, first: bool, last: bool) -> tuple[Stmt, ...]:
        return _pixel_nest(attrs, ops, w, (panel, block), firsts, width, (first, last))

    if blocks == 1:
        return stage(Affine(), True, True)
    out = stage(Affine(), True, False)
    if blocks > 2:
        inner = stage(Affine.of("kb") + 1 if blocks > 3 else Affine.of(1), False, False)
        out += (Loop("kb", blocks - 2, inner),) if blocks > 3 else inner
    return out + stage(Affine.of(blocks - 1), False, True)


def _pixel_nest(
    attrs: ConvAttrs,
    ops: _Operands,
    w: TensorRef,
    panel_block: tuple[Affine, Affine],
    firsts: tuple[Affine, Affine],
    width: int,
    first_last: tuple[bool, bool],
) -> tuple[Stmt, ...]:
    """The output pixels x the panel's channels, over one block of input channels."""
    (panel, block), (first_channel, first_input), (first, last) = panel_block, firsts, first_last
    x, out = ops.x, ops.out
    names = spatial_names(len(attrs.kernel))
    out_loops = [("o" + s, out.shape[2 + i]) for i, s in enumerate(names)]
    ci_block = attrs.ci_block
    planes_outside = attrs.planes_outside_row and ci_block > 1

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        n, co = env["n"], env["co"]
        channel = first_channel + co
        ci = Affine.of("ci") if ci_block > 1 else Affine()

        def tap(positions: list[Affine], k_vars: list[Affine]) -> tuple[Stmt, ...]:
            x_load = Load(x.buffer, x.at([n, first_input + block * ci_block + ci, *positions]))
            product = Binary("*", x_load, Load(w.buffer, w.at([panel, block, *k_vars, ci, co])))
            update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
            return (Loop("ci", ci_block, update),) if ci_block > 1 and not planes_outside else update

        index = [n, channel, *(env["o" + s] for s in names)]
        if not first:
            init: Expr = Load(out.buffer, out.at(index))
        else:
            init = Load(ops.bias.buffer, ops.bias.at([channel])) if ops.bias else Const.splat(0.0)
        value: Expr = LocalRef("acc")
        if last and ops.residual:
            value = Binary("+", value, Load(ops.residual.buffer, ops.residual.at(index)))
        if last:
            value = apply_activation(value, attrs.activation)
        window = window_nest(attrs, env, dict(out_loops), x.spatial_ranges, tap)
        if planes_outside:
            window = around_row_taps(window, len(names), ("ci", ci_block))
        return (Let("acc", init, (*window, Store(out.buffer, out.at(index), value))),)

    return nest([("n", out.shape[0]), *out_loops, ("co", width)], body, parallel=True)
