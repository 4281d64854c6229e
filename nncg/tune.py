"""Per-layer autotuning (`nncg-onnx --tune`), as in the paper: each layer is built in several code
variants, every variant is timed on the machine that runs the code, and each layer keeps its fastest.

Every pass that declares a Tunable (nncg/passes/manager.py) is a round, in pipeline order: today
winograd (direct or Winograd per 3x3 conv), vectorize-pixels (channels or pixels, timed as whole
models: it changes what the consumers read), register-block (block shapes) and unroll (budgets).
Within a round, variant i of every layer goes into build i of the whole model (a profile build, with
a timer around each layer); the builds run interleaved, batch after batch, and each layer keeps its
best time, so a busy machine slows all variants alike. The rounds time profile builds, whose timers
keep each layer a separate piece of code; last, the tuned pipeline's release build is timed against
the default pipeline's, interleaved, and the faster is kept (a compiler that schedules the layers
together differently could otherwise ship a tuned model slower than the untuned one). Choices are
cached by a signature built from the IR (nncg/ir/signature.py), the target and NNCG's own source (a
choice measured on other generated code is measured again), so a layer tuned before costs nothing.
The result is a pipeline whose tunable passes name each layer's choice: the C it gives is
reproducible without the cache."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from .backends import get_target
from .bench.benchmark import calibrate, interleaved_samples, paired_ratio, pinned
from .bench.harness import CompiledHarness
from .bench.progress import progress_bar
from .compiler import compile as compile_model
from .frontend import import_onnx
from .ir.signature import ir_signature, layer_signature
from .ir.target import Target
from .options import CompileOptions
from .passes import REGISTRY, PassManager, format_pipeline, parse_pipeline
from .passes.manager import Tunable
from .passes.per_layer import format_layer_map
from .passes.unroll import CODE_BUDGET
from .verify import find_c_compiler, random_inputs

CACHE_VERSION = 2


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
    """The default pipeline of `target` with every tunable pass's per-layer choices measured (with
    `cc`, run through `runner` if given), in pipeline order. Pass it to nncg.compile(pipeline=)."""
    progress = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    facts = get_target(target)
    pipeline = CompileOptions(weights=weights, code_budget=code_budget).pass_pipeline(facts)
    cc = find_c_compiler(cc)
    cache = cache or default_cache()
    known = _read_cache(cache)
    measure = _Measurer(model, target, cc, tuple(runner), input_shapes, batches, cpu, progress)
    where = f"{target}|{Path(cc).name}|{' '.join(runner)}|{_code_version()}"
    session = _Session(model, facts, input_shapes, where, known, measure)
    choices: dict[str, dict[str, str]] = {}
    for spec in parse_pipeline(pipeline):
        tunable = REGISTRY[spec.name].tunable
        if tunable is not None:
            choices[spec.name] = session.tune_pass(spec.name, tunable, with_layer_choices(pipeline, choices), progress)
    tuned = session.faster_as_a_whole(pipeline, with_layer_choices(pipeline, choices), progress)
    _write_cache(cache, known)
    return tuned


@dataclass
class _Session:
    """One --tune run: the model, the target, the cache and how builds are timed."""

    model: object
    target: Target
    input_shapes: object
    where: str  # target, compiler and runner: what cache keys are specific to
    known: dict
    measure: _Measurer

    def tune_pass(self, name: str, tunable: Tunable, pipeline: str, progress) -> dict[str, str]:
        """The pass's choice for each layer it offers choices for (the IR it gets from `pipeline`)."""
        ir = ir_before(self.model, pipeline, name, self.target, self.input_shapes)
        options = {
            layer: tuple(_text(tunable, v) for v in values)
            for layer, values in tunable.candidates(ir, self.target).items()
        }
        if not options:
            progress(f"tune: {name}: no layer to tune")
            return {}
        tuned = (
            self._whole_model(name, ir, options, pipeline)
            if tunable.whole_model
            else self._per_layer(name, ir, options, pipeline, progress)
        )
        for layer in options:
            progress(f"tune: {name}: {layer}: {tuned[layer]}")
        return tuned

    def _per_layer(self, name: str, ir, options: dict[str, tuple[str, ...]], pipeline: str, progress) -> dict[str, str]:
        """Each layer's fastest value; build i gives every layer its i-th value, timed per layer."""
        keys = {layer: _cache_key(self.where, name, layer_signature(ir, layer)) for layer in options}
        chosen = {layer: self.known[keys[layer]] for layer in options if self.known.get(keys[layer]) in options[layer]}
        todo = {layer: values for layer, values in options.items() if layer not in chosen}
        progress(f"tune: {name}: {len(options)} layers, {len(chosen)} cached, {len(todo)} to measure")
        if todo:
            chosen |= self.measure.best(name, todo, lambda pick: with_layer_choices(pipeline, {name: chosen | pick}))
            self.known.update({keys[layer]: chosen[layer] for layer in todo})
        return chosen

    def _whole_model(self, name: str, ir, options: dict[str, tuple[str, ...]], pipeline: str) -> dict[str, str]:
        """The fastest whole model among builds k = 0..N, where the first k layers take their last
        value and the rest their first (a layer's choice can depend on the ones before it)."""
        key = _cache_key(self.where, name, ir_signature(ir))
        cached = self.known.get(key)
        if isinstance(cached, dict) and set(cached) == set(options):
            return cached
        layers = list(options)
        builds = [
            {layer: options[layer][-1 if i < k else 0] for i, layer in enumerate(layers)}
            for k in range(len(layers) + 1)
        ]
        totals = self.measure.totals(name, [with_layer_choices(pipeline, {name: build}) for build in builds])
        self.known[key] = builds[min(range(len(builds)), key=totals.__getitem__)]
        return self.known[key]

    def faster_as_a_whole(self, default: str, tuned: str, progress) -> str:
        """`tuned`, unless its release build runs slower than the default pipeline's (cached)."""
        if tuned == default:
            return tuned
        graph = import_onnx(self.model, self.input_shapes)
        key = _cache_key(self.where, "whole-model", f"{ir_signature(graph)}|{default}|{tuned}")
        kept = self.known.get(key)
        if kept not in (default, tuned):
            ratio = self.measure.release_ratio(default, tuned)
            kept = tuned if ratio <= 1 else default
            verdict = "the tuned pipeline kept" if kept == tuned else "the default pipeline kept instead"
            progress(f"tune: whole model: the tuned release build takes {ratio:.3f}x the default's time: {verdict}")
            self.known[key] = kept
        return kept


