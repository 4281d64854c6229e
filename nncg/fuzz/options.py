"""Random compile options for a fuzz case: target, unroll level, code budget, where the weights go,
and pipelines with per-layer choices as `--tune` writes them (Winograd, pixel vectorisation, cache
blocks, block shapes, unroll budgets), mostly legal for the layer, now and then not (the pass must refuse those)."""

from __future__ import annotations

import shlex
import shutil
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
import onnx

from ..backends import get_target
from ..errors import NncgError
from ..ir.applicability import (
    cache_block_applies,
    depthwise_blocks_apply,
    group_panels_apply,
    panel_packing_applies,
)
from ..options import CompileOptions
from ..passes.register_block import block_candidates, blockable
from ..passes.unroll import CODE_BUDGET
from ..tune import ir_before, tuning_candidates, with_layer_choices
from .draw import Draw

# cc, flags, runner: plain neon on a CPU without the dot-product extension, neon-dotprod on one with it
CROSS = {
    "neon": ("aarch64-linux-gnu-gcc", ("-static",), ("qemu-aarch64", "-cpu", "cortex-a53")),
    "neon-dotprod": ("aarch64-linux-gnu-gcc", ("-static",), ("qemu-aarch64", "-cpu", "max")),
}
UNROLLS = ("auto", "auto", "0", "1", "2", "none")
BUDGETS = (CODE_BUDGET, 256, 1024, 4096, 64, None)  # None: no cap (--code-budget 0)
LAYER_BUDGETS = (64, 0, 16, 256, 1024)
UNCAPPED_MAX_ELEMENTS = 4096  # no code budget with full unrolling only on small models


@dataclass(frozen=True)
class Options:
    """One way to compile a model: what nncg.compile gets, plus whether to build under sanitizers."""

    target: str = "ansi-c"
    unroll: str = "auto"
    code_budget: int | None = CODE_BUDGET
    weights: str = "auto"
    layers: dict[str, dict[str, Any]] = field(default_factory=dict)  # pass -> {layer: choice}
    halos: bool = False
    sanitize: bool = False

    @property
    def default_layers(self) -> bool:
        return not any(self.layers.values()) and not self.halos

    def pipeline(self) -> str | None:
        """The pass pipeline with the per-layer choices; None for the default one."""
        if self.default_layers:
            return None
        choices = {name: dict(layers) for name, layers in self.layers.items()}
        if "register-block" in choices:
            choices["register-block"] = {n: tuple(shape) for n, shape in choices["register-block"].items()}
        text = with_layer_choices(_base(self), choices)
        return text.replace(",lower,", ",lower{halos=true},") if self.halos else text

    def compile_kwargs(self) -> dict[str, Any]:
        pipeline = self.pipeline()
        if pipeline:  # it records the unroll level, weights and code budget
            return {"target": self.target, "pipeline": pipeline}
        return {"target": self.target, "unroll": self.unroll, "weights": self.weights, "code_budget": self.code_budget}

    def command(self, model_path: str = "model.onnx") -> str:
        """The nncg-onnx command line that compiles and verifies the model with these options."""
        args = ["nncg-onnx", model_path, "--target", self.target, "--unroll", self.unroll]
        args += ["--code-budget", str(self.code_budget or 0), "--weights", self.weights]
        pipeline = self.pipeline()
        args += ["--pipeline", pipeline] if pipeline else []
        return shlex.join([*args, "-o", "out", "--verify"])

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(data: dict[str, Any]) -> Options:
        return Options(**data)

    def simpler(self) -> list[Options]:
        """Options one step closer to the defaults (for the shrinker), most drastic first."""
        base = Options()
        out = []
        for key in ("layers", "halos", "sanitize", "code_budget", "unroll", "weights", "target"):
            if getattr(self, key) != getattr(base, key):
                out.append(replace(self, **{key: getattr(base, key)}))
        for pass_name, choices in self.layers.items():
            for layer in choices:
                fewer = {
                    p: {k: v for k, v in c.items() if (p, k) != (pass_name, layer)} for p, c in self.layers.items()
                }
                out.append(replace(self, layers={p: c for p, c in fewer.items() if c}))
        return out


def cross_available(target: str) -> bool:
    cc, _, runner = CROSS[target]
    return shutil.which(cc) is not None and shutil.which(runner[0]) is not None


