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
from .plan_memory import parse_align, parse_reuse, parse_weights, plan_memory
from .unroll import NEST_BUDGET, unroll
from .vectorize import vectorize


def parse_unroll_level(text: str) -> int | None:
    """An unroll level: a loop depth >= 0, or `none`."""
    if text == "none":
        return None
    level = int(text)
    if level < 0:
        raise ValueError("the unroll level is a depth >= 0, or none")
    return level


def parse_lanes(text: str) -> int:
    lanes = int(text)
    if lanes not in (1, 2, 4, 8, 16):
        raise ValueError("lanes is 1, 2, 4, 8 or 16")
    return lanes


register("drop-identity", "graph", drop_identity)
register("fold-batchnorm", "graph", fold_batchnorm)
register("fuse-bias", "graph", fuse_bias)
register("fuse-residual", "graph", fuse_residual)
register("fuse-activation", "graph", fuse_activation)
register("lower", "lower", lower)
register("vectorize", "loop", vectorize, lanes=parse_lanes)
register("unroll", "loop", unroll, level=parse_unroll_level, budget=int, total=int)
register("inline-constants", "loop", inline_constants)
register("plan-memory", "loop", plan_memory, align=parse_align, reuse=parse_reuse, weights=parse_weights)

GRAPH_PIPELINE = "drop-identity,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation,lower"


def default_pipeline(lanes: int, unroll_level: str = "2", weights: str = "auto", budget: int | None = None) -> str:
    """The pipeline `nncg-onnx` runs for a target with `lanes` SIMD lanes at an unroll level;
    `weights` (auto, embed, bin) says where plan-memory puts the weights; `budget` caps the
    statements of the unrolled program (None: no cap)."""
    vector = f",vectorize{{lanes={lanes}}}" if lanes > 1 else ""
    try:
        parse_unroll_level(unroll_level)
    except ValueError:
        raise NncgError(f"unroll level '{unroll_level}' is not a depth >= 0 or none") from None
    plan = "plan-memory" if weights == "auto" else f"plan-memory{{weights={weights}}}"
    cap = f",budget={min(NEST_BUDGET, budget)},total={budget}" if budget and unroll_level != "none" else ""
    return f"{GRAPH_PIPELINE}{vector},unroll{{level={unroll_level}{cap}}},inline-constants,{plan}"


__all__ = [
    "REGISTRY",
    "PassManager",
    "PassSpec",
    "default_pipeline",
    "format_pipeline",
    "parse_pipeline",
    "register",
]
