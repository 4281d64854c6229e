"""Resize lowering (nearest, linear and cubic, antialiased or not; Upsample too) with every source
index fixed at compile time.

Per dim, each output coordinate o reads a few input coordinates ("taps") with weights: one tap for
nearest, two for linear (one at the clamped borders), four for cubic, more for an antialiased
kernel stretched over a shrinking dim; tf_crop_and_resize's positions outside the input read none
and hold the extrapolation value. The map o -> taps is not affine in general
(e.g. floor(o / 2)), but it is periodic: taps(o + P) = taps(o) shifted by Q input positions, over
most of the dim. So a dim is cut into pieces: a loop over blocks of P outputs whose body has one
statement per residue r < P, with source index Q * block + constant (affine), plus single positions
before and after where clamping breaks the period. A dim that is not resized is one piece with
P = Q = 1: a plain loop. Output element = the sum over the cross product of its dims' taps of
weight product * input element.

A ratio such as 60 -> 97 repeats only after the whole dim, which would make one statement per
output position. There the coordinates are made periodic and the weights are not: residue r of
block b reads a window of input positions first[r] + Q * b + k (k < width[r]) with weights from a
constant table (zero where the window is wider than the taps), with P and Q chosen so the windows
stay narrow, usually the two taps themselves. Such a resize runs one dim at a time (intermediate
buffers between), so the code grows with the sum of the dims' pieces, not their product; loops
stay loops and the unroll pass decides about them as everywhere else.

The output keeps the input's layout, so with a channels-last input the channel loop is innermost,
contiguous and vectorised. Coordinates are computed in float32 like onnxruntime, so nearest
rounding ties break the same way."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np

from ..ir.graph import Node, ResizeAttrs
from ..ir.loops import Affine, Binary, Const, Expr, Load, Loop, Stmt, Store
from .context import LoweringContext, TensorRef, dim_vars

Taps = tuple[tuple[int, float], ...]  # (input coordinate, weight) pairs of one output coordinate
EXTRAPOLATED = -1  # the coordinate of tf_crop_and_resize's one tap outside the input; its weight is the value
WEIGHT_TOLERANCE = 1e-6  # weights this close count as equal when looking for a period
DIRECT_STATEMENTS = 64  # statements of one nest over all dims; above, the dims are resized one at a time
MAX_PERIOD = 64  # longest period (statements per block) tried, exact or windowed


@dataclass(frozen=True)
class Piece:
    """Output coordinates start + period * b + r (b < blocks, r < period); residue r reads input
    coordinate c + step * b with weight w for each (c, w) in taps[r]. With a weight `table`, w is
    instead an index into it, advancing by table_step per block."""

    start: int
    blocks: int
    period: int
    step: int
    taps: tuple[tuple, ...]
    table: str | None = None
    table_step: int = 0


def lower_resize(ctx: LoweringContext, node: Node) -> None:
    attrs: ResizeAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    out_shape = ctx.graph.shape(node.outputs[0])
    taps = resize_taps(attrs, x.shape, out_shape)
    exact = [periodic_pieces(t, MAX_PERIOD) for t in taps]
    if math.prod(statements(p) for p in exact) <= DIRECT_STATEMENTS:
        _emit(ctx, node, x, ctx.output(node.outputs[0], x.order), exact)
    else:
        _lower_dim_by_dim(ctx, node, x, taps, exact)


def _lower_dim_by_dim(ctx: LoweringContext, node: Node, x: TensorRef, taps: list, exact: list) -> None:
    """One nest per resized dim, the shrinking ones first so the intermediate tensors stay small."""
    out_shape = ctx.graph.shape(node.outputs[0])
    rank = len(out_shape)
    resized = [d for d in range(rank) if not _is_identity(taps[d], x.shape[d])]
    resized.sort(key=lambda d: out_shape[d] / x.shape[d])
    source = x
    for i, d in enumerate(resized):
        shape = tuple(out_shape[k] if k in resized[: i + 1] else x.shape[k] for k in range(rank))
        if d == resized[-1]:
            target = ctx.output(node.outputs[0], x.order)
        else:
            dtype = ctx.graph.dtype(node.inputs[0])
            target = ctx.add_buffer(f"t_{node.outputs[0]}_{i}", "internal", shape, x.order, dtype=dtype)
        pieces = [_plain(shape[k]) for k in range(rank)]
        pieces[d] = _dim_cover(ctx, node, d, taps[d], exact[d])
        _emit(ctx, node, source, target, pieces)
        source = target


def statements(pieces: list[Piece]) -> int:
    """Statements a dim's pieces put into the nest: one per residue."""
    return sum(p.period for p in pieces)


