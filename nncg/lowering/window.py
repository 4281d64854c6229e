"""The spatial-window skeleton shared by Conv, MaxPool and ConvTranspose: loops over kernel taps,
the input position each tap reads, and the border checks that padding needs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from ..ir.loops import Affine, Bound, If, Loop, Stmt

SPATIAL_NAMES = {1: ("w",), 2: ("h", "w"), 3: ("d", "h", "w")}

Tap = Callable[[list[Affine], list[Affine]], tuple[Stmt, ...]]


def spatial_names(rank: int) -> tuple[str, ...]:
    return SPATIAL_NAMES.get(rank, tuple(f"s{i}" for i in range(rank)))


def window_nest(
    attrs,
    out_env: dict[str, Affine],
    out_extents: dict[str, int],
    in_ranges: list[tuple[int, int]],
    tap: Tap,
) -> tuple[Stmt, ...]:
    """for k_1 { if border_1 { for k_2 { ... tap(positions, k) } } }.

    `attrs` has kernel, strides, dilations and pads_begin: output o reads input o*stride +
    k*dilation - pad_begin. in_ranges[i] = [lo, hi) are the positions along dim i that may be read
    (TensorRef.spatial_ranges: the input, and the zero halo around it if it has one)."""
    loops, k_vars, positions = _taps(attrs, out_env)
    return guarded_taps(loops, positions, in_ranges, out_extents, lambda: tap(positions, k_vars))


def outside_window_nest(
    attrs,
    out_env: dict[str, Affine],
    out_extents: dict[str, int],
    in_ranges: list[tuple[int, int]],
    tap: Tap,
) -> tuple[Stmt, ...]:
    """The taps window_nest skips, each once: for each dim i, the taps inside the input along the
    dims before i, outside it along dim i (below, then above), anywhere along the dims after i.
    Empty where no tap can leave the input."""
    loops, k_vars, positions = _taps(attrs, out_env)
    extents = out_extents | dict(loops)
    ranges = [positions[i].bounds(extents) for i in range(len(loops))]
    stmts: list[Stmt] = []
    for i, ((lo, hi), (first, stop)) in enumerate(zip(ranges, in_ranges)):
        sides = ([Bound(positions[i], None, first)] if lo < first else []) + (
            [Bound(positions[i], stop, None)] if hi >= stop else []
        )
        for side in sides:
            body = tap(positions, k_vars)
            for j in reversed(range(len(loops))):
                if j == i:
                    body = (If((side,), body),)
                elif j < i:
                    body = guarded_taps([loops[j]], [positions[j]], [in_ranges[j]], extents, lambda b=body: b)
                    continue
                var, extent = loops[j]
                body = (Loop(var, extent, body),) if extent > 1 else body
            stmts += body
    return tuple(stmts)


def _taps(attrs, out_env: dict[str, Affine]) -> tuple[list[tuple[str, int]], list[Affine], list[Affine]]:
    """The tap loops, their variables and the input position each tap reads, per spatial dim."""
    names = spatial_names(len(attrs.kernel))
    loops = [("k" + s, attrs.kernel[i]) for i, s in enumerate(names)]
    k_vars = [Affine.of(var) if extent > 1 else Affine() for var, extent in loops]
    positions = [
        out_env["o" + s] * attrs.strides[i] + k_vars[i] * attrs.dilations[i] - attrs.pads_begin[i]
        for i, s in enumerate(names)
    ]
    return loops, k_vars, positions


def guarded_taps(
    loops: list[tuple[str, int]],
    positions: list[Affine],
    in_ranges: list[tuple[int, int]],
    out_extents: dict[str, int],
    body: Callable[[], tuple[Stmt, ...]],
) -> tuple[Stmt, ...]:
    """One tap loop per spatial dim around body(); positions[i] is the input position along dim
    i, affine in the output variables and tap variable i. Each border check sits right inside the
    tap loop it depends on, so it is evaluated as rarely as possible, and is left out where the
    position can never leave the input. Tap loops of extent 1 are not emitted."""
    extents = out_extents | dict(loops)
    stmts = body()
    for i in reversed(range(len(loops))):
        lo, hi = positions[i].bounds(extents)
        first, stop = in_ranges[i]
        if lo < first or hi >= stop:
            bound = Bound(positions[i], first if lo < first else None, stop if hi >= stop else None)
            stmts = (If((bound,), stmts),)
        var, extent = loops[i]
        if extent > 1:
            stmts = (Loop(var, extent, stmts),)
    return stmts


def around_row_taps(stmts: tuple[Stmt, ...], rank: int, loop: tuple[str, int]) -> tuple[Stmt, ...]:
    """stmts with `loop` (var, extent) wrapped around the taps along a row (the last spatial dim's
    tap loop of a window_nest)."""
    row_taps = "k" + spatial_names(rank)[-1]
    out: list[Stmt] = []
    for stmt in stmts:
        if isinstance(stmt, Loop) and stmt.var == row_taps:
            stmt = Loop(*loop, (stmt,))
        elif isinstance(stmt, Loop | If):
            stmt = replace(stmt, body=around_row_taps(stmt.body, rank, loop))
        out.append(stmt)
    return tuple(out)