def random_options(
    d: Draw, model: onnx.ModelProto, targets: list[str], sanitize_fraction: float, elements: int
) -> Options:
    """Options for one case; `elements` is the model's largest value (full unrolling without a code
    budget is only drawn for small ones)."""
    target = d.pick(targets)
    unroll = d.pick(UNROLLS)
    # No cap at a paper level unrolls whole layers into straight-line code: MBs of C is then what the
    # user asked for, not a bug, so an uncapped level is drawn only for tiny models.
    uncapped = unroll in ("auto", "none") or (elements <= UNCAPPED_MAX_ELEMENTS // 8 and unroll != "0")
    budgets = [b for b in BUDGETS if b is not None or uncapped]
    options = Options(
        target=target,
        unroll=unroll,
        code_budget=d.pick(budgets),
        weights=d.pick(("auto", "auto", "embed", "bin")),
        halos=d.chance(0.15),
        sanitize=target not in CROSS and d.chance(sanitize_fraction),
    )
    if d.chance(0.4):
        options = replace(options, layers=_layer_choices(d, model, options))
    return options


def _layer_choices(d: Draw, model: onnx.ModelProto, options: Options) -> dict[str, dict[str, Any]]:
    """Per-layer choices drawn from what --tune would measure (each legal), with a small chance of a
    choice the pass must refuse. The IR is imported and run up to each pass, as --tune does."""
    choices: dict[str, dict[str, Any]] = {}
    try:
        target = get_target(options.target)
        names = list(tuning_candidates(model, _base(options), "winograd", target))
        if names:
            choices["winograd"] = {n: d.chance(0.5) for n in names}
        pixels = _pixel_candidates(model, replace(options, layers=choices))
        if pixels:
            taken = d.int(0, len(pixels))
            choices["vectorize-pixels"] = {
                n: i < taken if d.chance(0.85) else d.chance(0.5) for i, n in enumerate(pixels)
            }
        blocked = _cache_block_choices(d, model, replace(options, layers=choices))
        if blocked:
            choices["cache-block"] = blocked
        registers = target.registers
        pipeline = replace(options, layers=choices).pipeline() or _base(options)
        layers = blockable(ir_before(model, pipeline, "register-block", target))
        blocks = {n: list(_block_choice(d, shape, registers)) for n, shape in layers.items() if d.chance(0.7)}
        budgets = {n: d.pick(LAYER_BUDGETS) for n in layers if d.chance(0.5)}
    except NncgError:
        return {}
    choices |= {k: v for k, v in (("register-block", blocks), ("unroll", budgets)) if v}
    return choices


def _base(options: Options) -> str:
    chosen = CompileOptions(options.unroll, options.weights, options.code_budget)
    return chosen.pass_pipeline(get_target(options.target))


def _pixel_candidates(model: onnx.ModelProto, options: Options) -> list[str]:
    pipeline = options.pipeline() or _base(options)
    if "vectorize-pixels" not in pipeline:
        return []
    return list(tuning_candidates(model, pipeline, "vectorize-pixels", get_target(options.target)))


def _cache_block_choices(d: Draw, model: onnx.ModelProto, options: Options) -> dict[str, tuple[int, int] | str]:
    """Panels and input-channel blocks, or a depthwise Conv's channel blocks, for some of the layers
    cache-block applies to: any legal shape, not only what --tune times (fuzz models are small: the
    cost model would block none of them). A grouped Conv, which the cost model always blocks, one
    group a panel, is now and then left unblocked (off)."""
    pipeline = options.pipeline() or _base(options)
    if "cache-block" not in pipeline:
        return {}
    graph = ir_before(model, pipeline, "cache-block", get_target(options.target))
    out = {}
    for node in graph.nodes:
        grouped = group_panels_apply(graph, node)
        conv = grouped or cache_block_applies(graph, node)
        depthwise = depthwise_blocks_apply(graph, node)
        if not (conv or depthwise or panel_packing_applies(graph, node)) or not d.chance(0.5):
            continue
        if depthwise:  # channels a block, the last block the rest
            out[node.name] = (d.int(1, graph.shape(node.outputs[0])[1]), 0)
            continue
        if grouped and d.chance(0.3):
            out[node.name] = "off"
            continue
        columns = graph.shape(node.outputs[0])[1 if conv else -1]
        c_in = graph.shape(node.inputs[1])[1]  # of a group
        block = d.pick([b for b in range(1, c_in + 1) if c_in % b == 0]) if conv else 0
        panel = columns // node.attrs.group if grouped else d.int(1, columns)  # a grouped Conv's panel: its group
        out[node.name] = (panel, block)
    return out


def _block_choice(d: Draw, shape: tuple[int, int], registers: int) -> tuple[int, int]:
    """A block shape --tune would time, or now and then another one that fits the register file
    (pixels may exceed the loop, channels the vectors there are: the pass must cope)."""
    if d.chance(0.85):
        return d.pick(block_candidates(shape, registers))
    extent, vectors = shape
    channels = d.int(1, vectors + 1)
    return d.int(1, max(1, min(extent + 2, registers // channels))), channels


def options_rng(seed: int, index: int) -> Draw:
    """The options' own random stream, apart from the graph's (so shrinking one keeps the other)."""
    return Draw(np.random.default_rng([seed, index, 1]), 0)