def cover_cost(pieces: list[Piece]) -> int:
    """Taps computed along one line of the dim plus taps printed: the work and the code of a cover."""
    return sum((p.blocks + 1) * sum(len(r) for r in p.taps) for p in pieces)


def _dim_cover(ctx: LoweringContext, node: Node, d: int, taps: list[Taps], exact: list[Piece]) -> list[Piece]:
    """The exact pieces, or windowed ones with their weight table when those are cheaper."""
    if ctx.graph.dtype(node.inputs[0]).is_integer:
        return exact  # integers are moved, never multiplied by a table's weights
    window = windowed_pieces(taps, ctx.graph.shape(node.inputs[0])[d])
    if window is None or cover_cost(exact) <= cover_cost(window[0]):
        return exact
    pieces, weights = window
    table = ctx.add_constant(f"resize_weights_{node.name}_{d}", weights).buffer
    return [replace(p, table=table) if p.table is not None else p for p in pieces]


def _plain(n: int) -> list[Piece]:
    return periodic_pieces([((o, 1.0),) for o in range(n)])


def _is_identity(taps: list[Taps], n_in: int) -> bool:
    """Output coordinate o reads input o alone, over the input's whole extent (3 -> 1 reading
    pixel 0 is no identity: the dim still shrinks)."""
    return len(taps) == n_in and all(t == ((o, 1.0),) for o, t in enumerate(taps))


def _emit(ctx: LoweringContext, node: Node, x: TensorRef, out: TensorRef, pieces: list[list[Piece]]) -> None:
    builder = _NestBuilder(x, out, pieces, dim_vars(len(x.shape)))
    ctx.emit(node.name, node.op, builder.dims(0, (Affine(),) * len(x.shape), ((),) * len(x.shape)))


# ---------------------------------------------------------------------------- taps per output coordinate


def resize_taps(attrs: ResizeAttrs, in_shape: tuple[int, ...], out_shape: tuple[int, ...]) -> list[list[Taps]]:
    """The taps of every dim. A resize whose output has the input's shape is a copy in onnxruntime,
    whatever its scales (1.013 floors 10 pixels back to 10); otherwise each dim follows its scale."""
    if tuple(in_shape) == tuple(out_shape):
        return [[((o, 1.0),) for o in range(n)] for n in in_shape]
    return [dim_taps(attrs, d, n_in, n_out) for d, (n_in, n_out) in enumerate(zip(in_shape, out_shape))]


def dim_taps(attrs: ResizeAttrs, d: int, n_in: int, n_out: int) -> list[Taps]:
    scale = np.float32(attrs.scales[d])
    roi = attrs.roi[d] if attrs.roi else None
    if scale == 1:
        # onnxruntime maps a dim of scale 1 onto itself, whatever the coordinate mode: only
        # tf_half_pixel_for_nn would move it ((o + 0.5) / 1 rounds up to o + 1) and only
        # tf_crop_and_resize's roi would crop it (onnx's reference does both).
        return [((o, 1.0),) for o in range(n_out)]
    taps = []
    for o in range(n_out):
        x = source_coordinate(attrs.coordinate_transformation_mode, np.float32(o), scale, n_in, n_out, roi)
        if roi is not None and not 0 <= x <= n_in - 1:
            taps.append(((EXTRAPOLATED, attrs.extrapolation_value),))
        elif attrs.mode == "nearest":
            taps.append(((_nearest(x, attrs.nearest_mode, scale, n_in), 1.0),))
        elif attrs.mode == "linear" and not attrs.antialias and not attrs.exclude_outside:
            taps.append(_linear(x, n_in))
        else:
            taps.append(_kernel_taps(attrs, x, float(scale), n_in))
    return taps


def source_coordinate(
    mode: str, o: np.float32, scale: np.float32, n_in: int, n_out: int, roi: tuple[float, float] | None = None
) -> np.float32:
    """The input coordinate of output coordinate o (ONNX Resize coordinate_transformation_mode)."""
    half = np.float32(0.5)
    if mode == "asymmetric":
        return o / scale
    if mode == "tf_half_pixel_for_nn":
        return (o + half) / scale
    if mode == "align_corners":
        return np.float32(0) if n_out == 1 else o * np.float32(n_in - 1) / np.float32(n_out - 1)
    if mode == "tf_crop_and_resize":
        start, end = np.float32(roi[0]), np.float32(roi[1])
        if n_out == 1:
            return half * (start + end) * np.float32(n_in - 1)
        return start * np.float32(n_in - 1) + o * (end - start) * np.float32(n_in - 1) / np.float32(n_out - 1)
    if mode == "pytorch_half_pixel":
        return (o + half) / scale - half if n_out > 1 else np.float32(0)
    if mode == "half_pixel_symmetric":  # the offset in float32, the rest in double, as onnxruntime has it
        adjustment = np.float32(n_out) / (scale * np.float32(n_in))
        offset = np.float32(n_in) / np.float32(2) * (np.float32(1) - adjustment)
        return np.float32(float(offset) + (float(o) + 0.5) / float(scale) - 0.5)
    return (o + half) / scale - half  # half_pixel