def _code_version() -> str:
    """A digest of NNCG's Python source: what the generated code, and so a measured choice, depends on."""
    root = Path(__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def _text(tunable: Tunable, value: object) -> str:
    return value if isinstance(value, str) else tunable.format_value(value)


# ---------------------------------------------------------------------------- what to tune


def tuning_candidates(model, pipeline: str, pass_name: str, target: Target, input_shapes=None) -> dict[str, tuple]:
    """Layer -> the values --tune would time for the tunable pass `pass_name` in `pipeline`."""
    tunable = REGISTRY[pass_name].tunable
    return tunable.candidates(ir_before(model, pipeline, pass_name, target, input_shapes), target)


def ir_before(model, pipeline: str, pass_name: str, target: Target, input_shapes=None):
    """The IR the pipeline gives the pass `pass_name` (a graph or a loop-nest program)."""
    specs = parse_pipeline(pipeline)
    cut = next(i for i, spec in enumerate(specs) if spec.name == pass_name)
    return PassManager(specs[:cut], target, finish=False).run(import_onnx(model, input_shapes))


def with_layer_choices(pipeline: str, choices: dict[str, dict[str, object]]) -> str:
    """The pipeline with each named pass's per-layer choices as its `layers` parameter (values as
    the pass spells them, or raw values its Tunable formats)."""
    specs = []
    for spec in parse_pipeline(pipeline):
        params = dict(spec.params)
        layers = choices.get(spec.name)
        if layers:
            tunable = REGISTRY[spec.name].tunable
            params["layers"] = format_layer_map({k: _text(tunable, v) for k, v in layers.items()})
        specs.append(replace(spec, params=tuple(params.items())))
    return format_pipeline(specs)


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

    def totals(self, what: str, pipelines: list[str]) -> list[float]:
        """Seconds per inference of each build: the sum of its layers' best times."""
        self.progress(f"tune: {what}: {len(pipelines)} builds of the model")
        return [sum(times.values()) for times in self._layer_times(pipelines)]

    def release_ratio(self, default: str, tuned: str) -> float:
        """The tuned release build's time over the default's: the median of per-batch ratios, the two
        run interleaved as --benchmark runs NNCG and onnxruntime."""
        self.progress("tune: whole model: timing the tuned and the default release build")
        with self._built([default, tuned], profile=False) as (default_build, tuned_build), pinned(self.cpu):
            samples = interleaved_samples({"default": default_build.run, "tuned": tuned_build.run}, self.batches, 0.01)
        return paired_ratio(samples["tuned"], samples["default"])

    def _layer_times(self, pipelines: list[str]) -> list[dict[str, float]]:
        """Best seconds per call of each layer in each build, builds run in turn."""
        with self._built(pipelines, profile=True) as harnesses, pinned(self.cpu):
            return self._interleaved(harnesses)

    @contextmanager
    def _built(self, pipelines: list[str], profile: bool) -> Iterator[list[CompiledHarness]]:
        """A harness per pipeline, built in parallel and fed the same inputs; closed on leaving."""
        with tempfile.TemporaryDirectory(prefix="nncg-tune-") as tmp:
            compiled = [
                compile_model(self.model, self.target, pipeline=p, input_shapes=self.input_shapes, profile=profile)
                for p in pipelines
            ]
            inputs = random_inputs(compiled[0].inputs, seed=0)

            def build(i):
                workdir = Path(tmp) / str(i)
                workdir.mkdir()
                return CompiledHarness(compiled[i], workdir, self.cc, inputs, profile=profile, runner=self.runner)

            harnesses: list[CompiledHarness] = []
            try:
                with (
                    ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool,
                    progress_bar(len(pipelines), "tune: building") as bar,
                ):
                    for harness in pool.map(build, range(len(pipelines))):
                        harnesses.append(harness)
                        bar.update()
                yield harnesses
            finally:
                for harness in harnesses:
                    harness.close()

    def _interleaved(self, harnesses) -> list[dict[str, float]]:
        calls = [calibrate(h.run, 0.002) for h in harnesses]
        best: list[dict[str, float]] = [{} for _ in harnesses]
        for h in harnesses:
            h.layer_seconds()  # drop what calibration accumulated
        with progress_bar(self.batches, f"tune: {len(harnesses)} builds, batches") as bar:
            for _ in range(self.batches):
                for i, h in enumerate(harnesses):
                    h.run(calls[i])
                    for layer, seconds in h.layer_seconds():
                        best[i][layer] = min(best[i].get(layer, float("inf")), seconds / calls[i])
                bar.update()
        return best


# ---------------------------------------------------------------------------- cache


def _cache_key(where: str, pass_name: str, signature: str) -> str:
    return hashlib.sha256(f"{CACHE_VERSION}|{where}|{pass_name}|{signature}".encode()).hexdigest()


def _read_cache(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    entries = data.get("entries", {}) if isinstance(data, dict) else {}
    return {k: v for k, v in entries.items() if _valid_entry(v)}


def _valid_entry(entry) -> bool:
    """A layer's choice as its pass spells it, or a whole-model round's choices by layer."""
    if isinstance(entry, dict):
        return all(isinstance(k, str) and isinstance(v, str) for k, v in entry.items())
    return isinstance(entry, str)


def _write_cache(path: Path, entries: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temp = tempfile.mkstemp(prefix=".tune.", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        json.dump({"version": CACHE_VERSION, "entries": entries}, f, indent=1, sort_keys=True)
    os.replace(temp, path)
