"""Passes over the graph IR and the loop-nest IR, registered by name for pipelines.

The default pipeline for a target is `default_pipeline(target, unroll)`; researchers compose their
own from the same names (`nncg-onnx --list-passes`)."""

from __future__ import annotations

from ..errors import NncgError
from ..lowering import lower
from .drop_identity import drop_identity
from .fold_batchnorm import fold_batchnorm
from .fuse_activation import fuse_activation
from .fuse_bias import fuse_bias
from .fuse_residual import fuse_residual
from .inline_constants import inline_constants
from .manager import REGISTRY, PassManager, PassSpec, format_pipeline, parse_pipeline, register
from .plan_memory import parse_align, parse_bool, parse_weights, plan_memory
from .register_block import parse_layers, register_block
from .unroll import AUTO_BUDGET, NEST_BUDGET, parse_layer_budgets, unroll
from .vectorize import vectorize
from .vectorize_pixels import parse_layers as parse_pixel_layers
from .vectorize_pixels import vectorize_pixels
from .winograd import parse_layers as parse_winograd_layers
from .winograd import winograd


def parse_unroll_level(text: str) -> int | None:
    """An unroll level: a loop depth >= 0, `none`, or `auto` (every loop that unrolls to at most the
    unroll pass's `budget` statements)."""
    if text == "none":
        return None
    if text == "auto":
        return text
    level = int(text)
    if level < 0:
        raise ValueError("the unroll level is a depth >= 0, or none")
    return level


def parse_lanes(text: str) -> tuple[int, ...]:
    """Vector widths, widest first: `4`, or `16/8/4` (a loop is split into blocks of the widest that
    fits, the rest into the next narrower, ...). `1`: no vectors."""
    widths = tuple(int(part) for part in text.split("/"))
    if widths == (1,):
        return widths
    if not all(w in (2, 4, 8, 16) for w in widths) or list(widths) != sorted(set(widths), reverse=True):
        raise ValueError("lanes is 1, 2, 4, 8 or 16, or widths from 2, 4, 8, 16 widest first: 16/8/4")
    return widths


register("drop-identity", "graph", drop_identity)
register("fold-batchnorm", "graph", fold_batchnorm)
register("fuse-bias", "graph", fuse_bias)
register("fuse-residual", "graph", fuse_residual)
register("fuse-activation", "graph", fuse_activation)
register("winograd", "graph", winograd, lanes=parse_lanes, layers=parse_winograd_layers)
register("vectorize-pixels", "graph", vectorize_pixels, lanes=parse_lanes, layers=parse_pixel_layers)
register("lower", "lower", lower, halos=parse_bool)
register("vectorize", "loop", vectorize, lanes=parse_lanes)
register("register-block", "loop", register_block, registers=int, layers=parse_layers)
register("unroll", "loop", unroll, level=parse_unroll_level, budget=int, total=int, layers=parse_layer_budgets)
register("inline-constants", "loop", inline_constants)
register("plan-memory", "loop", plan_memory, align=parse_align, reuse=parse_bool, weights=parse_weights)

GRAPH_PIPELINE = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation"


def default_pipeline(
    widths: tuple[int, ...] | int,
    unroll_level: str = "auto",
    weights: str = "auto",
    budget: int | None = None,
    registers: int = 16,
) -> str:
    """The pipeline `nncg-onnx` runs for a target with these SIMD widths (widest first; one int: one
    width) and `registers` vector registers, at an unroll level; `weights` (auto, embed, bin) says
    where plan-memory puts the weights; `budget` caps the statements of the unrolled program (None: no cap)."""
    widths = tuple(w for w in ((widths,) if isinstance(widths, int) else widths) if w > 1)
    lanes = f"{{lanes={'/'.join(map(str, widths))}}}" if widths else ""
    vector = f",vectorize{lanes}" if widths else ""
    try:
        parse_unroll_level(unroll_level)
    except ValueError:
        raise NncgError(f"unroll level '{unroll_level}' is not auto, a depth >= 0 or none") from None
    plan = "plan-memory" if weights == "auto" else f"plan-memory{{weights={weights}}}"
    nest = AUTO_BUDGET if unroll_level == "auto" else NEST_BUDGET
    cap = f",budget={min(nest, budget)},total={budget}" if budget and unroll_level != "none" else ""
    if unroll_level == "auto" and not budget:
        cap = f",budget={nest}"
    block = f",register-block{{registers={registers}}}"
    loops = f"{vector}{block},unroll{{level={unroll_level}{cap}}},inline-constants,{plan}"
    pixels = f",vectorize-pixels{lanes}" if widths else ""
    return f"{GRAPH_PIPELINE},winograd{lanes}{pixels},lower{loops}"


__all__ = [
    "REGISTRY",
    "PassManager",
    "PassSpec",
    "default_pipeline",
    "format_pipeline",
    "parse_pipeline",
    "register",
]