def _nearest(x: np.float32, mode: str, scale: np.float32, n_in: int) -> int:
    """The rounded coordinate, clamped into the input. A coordinate within one float32 ulp of a
    half-way point is a tie: the exact coordinate is a tie there (7 -> 4 asymmetric: 2 * 7/4 = 3.5)
    and float32 lands on either side of it (3.4999998); onnxruntime breaks such ties by the mode."""
    if mode == "simple":  # Resize-10 and Upsample (x >= 0 there): floor when enlarging, ceil when shrinking
        mode = "ceil" if scale < 1 else "floor"
    value = float(x)  # exact: float64 holds every float32
    if mode in ("floor", "ceil"):
        index = math.floor(value) if mode == "floor" else math.ceil(value)
    else:
        half = math.floor(value) + 0.5  # the half-way point nearest to value
        if abs(value - half) <= float(np.spacing(np.float32(abs(half)))):
            index = math.floor(half) if mode == "round_prefer_floor" else math.ceil(half)
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


def _kernel_taps(attrs: ResizeAttrs, x: np.float32, scale: float, n_in: int) -> Taps:
    """Linear (triangle) or cubic kernel taps around x, as ONNX's reference places them: the kernel
    is stretched by 1/scale when shrinking with antialias, taps past the borders read the border
    pixel (or are dropped with exclude_outside), and the weights are normalised to sum to 1."""
    x = float(x)
    ratio = x - math.floor(x) if x != math.floor(x) else 1.0  # in (0, 1]: x = base + ratio
    base = round(x - ratio)
    stretch = min(scale, 1.0) if attrs.antialias else 1.0
    radius = 2 if attrs.mode == "cubic" else 1
    first = math.floor(-radius / stretch) + 1
    weights: dict[int, float] = {}
    for i in range(first, 2 - first):
        pixel = base + i
        if attrs.exclude_outside and not 0 <= pixel < n_in:
            continue
        pixel = min(max(pixel, 0), n_in - 1)
        weights[pixel] = weights.get(pixel, 0.0) + _kernel(attrs, (i - ratio) * stretch)
    total = sum(weights.values())
    return tuple((c, float(np.float32(w / total))) for c, w in weights.items() if w != 0.0)


def _kernel(attrs: ResizeAttrs, t: float) -> float:
    """The interpolation kernel at distance t: the triangle 1 - |t|, or Keys' cubic with a = cubic_coeff_a."""
    t = abs(t)
    if attrs.mode != "cubic":
        return max(0.0, 1.0 - t)
    a = attrs.cubic_coeff_a
    if t <= 1:
        return ((a + 2) * t - (a + 3)) * t * t + 1
    if t < 2:
        return ((a * t - 5 * a) * t + 8 * a) * t - 4 * a
    return 0.0


# ---------------------------------------------------------------------------- periodic pieces


def periodic_pieces(taps: list[Taps], max_period: int | None = None) -> list[Piece]:
    """The cheapest cover of the dim (fewest statements: one per residue plus one per single
    position) by single positions and at most one periodic piece of at most `max_period` residues."""
    n = len(taps)
    best_cost, best = n, None
    for period in range(1, n if max_period is None else min(n, max_period + 1)):
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
    if any(c == EXTRAPOLATED for c, _ in (*a, *b)):
        return 0 if a == b else None
    step = b[0][0] - a[0][0]
    same = all(cb - ca == step and abs(wb - wa) <= WEIGHT_TOLERANCE for (ca, wa), (cb, wb) in zip(a, b))
    return step if same else None


def _single(taps: list[Taps], o: int) -> Piece:
    return Piece(o, 1, 1, 0, (taps[o],))


# ---------------------------------------------------------------------------- windowed pieces


