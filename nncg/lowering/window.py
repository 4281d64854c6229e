"""The spatial-window skeleton shared by Conv and MaxPool: window loops over the kernel, the input
position each tap reads, and the border checks that padding needs."""

from __future__ import annotations

from collections.abc import Callable

from ..ir.loops import Affine, Bound, If, Loop, Stmt

SPATIAL_NAMES = {1: ("w",), 2: ("h", "w"), 3: ("d", "h", "w")}


def spatial_names(rank: int) -> tuple[str, ...]:
    return SPATIAL_NAMES.get(rank, tuple(f"s{i}" for i in range(rank)))


def window_nest(
    attrs,
    out_env: dict[str, Affine],
    out_extents: dict[str, int],
    in_spatial: tuple[int, ...],
    tap: Callable[[list[Affine], list[Affine]], tuple[Stmt, ...]],
) -> tuple[Stmt, ...]:
    """for k_1 { if border_1 { for k_2 { ... tap(positions, k) } } }.

    `attrs` has kernel, strides, dilations and pads_begin. Each border check sits right inside the
    kernel loop it depends on, so it is evaluated as rarely as possible, and is left out where the
    position can never leave the input."""
    names = spatial_names(len(attrs.kernel))
    k_vars = [Affine.of("k" + s) if attrs.kernel[i] > 1 else Affine() for i, s in enumerate(names)]
    positions = [
        out_env["o" + s] * attrs.strides[i] + k_vars[i] * attrs.dilations[i] - attrs.pads_begin[i]
        for i, s in enumerate(names)
    ]
    extents = out_extents | {"k" + s: attrs.kernel[i] for i, s in enumerate(names)}
    body = tap(positions, k_vars)
    for i in reversed(range(len(names))):
        lo, hi = positions[i].bounds(extents)
        if lo < 0 or hi >= in_spatial[i]:
            bound = Bound(positions[i], 0 if lo < 0 else None, in_spatial[i] if hi >= in_spatial[i] else None)
            body = (If((bound,), body),)
        if attrs.kernel[i] > 1:
            body = (Loop("k" + names[i], attrs.kernel[i], body),)
    return body
