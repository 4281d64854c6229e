"""Per-layer autotuning (`nncg-onnx --tune`), as in the paper: each layer is built in several code
variants, every variant is timed on the machine that runs the code, and each layer keeps its fastest.

Variants are measured together: variant i of every layer goes into build i of the whole model (a
profile build, with a timer around each layer); the builds run interleaved, batch after batch, and
each layer keeps its best time, so a busy machine slows all variants alike. Four rounds: the
algorithm of each 3x3 convolution (direct or Winograd), the vectorisation axis of the layers that
can vectorise over output pixels (timed as whole models: it changes what their consumers read),
then block shapes (pixels x channel vectors) of the register-blocked layers at the default unroll
budget, then unroll budgets with the best shapes. Choices are cached by layer signature and target,
so a layer tuned before costs nothing. The result is a pipeline whose winograd, vectorize-pixels,
register-block and unroll passes name each layer's choice: the C it gives is reproducible without
the cache."""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from .backends import get_target
from .bench.benchmark import calibrate, pinned
from .bench.harness import CompiledHarness
from .compiler import compile as compile_model
from .frontend import import_onnx
from .ir.loops import Program
from .ir.target import Target
from .ir.text import program_to_text
from .options import CompileOptions
from .passes import PassManager, format_pipeline, parse_pipeline
from .passes.per_layer import format_layer_map
from .passes.register_block import block_shape, choose_blocks, format_block, parse_block
from .passes.unroll import AUTO_BUDGET, CODE_BUDGET, parse_budget
from .passes.vectorize_pixels import pixel_candidates
from .passes.winograd import winograd_candidates
from .verify import find_c_compiler, random_inputs

UNROLL_BUDGETS = (AUTO_BUDGET, 0, 16, 256)  # the default first: it is the reference
PIXEL_BLOCKS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24)
CACHE_VERSION = 1


def default_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "nncg" / "tune.json"


