"""Passes over the graph IR and the loop-nest IR, registered by name for pipelines.

The default pipeline for a target is `default_pipeline(target, unroll)`; researchers compose their
own from the same names (`nncg-onnx --list-passes`) and run them with the target's facts:
`PassManager(pipeline, target=nncg.get_target("ssse3"))`."""

from __future__ import annotations

from ..errors import NncgError
from ..ir.target import Target
from ..lowering import lower
from ..lowering.band_plan import parse_memory
from ..lowering.requantize import parse_requantize
from .cache_block import cache_block
from .cache_block import format_choice as format_cache_block
from .cache_block import parse_layers as parse_cache_block_layers
from .cache_block import tuning_candidates as cache_block_choices
from .cancel_transposes import cancel_transposes
from .drop_identity import drop_identity
from .fold_batchnorm import fold_batchnorm
from .fuse_activation import fuse_activation
from .fuse_bias import fuse_bias
from .fuse_residual import fuse_residual
from .inline_constants import inline_constants
from .manager import REGISTRY, PassManager, PassSpec, Tunable, format_pipeline, parse_pipeline, register
from .plan_memory import format_bool, parse_align, parse_bool, parse_weights, plan_memory
from .register_block import format_block, parse_layers, register_block
from .register_block import tuning_candidates as block_choices
from .unroll import AUTO_BUDGET, NEST_BUDGET, parse_layer_budgets, unroll
from .unroll import tuning_candidates as unroll_choices
from .vectorize import vectorize
from .vectorize_pixels import parse_layers as parse_pixel_layers
from .vectorize_pixels import tuning_candidates as pixel_choices
from .vectorize_pixels import vectorize_pixels
from .winograd import parse_layers as parse_winograd_layers
from .winograd import tuning_candidates as winograd_choices
from .winograd import winograd


def parse_halos(text: str) -> bool | str:
    """lower's halos: auto (for cache-blocked Convs' inputs), true or false."""
    return "auto" if text == "auto" else parse_bool(text)


def parse_budget(text: str) -> int:
    """lower's RAM budget in bytes: an integer >= 1 (0: none)."""
    budget = int(text)
    if budget < 0:
        raise ValueError("the budget is a number of bytes >= 0")
    return budget


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


register("drop-identity", "graph", drop_identity)
register("cancel-transposes", "graph", cancel_transposes)
register("fold-batchnorm", "graph", fold_batchnorm)
register("fuse-bias", "graph", fuse_bias)
register("fuse-residual", "graph", fuse_residual)
register("fuse-activation", "graph", fuse_activation)
register(
    "winograd",
    "graph",
    winograd,
    target=True,
    tunable=Tunable(winograd_choices, format_bool),
    layers=parse_winograd_layers,
)
register(
    "vectorize-pixels", "graph", vectorize_pixels, target=True,
    tunable=Tunable(pixel_choices, format_bool, whole_model=True), layers=parse_pixel_layers,
)  # fmt: skip
register(
    "cache-block", "graph", cache_block, target=True,
    tunable=Tunable(cache_block_choices, format_cache_block), layers=parse_cache_block_layers,
)  # fmt: skip
register(
    "lower", "lower", lower, priced=True,
    halos=parse_halos, memory=parse_memory, budget=parse_budget, requantize=parse_requantize,
)  # fmt: skip
register("vectorize", "loop", vectorize, target=True)
register(
    "register-block",
    "loop",
    register_block,
    target=True,
    tunable=Tunable(block_choices, format_block),
    layers=parse_layers,
)
register(
    "unroll", "loop", unroll, tunable=Tunable(unroll_choices),
    level=parse_unroll_level, budget=int, total=int, layers=parse_layer_budgets,
)  # fmt: skip
register("inline-constants", "loop", inline_constants)
register("plan-memory", "loop", plan_memory, finishing=True, align=parse_align, reuse=parse_bool, weights=parse_weights)

GRAPH_PIPELINE = "drop-identity,cancel-transposes,fold-batchnorm,fuse-bias,fuse-residual,fuse-activation"


def default_pipeline(
    target: Target,
    unroll_level: str = "auto",
    weights: str = "auto",
    budget: int | None = None,
    memory: str = "speed",
    ram_budget: int | None = None,
    requantize: str = "float",
) -> str:
    """The pipeline `nncg-onnx` runs for `target` at an unroll level; `weights` (auto, embed, bin) says
    where plan-memory puts the weights; `budget` caps the statements of the unrolled program (None: no
    cap); `memory` (speed, balanced, min) or `ram_budget` (bytes) choose the layers lower runs in bands;
    `requantize` is lower's form of requantisation. Defaults are not written. Vector widths and
    registers are the target's, not the text's."""
    try:
        parse_unroll_level(unroll_level)
    except ValueError:
        raise NncgError(f"unroll level '{unroll_level}' is not auto, a depth >= 0 or none") from None
    plan = "plan-memory" if weights == "auto" else f"plan-memory{{weights={weights}}}"
    nest = AUTO_BUDGET if unroll_level == "auto" else NEST_BUDGET
    cap = f",budget={min(nest, budget)},total={budget}" if budget and unroll_level != "none" else ""
    if unroll_level == "auto" and not budget:
        cap = f",budget={nest}"
    vectors = bool(target.vector_widths)
    graph = f"{GRAPH_PIPELINE},winograd" + (",vectorize-pixels,cache-block" if vectors else "")
    loops = ",vectorize" if vectors else ""
    loops += f",register-block,unroll{{level={unroll_level}{cap}}},inline-constants,{plan}"
    lower_params = [f"budget={ram_budget}" if ram_budget else "" if memory == "speed" else f"memory={memory}"]
    lower_params.append("" if requantize == "float" else f"requantize={requantize}")
    lower_text = ",".join(p for p in lower_params if p)
    return f"{graph},lower{'{' + lower_text + '}' if lower_text else ''}{loops}"


__all__ = [
    "REGISTRY",
    "PassManager",
    "PassSpec",
    "default_pipeline",
    "format_pipeline",
    "parse_pipeline",
    "register",
]