def windowed_pieces(taps: list[Taps], n_in: int) -> tuple[list[Piece], np.ndarray] | None:
    """The cheapest cover (cover_cost) by single positions around one periodic piece whose residues
    read windows at periodic coordinates with weights from a table, and that table [blocks, row]:
    its piece's taps are (coordinate, table column) pairs. None when no period fits twice."""
    n = len(taps)
    lead = _clamped_run(taps, range(n), 0)
    interior = n - lead - _clamped_run(taps, range(n - 1, lead - 1, -1), n_in - 1)
    best = None
    for period in range(1, MAX_PERIOD + 1):
        blocks = interior // period
        if blocks < 2:
            break
        for step in _steps(taps, lead, blocks, period):
            window = _window(taps, lead, blocks, period, step, n_in)
            if window is None:
                continue
            end = lead + blocks * period
            pieces = [*(_single(taps, o) for o in range(lead)), window[0], *(_single(taps, o) for o in range(end, n))]
            if best is None or cover_cost(pieces) < cover_cost(best[0]):
                best = (pieces, window[1])
    return best


def _clamped_run(taps: list[Taps], positions: range, coordinate: int) -> int:
    """How many of `positions`, from the first, only read `coordinate` (clamped to the border)."""
    count = 0
    for o in positions:
        if taps[o] != ((coordinate, 1.0),):
            break
        count += 1
    return count


def _steps(taps: list[Taps], lead: int, blocks: int, period: int) -> set[int]:
    """The input steps per block worth trying: the average advance of `period` outputs, rounded."""
    first, last = taps[lead][0][0], taps[lead + (blocks - 1) * period][0][0]
    slope = (last - first) / (blocks - 1)
    return {max(0, math.floor(slope)), max(0, math.ceil(slope))}


def _window(taps: list[Taps], lead: int, blocks: int, period: int, step: int, n_in: int):
    """The windowed piece over outputs [lead, lead + blocks * period) with this step and its weight
    table, or None when a window would reach outside the input."""
    firsts, widths = [], []
    for r in range(period):
        rows = [taps[lead + b * period + r] for b in range(blocks)]
        firsts.append(min(c - b * step for b, row in enumerate(rows) for c, _ in row))
        last = max(c - b * step for b, row in enumerate(rows) for c, _ in row)
        widths.append(last - firsts[-1] + 1)
        if firsts[-1] < 0 or last + (blocks - 1) * step >= n_in:
            return None
    columns = list(itertools.accumulate([0, *widths[:-1]]))
    weights = np.zeros((blocks, sum(widths)), np.float32)
    for b, r in itertools.product(range(blocks), range(period)):
        for c, w in taps[lead + b * period + r]:
            weights[b, columns[r] + c - b * step - firsts[r]] += np.float32(w)
    residues = tuple(
        tuple((first + k, column + k) for k in range(width)) for first, width, column in zip(firsts, widths, columns)
    )
    return Piece(lead, blocks, period, step, residues, table="", table_step=sum(widths)), weights.reshape(-1)


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
                reads = tuple(
                    (None, w) if c == EXTRAPOLATED else (block * piece.step + c, self._weight(piece, block, w))
                    for c, w in residue
                )
                inner += self.dims(level + 1, _put(at, d, here), _put(taps, d, reads))
            body += [Loop(self.names[d], piece.blocks, tuple(inner), parallel=True)] if piece.blocks > 1 else inner
        return tuple(body)

    @staticmethod
    def _weight(piece: Piece, block: Affine, w) -> float | Load:
        """A tap's weight: a constant, or the load of its column in this block's row of the table."""
        return w if piece.table is None else Load(piece.table, block * piece.table_step + w)

    def _blend(self, taps: tuple[tuple, ...]) -> Expr:
        """Sum over the cross product of the dims' taps of weight product * input element; the
        extrapolation value where a dim reads outside the input (its one tap has no coordinate)."""
        for (coordinate, value), *others in taps:
            if coordinate is None and not others:
                return Const.splat(float(value))
        total: Expr | None = None
        for combo in itertools.product(*taps):
            constant = [np.float32(w) for _, w in combo if not isinstance(w, Load)]
            weight = float(np.prod(constant, dtype=np.float32))
            term: Expr = Load(self.x.buffer, self.x.at([c for c, _ in combo]))
            if weight != 1.0:
                term = Binary("*", Const.splat(weight), term)
            for table_weight in (w for _, w in combo if isinstance(w, Load)):
                term = Binary("*", table_weight, term)
            total = term if total is None else Binary("+", total, term)
        return total


def _put(values: tuple, d: int, value) -> tuple:
    return tuple(value if i == d else v for i, v in enumerate(values))