def tune(
    model,
    target: str = "ssse3",
    *,
    cc: str | None = None,
    runner: Sequence[str] = (),
    cache: Path | None = None,
    input_shapes=None,
    weights: str = "auto",
    code_budget: int | None = CODE_BUDGET,
    batches: int = 15,
    cpu: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> str:
    """The default pipeline of `target` with each 3x3 conv's algorithm and each register-blocked
    layer's block shape and unroll budget measured (with `cc`, run through `runner` if given). Pass it
    to nncg.compile(pipeline=)."""
    progress = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    facts = get_target(target)
    base = CompileOptions(weights=weights, code_budget=code_budget).pass_pipeline(facts)
    cc = find_c_compiler(cc)
    where = f"{target}|{Path(cc).name}|{' '.join(runner)}"
    cache = cache or default_cache()
    known = _read_cache(cache)
    measure = _Measurer(model, target, cc, tuple(runner), input_shapes, batches, cpu, progress)
    algorithms = _tune_algorithms(model, base, facts, input_shapes, where, known, measure, progress)
    base = with_layer_choices(base, {}, {}, algorithms)
    pixels = _tune_pixel_axis(model, base, facts, input_shapes, where, known, measure, progress)
    base = with_layer_choices(base, {}, {}, pixels=pixels)
    layers = tunable_layers(model, base, facts, input_shapes)
    if not layers:
        progress("tune: no register-blocked layer to tune")
        _write_cache(cache, known)
        return base
    keys = {name: _cache_key(where, signature) for name, (_, signature) in layers.items()}
    todo = {name: shape for name, (shape, _) in layers.items() if keys[name] not in known}
    blocks = {name: parse_block(known[keys[name]]["block"]) for name in layers if name not in todo}
    budgets = {name: known[keys[name]]["unroll"] for name in layers if name not in todo}
    progress(f"tune: {len(layers)} layers, {len(layers) - len(todo)} cached, {len(todo)} to measure")
    if todo:
        shapes = {name: block_candidates(shape, facts.registers) for name, shape in todo.items()}
        blocks |= measure.best("block shape", shapes, lambda pick: with_layer_choices(base, blocks | pick, budgets))
        unrolls = {name: UNROLL_BUDGETS for name in todo}
        budgets |= measure.best("unroll budget", unrolls, lambda pick: with_layer_choices(base, blocks, budgets | pick))
        for name in todo:
            known[keys[name]] = {"block": format_block(blocks[name]), "unroll": budgets[name]}
    _write_cache(cache, known)
    for name in sorted(layers):
        progress(f"tune: {name}: {format_block(blocks[name])} block, unroll budget {budgets[name]}")
    return with_layer_choices(base, blocks, budgets)


def _tune_algorithms(model, base, target, input_shapes, where, known, measure, progress) -> dict[str, bool]:
    """Winograd or not for each layer it applies to: measured (both variants in two builds) or
    from the cache, keyed by the layer's direct loop nest."""
    layers = algorithm_layers(model, base, target, input_shapes)
    keys = {name: _cache_key(where + "|winograd", signature) for name, signature in layers.items()}
    chosen = {name: known[keys[name]]["winograd"] for name in layers if keys[name] in known}
    todo = {name: (False, True) for name in layers if name not in chosen}
    if todo:
        progress(f"tune: direct or Winograd for {', '.join(sorted(todo))}")
        chosen |= measure.best("algorithm", todo, lambda pick: with_layer_choices(base, {}, {}, chosen | pick))
        for name in todo:
            known[keys[name]] = {"winograd": chosen[name]}
    for name in sorted(layers):
        progress(f"tune: {name}: {'Winograd' if chosen[name] else 'direct'}")
    return chosen


def _tune_pixel_axis(model, base, target, input_shapes, where, known, measure, progress) -> dict[str, bool]:
    """Which layers vectorise over output pixels. A layer's choice changes its consumers' time too
    (they read a planar tensor), and a layer can take the pixel axis only if its input is planar, so
    the builds are: the first k candidates on, k = 0..N; the fastest whole model wins. Cached by the
    network's loop nests with every candidate off."""
    if all(spec.name != "vectorize-pixels" for spec in parse_pipeline(base)):
        return {}  # a target without vectors
    names = pixel_candidates(ir_before(model, base, "vectorize-pixels", target, input_shapes))
    if not names:
        return {}
    off = with_layer_choices(base, {}, {}, pixels=dict.fromkeys(names, False))
    program = ir_before(model, off, "register-block", target, input_shapes)
    key = _cache_key(where + "|pixels", "\n".join(layer_signature(program, k) for k in program.kernels))
    if key in known:
        chosen = {name: name in known[key]["pixels"] for name in names}
    else:
        progress(f"tune: vectorise over pixels or channels: {', '.join(names)}")
        builds = [{name: i < k for i, name in enumerate(names)} for k in range(len(names) + 1)]
        totals = measure.totals([with_layer_choices(base, {}, {}, pixels=b) for b in builds])
        chosen = builds[min(range(len(builds)), key=totals.__getitem__)]
        known[key] = {"pixels": sorted(name for name, on in chosen.items() if on)}
    for name in names:
        progress(f"tune: {name}: vectorised over {'pixels' if chosen[name] else 'channels'}")
    return chosen


# ---------------------------------------------------------------------------- what to tune


def algorithm_layers(model, pipeline: str, target: Target, input_shapes=None) -> dict[str, str]:
    """Layer name -> signature of its direct loop nest, for every layer Winograd applies to (whose
    kernel carries the node's name)."""
    names = winograd_candidates(ir_before(model, pipeline, "winograd", target, input_shapes))
    if not names:
        return {}
    direct = with_layer_choices(pipeline, {}, {}, dict.fromkeys(names, False))
    program = ir_before(model, direct, "register-block", target, input_shapes)
    return _signatures(program, names)


def _signatures(program: Program, names: list[str]) -> dict[str, str]:
    """Layer name -> its loop nest's signature; every layer a round tunes has a kernel of its name."""
    kernels = {k.name: k for k in program.kernels}
    missing = [name for name in names if name not in kernels]
    if missing:
        raise RuntimeError(f"tune: no kernel for the layers {missing}: graph and kernel names disagree")
    return {name: layer_signature(program, kernels[name]) for name in names}


def tunable_layers(model, pipeline: str, target: Target, input_shapes=None) -> dict[str, tuple[tuple[int, int], str]]:
    """Layer name -> (its block_shape, a signature of its loop nest) for every layer the
    register-block pass would block, from the IR just before that pass."""
    program = ir_before(model, pipeline, "register-block", target, input_shapes)
    out = {}
    for kernel in program.kernels:
        shape = block_shape(kernel.body)
        if shape is not None:
            out[kernel.name] = (shape, layer_signature(program, kernel))
    return out


def ir_before(model, pipeline: str, pass_name: str, target: Target, input_shapes=None):
    """The IR the pipeline gives the pass `pass_name` (a graph or a loop-nest program)."""
    specs = parse_pipeline(pipeline)
    cut = next(i for i, spec in enumerate(specs) if spec.name == pass_name)
    return PassManager(specs[:cut], target, finish=False).run(import_onnx(model, input_shapes))


def layer_signature(program: Program, kernel) -> str:
    """The kernel's loop nest as text with buffers named by role and size, so the same layer in
    another model (or under another name) has the same signature."""
    single = replace(program, kernels=(kernel,), buffers=program.buffers)
    text = program_to_text(single).split(f"kernel {kernel.name} ", 1)[1]
    for buf in program.buffers:
        text = re.sub(rf"\b{re.escape(buf.name)}\b", f"{buf.role}{buf.size}", text)
    return text


def block_candidates(shape: tuple[int, int], registers: int) -> list[tuple[int, int]]:
    """Block shapes worth timing: the cost model's first, then pixel counts up to a register file
    of accumulators, with all channel vectors of a pixel (or 2, 3, 4 of them when there are many)."""
    extent, vectors = shape
    first = choose_blocks(shape, registers)
    channel_options = [vectors] if vectors <= 5 else [2, 3, 4]
    out = [first]
    for channels in channel_options:
        for pixels in PIXEL_BLOCKS:
            if pixels <= extent and pixels * channels <= registers - 2 and (pixels, channels) not in out:
                out.append((pixels, channels))
    return out


def with_layer_choices(
    pipeline: str,
    blocks: dict[str, tuple[int, int]],
    budgets: dict[str, int],
    algorithms: dict[str, bool] | None = None,
    pixels: dict[str, bool] | None = None,
) -> str:
    """The pipeline with register-block's, unroll's (and winograd's, vectorize-pixels') per-layer
    choices set."""
    specs = []
    for spec in parse_pipeline(pipeline):
        params = dict(spec.params)
        if spec.name == "winograd" and algorithms:
            params["layers"] = format_layer_map(algorithms, _format_bool)
        if spec.name == "vectorize-pixels" and pixels:
            params["layers"] = format_layer_map(pixels, _format_bool)
        if spec.name == "register-block" and blocks:
            params["layers"] = format_layer_map(blocks, format_block)
        if spec.name == "unroll" and budgets:
            params["layers"] = format_layer_map(budgets)
        specs.append(replace(spec, params=tuple(params.items())))
    return format_pipeline(specs)


def _format_bool(on: bool) -> str:
    return "true" if on else "false"


# ---------------------------------------------------------------------------- measuring


class _Measurer:
    def __init__(self, model, target, cc, runner, input_shapes, batches, cpu, progress):
        self.model, self.target, self.cc, self.runner = model, target, cc, runner
        self.input_shapes, self.batches, self.cpu, self.progress = input_shapes, batches, cpu, progress

    def best(self, what: str, candidates: dict[str, Sequence], pipeline_for: Callable[[dict], str]) -> dict:
        """For each layer, its candidate with the lowest time. Build i gives every layer its i-th
        candidate (its last when it has fewer); pipeline_for(choices) is the pipeline of a build."""
        rounds = max(len(c) for c in candidates.values())
        picks = [{name: c[min(i, len(c) - 1)] for name, c in candidates.items()} for i in range(rounds)]
        self.progress(f"tune: {what}: {rounds} builds of the model")
        times = self._layer_times([pipeline_for(pick) for pick in picks])
        best = {}
        for name, options in candidates.items():
            scored = [(times[i].get(name, float("inf")), i) for i in range(len(options))]
            best[name] = options[min(scored)[1]]
        return best

    def totals(self, pipelines: list[str]) -> list[float]:
        """Seconds per inference of each build: the sum of its layers' best times."""
        self.progress(f"tune: {len(pipelines)} builds of the model")
        return [sum(times.values()) for times in self._layer_times(pipelines)]

    def _layer_times(self, pipelines: list[str]) -> list[dict[str, float]]:
        """Best seconds per call of each layer in each build, builds run in turn."""
        with tempfile.TemporaryDirectory(prefix="nncg-tune-") as tmp:
            compiled = [
                compile_model(self.model, self.target, pipeline=p, input_shapes=self.input_shapes, profile=True)
                for p in pipelines
            ]
            inputs = random_inputs(compiled[0].inputs, seed=0)

            def build(i):
                workdir = Path(tmp) / str(i)
                workdir.mkdir()
                return CompiledHarness(compiled[i], workdir, self.cc, inputs, profile=True, runner=self.runner)

            with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
                harnesses = list(pool.map(build, range(len(pipelines))))
            try:
                with pinned(self.cpu):
                    return self._interleaved(harnesses)
            finally:
                for harness in harnesses:
                    harness.close()

    def _interleaved(self, harnesses) -> list[dict[str, float]]:
        calls = [calibrate(h.run, 0.002) for h in harnesses]
        best: list[dict[str, float]] = [{} for _ in harnesses]
        for h in harnesses:
            h.layer_seconds()  # drop what calibration accumulated
        for batch in range(self.batches):
            for i, h in enumerate(harnesses):
                h.run(calls[i])
                for layer, seconds in h.layer_seconds():
                    best[i][layer] = min(best[i].get(layer, float("inf")), seconds / calls[i])
            if (batch + 1) % 5 == 0 or batch + 1 == self.batches:
                self.progress(f"tune:   {batch + 1}/{self.batches} batches")
        return best


# ---------------------------------------------------------------------------- cache


def _cache_key(where: str, signature: str) -> str:
    return hashlib.sha256(f"{CACHE_VERSION}|{where}|{signature}".encode()).hexdigest()


def _read_cache(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    entries = data.get("entries", {}) if isinstance(data, dict) else {}
    return {k: v for k, v in entries.items() if _valid_entry(v)}


def _valid_entry(entry) -> bool:
    if isinstance(entry, dict) and set(entry) == {"winograd"}:
        return isinstance(entry["winograd"], bool)
    if isinstance(entry, dict) and set(entry) == {"pixels"}:
        return isinstance(entry["pixels"], list) and all(isinstance(name, str) for name in entry["pixels"])
    try:
        parse_block(entry["block"])
        parse_budget(str(entry["unroll"]))
    except (KeyError, TypeError, ValueError):
        return False
    return True


def _write_cache(path: Path, entries: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temp = tempfile.mkstemp(prefix=".tune.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump({"version": CACHE_VERSION, "entries": entries}, f, indent=1, sort_keys=True)
    os.replace(temp, path)
