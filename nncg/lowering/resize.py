"""Resize lowering (nearest and linear; Upsample too) with every source index and weight fixed at
compile time.

Per dim, each output coordinate o reads a few input coordinates ("taps") with constant weights:
one tap for nearest, two for linear (one at the clamped borders). The map o -> taps is not affine
in general (e.g. floor(o / 2)), but it is periodic: taps(o + P) = taps(o) shifted by Q input
positions, over most of the dim. So a dim is cut into pieces: a loop over blocks of P outputs whose
body has one statement per residue r < P, with source index Q * block + constant — affine — plus
single positions before and after where clamping breaks the period. A dim that is not resized is
one piece with P = Q = 1: a plain loop. Output element = the sum over the cross product of its
dims' taps of weight product * input element.

The output keeps the input's layout, so with a channels-last input the channel loop is innermost,
contiguous and vectorised. Coordinates are computed in float32 like onnxruntime, so nearest
rounding ties break the same way."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..ir.graph import Node, ResizeAttrs
from ..ir.loops import Affine, Binary, Const, Expr, Load, Loop, Stmt, Store
from .context import LoweringContext, TensorRef, dim_vars

Taps = tuple[tuple[int, float], ...]  # (input coordinate, weight) pairs of one output coordinate
WEIGHT_TOLERANCE = 1e-6  # weights this close count as equal when looking for a period


@dataclass(frozen=True)
class Piece:
    """Output coordinates start + period * b + r (b < blocks, r < period); residue r reads input
    coordinate c + step * b with weight w for each (c, w) in taps[r]."""

    start: int
    blocks: int
    period: int
    step: int
    taps: tuple[Taps, ...]


def lower_resize(ctx: LoweringContext, node: Node) -> None:
    attrs: ResizeAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out = ctx.output(node.outputs[0], x.order)
    pieces = [periodic_pieces(dim_taps(attrs, d, x.shape[d], out.shape[d])) for d in range(len(x.shape))]
    builder = _NestBuilder(x, out, pieces, dim_vars(len(x.shape)))
    ctx.emit(node.name, node.op, builder.dims(0, (Affine(),) * len(x.shape), ((),) * len(x.shape)))


# ---------------------------------------------------------------------------- taps per output coordinate


def dim_taps(attrs: ResizeAttrs, d: int, n_in: int, n_out: int) -> list[Taps]:
    scale = np.float32(attrs.scales[d])
    if scale == 1:
        # onnxruntime maps a dim of scale 1 onto itself, whatever the coordinate mode: only
        # tf_half_pixel_for_nn would move it ((o + 0.5) / 1 rounds up to o + 1).
        return [((o, 1.0),) for o in range(n_out)]
    taps = []
    for o in range(n_out):
        x = source_coordinate(attrs.coordinate_transformation_mode, np.float32(o), scale, n_in, n_out)
        if attrs.mode == "nearest":
            taps.append(((_nearest(x, attrs.nearest_mode, scale, n_in), 1.0),))
        else:
            taps.append(_linear(x, n_in))
    return taps


def source_coordinate(mode: str, o: np.float32, scale: np.float32, n_in: int, n_out: int) -> np.float32:
    """The input coordinate of output coordinate o (ONNX Resize coordinate_transformation_mode)."""
    half = np.float32(0.5)
    if mode == "asymmetric":
        return o / scale
    if mode == "tf_half_pixel_for_nn":
        return (o + half) / scale
    if mode == "align_corners":
        return np.float32(0) if n_out == 1 else o * np.float32(n_in - 1) / np.float32(n_out - 1)
    if mode == "pytorch_half_pixel":
        return (o + half) / scale - half if n_out > 1 else np.float32(0)
    if mode == "half_pixel_symmetric":
        adjustment = np.float32(n_out) / (scale * np.float32(n_in))
        offset = np.float32(n_in) / np.float32(2) * (np.float32(1) - adjustment)
        return offset + (o + half) / scale - half
    return (o + half) / scale - half  # half_pixel


def _nearest(x: np.float32, mode: str, scale: np.float32, n_in: int) -> int:
    """The rounded coordinate, clamped into the input."""
    if mode == "simple":  # Resize-10 and Upsample (x >= 0 there): floor when enlarging, ceil when shrinking
        mode = "ceil" if scale < 1 else "floor"
    value = float(x)  # exact: float64 holds every float32
    floor = math.floor(value)
    if mode in ("floor", "ceil"):
        index = floor if mode == "floor" else math.ceil(value)
    elif value - floor == 0.5:
        index = floor if mode == "round_prefer_floor" else floor + 1
    else:
        index = round(value)  # not a tie, so round()'s tie rule does not matter
    return min(max(index, 0), n_in - 1)


def _linear(x: np.float32, n_in: int) -> Taps:
    """The two neighbours of x (clamped into the input) weighted by distance; zero weights dropped."""
    x = min(max(x, np.float32(0)), np.float32(n_in - 1))
    lo = int(x)
    hi = min(lo + 1, n_in - 1)
    frac = float(x - np.float32(lo))
    if hi == lo or frac == 0.0:
        return ((lo, 1.0),)
    return ((lo, float(np.float32(1) - np.float32(frac))), (hi, frac))


# ---------------------------------------------------------------------------- periodic pieces


def periodic_pieces(taps: list[Taps]) -> list[Piece]:
    """The cheapest cover of the dim (fewest statements: one per residue plus one per single
    position) by single positions and at most one periodic piece."""
    n = len(taps)
    best_cost, best = n, None
    for period in range(1, n):
        if period >= best_cost:  # the period alone costs as much as the best cover so far
            break
        run = _longest_shift_run(taps, period)
        if run is None:
            continue
        first, stop, step = run
        blocks = (stop - first + period) // period
        cost = period + n - blocks * period
        if blocks >= 2 and cost < best_cost:
            best_cost, best = cost, Piece(first, blocks, period, step, tuple(taps[first : first + period]))
    if best is None:
        return [_single(taps, o) for o in range(n)]
    end = best.start + best.blocks * best.period
    return [*(_single(taps, o) for o in range(best.start)), best, *(_single(taps, o) for o in range(end, n))]


def _longest_shift_run(taps: list[Taps], period: int) -> tuple[int, int, int] | None:
    """(first, stop, step): taps[o + period] is taps[o] shifted by `step` for every o in
    [first, stop), the longest such run; None when there is none."""
    shifts = [_shift(taps[o], taps[o + period]) for o in range(len(taps) - period)]
    best, first = None, 0
    for step, group in itertools.groupby(shifts):
        stop = first + len(list(group))
        if step is not None and (best is None or stop - first > best[1] - best[0]):
            best = (first, stop, step)
        first = stop
    return best


def _shift(a: Taps, b: Taps) -> int | None:
    """Q when b is a with every input coordinate moved by Q and the same weights, else None."""
    if len(a) != len(b):
        return None
    step = b[0][0] - a[0][0]
    same = all(cb - ca == step and abs(wb - wa) <= WEIGHT_TOLERANCE for (ca, wa), (cb, wb) in zip(a, b))
    return step if same else None


def _single(taps: list[Taps], o: int) -> Piece:
    return Piece(o, 1, 1, 0, (taps[o],))


# ---------------------------------------------------------------------------- loop nest


@dataclass(frozen=True)
class _NestBuilder:
    """Builds the nest dim by dim in the output's memory order, outermost first."""

    x: TensorRef
    out: TensorRef
    pieces: list[list[Piece]]
    names: tuple[str, ...]

    def dims(self, level: int, at: tuple[Affine, ...], taps: tuple[tuple, ...]) -> tuple[Stmt, ...]:
        """Statements for the dims from `level` on; `at` and `taps` fix the outer dims' output
        coordinate and input taps (affine in the enclosing block loops)."""
        if level == len(self.out.order):
            return (Store(self.out.buffer, self.out.at(at), self._blend(taps)),)
        d = self.out.order[level]
        body: list[Stmt] = []
        for piece in self.pieces[d]:
            block = Affine.of(self.names[d]) if piece.blocks > 1 else Affine()
            inner: list[Stmt] = []
            for r, residue in enumerate(piece.taps):
                here = block * piece.period + (piece.start + r)
                reads = tuple((block * piece.step + c, w) for c, w in residue)
                inner += self.dims(level + 1, _put(at, d, here), _put(taps, d, reads))
            body += [Loop(self.names[d], piece.blocks, tuple(inner), parallel=True)] if piece.blocks > 1 else inner
        return tuple(body)

    def _blend(self, taps: tuple[tuple, ...]) -> Expr:
        """Sum over the cross product of the dims' taps of weight product * input element."""
        total: Expr | None = None
        for combo in itertools.product(*taps):
            weight = float(np.prod([np.float32(w) for _, w in combo], dtype=np.float32))
            term: Expr = Load(self.x.buffer, self.x.at([c for c, _ in combo]))
            if weight != 1.0:
                term = Binary("*", Const.splat(weight), term)
            total = term if total is None else Binary("+", total, term)
        return total


def _put(values: tuple, d: int, value) -> tuple:
    return tuple(value if i == d else v for i, v in enumerate(values))
